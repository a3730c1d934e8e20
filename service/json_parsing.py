"""Strict JSON parsing and request validation, as run in a body-parser process.

This module imports only the standard library and pydantic: it is what a parser process loads
(see service.json_body), and it must not drag the web stack into it.
"""
from __future__ import annotations

import json
import os
import re
import threading
import time
from typing import Any, Optional

from pydantic import BaseModel, ValidationError


class _DuplicateKey(ValueError):
    pass


def _refuse_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def loads_strict(body: bytes) -> Any:
    """json.loads that raises JSONDecodeError on a duplicate key (FastAPI reports it as a 422).

    A key twice in one object is an error: json.loads would silently keep the last value, so a
    request could carry two different `experiments` and the reader of the JSON would see the first.
    """
    try:
        return json.loads(body, object_pairs_hook=_refuse_duplicates)
    except _DuplicateKey as exc:
        text = body.decode("utf-8", "replace")
        key = str(exc)
        # point at the second occurrence of the key (the first one that is a key, not a value)
        hits = [m.start() for m in re.finditer(re.escape(json.dumps(key)) + r"\s*:", text)]
        raise json.JSONDecodeError(f"duplicate key {key!r} in one object: send each key once",
                                   text, hits[1] if len(hits) > 1 else 0) from None


def parse_and_validate(model: Optional[type[BaseModel]], body: bytes) -> tuple[str, Any]:
    """Parse a body and validate it as `model`; never raises, the outcome says what happened.

    ("ok", (instance or, without a model, the parsed JSON; request_texts)) | ("json_invalid", (message, position))
    | ("invalid", pydantic errors without their input) | ("unparsable", None): not UTF-8 JSON or
    nested too deeply to parse (FastAPI answers 400) | ("too_deep", None): nested too deeply to
    validate (answered 422, as in the web process).

    `request_texts`: for a job body (a model with a list `requests`), the JSON text of each request,
    made here so that the web process only stores it (serialising holds the interpreter lock too).
    """
    try:
        data = loads_strict(body)
    except json.JSONDecodeError as exc:
        return "json_invalid", (exc.msg, exc.pos)
    except (ValueError, RecursionError):    # UnicodeDecodeError is a ValueError
        return "unparsable", None
    if model is None:
        return "ok", (data, None)
    try:
        instance = model.model_validate(data)
    except ValidationError as exc:
        # the input of each error is left out: it may be megabytes, and the answer never shows it
        return "invalid", [{"type": e["type"], "loc": tuple(e["loc"]), "msg": e["msg"]}
                           for e in exc.errors(include_url=False, include_input=False, include_context=False)]
    except RecursionError:
        return "too_deep", None
    requests = getattr(instance, "requests", None)
    texts = [r.model_dump_json() for r in requests] if isinstance(requests, list) and \
        all(isinstance(r, BaseModel) for r in requests) else None
    return "ok", (instance, texts)


def exit_with_parent(parent_pid: int) -> None:
    """Initializer of a parser process: end it when the server is gone (even after kill -9).

    Pool processes wait on a queue whose writing end they hold themselves, so they would not
    notice on their own."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
