"""Strict JSON parsing and request validation, as run in a body-parser process.

This module imports only the standard library and pydantic: it is what a parser process loads
(see service.http.json_body), and it must not drag the web stack into it.
"""
from __future__ import annotations

import importlib
import json
import os
import re
import threading
import time
from typing import Any, Optional, TypeVar

from pydantic import BaseModel, ValidationError

from greyfit.service.http.json_shape import ListLimits, ShapeError, check_shape

M = TypeVar("M", bound=BaseModel)

# errors listed in one answer at most; the rest are counted
MAX_ERRORS = 50


class _DuplicateKey(ValueError):
    pass


def _refuse_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def loads_strict(body: bytes | str) -> Any:
    """json.loads that raises JSONDecodeError on a duplicate key (FastAPI reports it as a 422).

    A key twice in one object is an error: json.loads would silently keep the last value, so a
    request could carry two different `experiments` and the reader of the JSON would see the first.
    """
    try:
        return json.loads(body, object_pairs_hook=_refuse_duplicates)
    except _DuplicateKey as exc:
        text = body if isinstance(body, str) else body.decode("utf-8", "replace")   # (the CLI reads text)
        key = str(exc)
        # point at the second occurrence of the key (the first one that is a key, not a value)
        hits = [m.start() for m in re.finditer(re.escape(json.dumps(key)) + r"\s*:", text)]
        raise json.JSONDecodeError(f"duplicate key {key!r} in one object: send each key once",
                                   text, hits[1] if len(hits) > 1 else 0) from None


# an array of plain numbers (no key can be inside one): what most of a large body is
_NUMBER_ARRAY = re.compile(rb"\[[-+0-9.eE,\s]*\]")


def has_duplicate_keys(body: bytes) -> bool:
    """Whether loads_strict would find a key twice in one object (or cannot tell).

    It looks at the body with its arrays of numbers emptied: the keys are all there, and parsing
    the numbers (most of the time of json.loads on a large body) is pydantic's job."""
    try:
        loads_strict(_NUMBER_ARRAY.sub(b"[]", body))
    except (ValueError, RecursionError):     # JSONDecodeError (a duplicate) is a ValueError
        return True
    return False


def validate_json(model: type[BaseModel], body: bytes | str) -> tuple[Optional[BaseModel], Optional[list[dict]]]:
    """(instance, None) for a valid body, (None, errors) for one pydantic's JSON parser read but that
    is invalid, (None, None) when that parser could not read it (json.loads may: it is the judge).

    Strict: a string is not a number and a boolean is not a number ("500", true for a float), as
    in the JSON schema the service publishes; an integer is a number. Validating the JSON text
    (not the parsed dict) is what makes strict mode right for JSON: enum values, tuples from
    arrays and the like are accepted there as JSON has them. The errors leave out their input: it
    may be megabytes, and an answer never shows it."""
    try:
        return model.model_validate_json(body, strict=True), None
    except ValidationError as exc:
        errors = exc.errors(include_url=False, include_input=False, include_context=False)
        if any(e["type"] == "json_invalid" for e in errors):
            return None, None
        return None, [{"type": e["type"], "loc": tuple(e["loc"]), "msg": e["msg"]} for e in errors]
    except (ValueError, RecursionError):
        return None, None


def validate_strict(model: type[M], data: Any) -> M:
    """`model` validated from parsed JSON (a dict) as strictly as the service validates a body:
    for the command line, which reads files with loads_strict. Raises pydantic's ValidationError."""
    return model.model_validate_json(json.dumps(data), strict=True)


def warm_up(modules: list[str]) -> None:
    """Import the body models' modules, so that the first large body does not wait for them."""
    for name in modules:
        importlib.import_module(name)


def parse_and_validate(model: Optional[type[BaseModel]], body: bytes,
                       limits: ListLimits = ListLimits()) -> tuple[str, Any]:
    """Parse a body and validate it as `model`; never raises, the outcome says what happened.

    ("ok", (instance or, without a model, the parsed JSON; request_texts)) | ("json_invalid", (message, position))
    | ("invalid", pydantic errors without their input, at most MAX_ERRORS and a count of the rest)
    | ("limit", (location, message)): a list or an object beyond `limits` (service.http.json_shape), found
    before anything was validated | ("unparsable", None): not UTF-8 JSON or nested too deeply to parse
    (FastAPI answers 400) | ("too_deep", None): nested too deeply to validate (answered 422, as in the
    web process).

    `request_texts`: for a job body (a model with a list `requests`), the JSON text of each request,
    made here so that the web process only stores it (serialising holds the interpreter lock too).
    """
    shape = shape_of(model, body, limits)
    if shape[0] != "ok":
        return shape
    instance, errors = validate_json(model, body) if model is not None else (None, None)
    if instance is not None and not has_duplicate_keys(body):
        return "ok", (instance, _request_texts(instance))
    try:
        data = loads_strict(body)
    except json.JSONDecodeError as exc:
        return "json_invalid", (exc.msg, exc.pos)
    except (ValueError, RecursionError):    # UnicodeDecodeError is a ValueError
        return "unparsable", None
    if model is None:
        return "ok", (data, None)
    if errors is not None:
        return "invalid", capped(errors, shape[1])
    try:   # pydantic's parser could not read what json.loads did: validated as before
        instance = model.model_validate(data)
    except ValidationError as exc:
        # the input of each error is left out: it may be megabytes, and the answer never shows it
        return "invalid", capped([{"type": e["type"], "loc": tuple(e["loc"]), "msg": e["msg"]} for e in
                                  exc.errors(include_url=False, include_input=False, include_context=False)],
                                 shape[1])
    except RecursionError:
        return "too_deep", None
    return "ok", (instance, _request_texts(instance))


def shape_of(model: Optional[type[BaseModel]], body: bytes, limits: ListLimits) -> tuple[str, Any]:
    """("ok", the number of requests or None), or the outcome of a body refused by its shape
    (service.http.json_shape): ("limit", (location, message)) or ("invalid", [the unknown field's error])."""
    if model is None:
        return "ok", None
    try:
        return "ok", check_shape(model, body, limits)
    except ShapeError as exc:
        if exc.kind == "unknown":
            return "invalid", [{"type": "extra_forbidden", "loc": exc.loc, "msg": "Extra inputs are not permitted"}]
        return "limit", (exc.loc, exc.msg)


def capped(errors: list[dict], requests: Optional[int] = None) -> list[dict]:
    """At most MAX_ERRORS errors, then one that counts the rest. A job body's requests are validated up
    to the first invalid one (`fail_fast`): the last entry says how many were not checked."""
    if any(e.get("type") in ("too_many_errors", "not_checked") for e in errors):
        return errors    # capped already (in a parser process)
    out = errors[:MAX_ERRORS]
    if len(errors) > MAX_ERRORS:
        out.append({"type": "too_many_errors", "loc": (), "msg": f"{len(errors) - MAX_ERRORS} more errors "
                    "not listed: fix these and send the body again"})
    failed = [e["loc"][1] for e in errors if tuple(e["loc"][:1]) == ("requests",) and len(e["loc"]) > 1
              and isinstance(e["loc"][1], int)]
    if requests is not None and failed and requests > max(failed) + 1:
        rest = requests - max(failed) - 1
        out.append({"type": "not_checked", "loc": ("requests",), "msg": f"the {rest} requests after "
                    f"requests[{max(failed)}] were not checked (validation stops at the first invalid one)"})
    return out


def _request_texts(instance: BaseModel) -> Optional[list[str]]:
    requests = getattr(instance, "requests", None)
    return [r.model_dump_json(exclude_unset=True) for r in requests] if isinstance(requests, list) and \
        all(isinstance(r, BaseModel) for r in requests) else None


def exit_with_parent(parent_pid: int) -> None:
    """Initializer of a parser process: end it when the server is gone (even after kill -9).

    Pool processes wait on a queue whose writing end they hold themselves, so they would not
    notice on their own."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
