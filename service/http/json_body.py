"""JSON bodies parsed strictly, and large ones parsed and validated outside the web process.

- A body must come as JSON (Content-Type application/json or */*+json): anything else is a 415
  that says so, not a 422 about a body that "should be a valid dictionary".
- A key twice in one object is an error (service.http.json_parsing.loads_strict).
- A valid body is validated straight from its JSON text (service.http.json_parsing.validate_json, strictly:
  a string or a boolean is not a number) and
  the route receives the model; any other body is parsed and validated as before, with its errors.
  The text it was validated from stays with the request (`validated_text`): a worker validates
  that text again, which costs less than dumping the model to a dict, pickling the dict and
  validating the dict.
- A body above LARGE_BODY_BYTES is parsed and validated as the route's body model in a parser
  process. Parsing holds the interpreter lock (about a second for 30 MB): in a thread of the web
  process it stalls the event loop all the same, and /healthz with it. The route receives the
  validated model; FastAPI does not validate an instance of its body model again.
  `GREYFIT_BODY_PARSER_PROCESSES=0` parses them in a thread instead (small deployments, benchmarks).
- How many bodies are parsed at once is bounded by the parser processes; how many wait for them,
  by the in-flight body budget (service.http.admission), which counts a body until its answer is sent.
- The parser processes start with the server, with the body models imported: the first large
  body would otherwise wait half a second for them.
"""
from __future__ import annotations

import asyncio
import concurrent.futures as cf
import multiprocessing as mp
import os
import threading
from typing import Any, Callable, Optional

import anyio
from fastapi import HTTPException, Request, Response
from fastapi.params import Form
from fastapi.routing import APIRoute
from pydantic import BaseModel

from greyfit.service.http.json_parsing import (
    capped,
    exit_with_parent,
    has_duplicate_keys,
    loads_strict,
    parse_and_validate,
    validate_json,
    warm_up,
)
from greyfit.service.http.json_shape import ListLimits, worth_checking

LARGE_BODY_BYTES = 1 << 20


class InvalidBody(HTTPException):
    """A body that failed validation in a parser process: answered like FastAPI's own 422.

    An HTTPException, because FastAPI passes those through from `Request.json()` (any other
    exception there becomes a 400)."""

    def __init__(self, errors: list[dict], body: bytes):
        super().__init__(422, "invalid request")
        self.errors, self.body = errors, body


class BodyLimitExceeded(HTTPException):
    """A body with a list or an object beyond this server's limits, found before it was validated (422,
    answered like service.http.problems.LimitExceeded)."""

    def __init__(self, field: str, detail: str):
        super().__init__(422, detail)
        self.field = field


class NotJSON(HTTPException):
    """A body sent without a JSON media type: 415, saying what to send."""

    def __init__(self, content_type: Optional[str]):
        sent = f"'{content_type}'" if content_type else "no Content-Type"
        super().__init__(415, f"the body must be JSON, sent with 'Content-Type: application/json' ({sent} was "
                         "sent); e.g. curl -H 'Content-Type: application/json' --data @request.json")


class BodyParser:
    """Parser processes (started by `start()`, else on the first large body); 0 processes parses in a
    thread."""

    def __init__(self, processes: int, retry_after: int, limits: ListLimits = ListLimits(), max_waiting: int = 8):
        self.processes, self.retry_after, self.limits = processes, retry_after, limits
        self.max_waiting = max_waiting   # bodies waiting for a parser beyond those being parsed: then 503
        self.pending = 0                 # bodies submitted and not yet parsed (one event loop: no lock)
        self._pool: Optional[cf.ProcessPoolExecutor] = None
        self._lock = threading.Lock()

    def _executor(self) -> cf.ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = cf.ProcessPoolExecutor(self.processes, mp_context=mp.get_context("spawn"),
                                                    initializer=exit_with_parent, initargs=(os.getpid(),))
            return self._pool

    def start(self, modules: list[str]) -> None:
        """Start the parser processes now and import `modules` in them (without waiting)."""
        if self.processes == 0:
            return
        pool = self._executor()
        for _ in range(self.processes):   # each submit with no idle process starts one
            pool.submit(warm_up, modules)

    async def parse(self, model: Optional[type[BaseModel]], body: bytes) -> tuple[Any, Optional[list[str]]]:
        """The validated model (or, without one, the parsed JSON) and, for a job body, the JSON text
        of each request; the same errors as in the web process."""
        if self.pending >= max(1, self.processes) + self.max_waiting:
            raise HTTPException(503, f"{self.pending} bodies are waiting to be parsed; retry later",
                                headers={"Retry-After": str(self.retry_after)})
        self.pending += 1
        try:
            outcome = await self._run(model, body)
        finally:
            self.pending -= 1
        status, value = outcome
        if status == "limit":
            raise BodyLimitExceeded(_dotted(value[0]), f"{_dotted(value[0])}: {value[1]}")
        if status == "ok":
            return value          # (the instance or parsed JSON, the requests' JSON texts or None)
        if status == "json_invalid":
            raise InvalidBody([{"type": "json_invalid", "loc": ("body", value[1]), "msg": "JSON decode error",
                                "ctx": {"error": value[0]}}], body)
        if status == "invalid":
            raise InvalidBody([{**e, "loc": ("body", *e["loc"])} for e in value], body)
        if status == "too_deep":
            raise RecursionError("nested too deeply")
        raise ValueError("unparsable body")   # FastAPI answers 400, as for a body it parsed itself

    async def _run(self, model: Optional[type[BaseModel]], body: bytes) -> tuple[str, Any]:
        if self.processes == 0:
            return await anyio.to_thread.run_sync(parse_and_validate, model, body, self.limits)
        pool = self._executor()
        try:
            return await asyncio.wrap_future(pool.submit(parse_and_validate, model, body, self.limits))
        except cf.BrokenExecutor:      # a parser process died (e.g. out of memory): start afresh
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            raise HTTPException(503, "the process parsing large bodies was lost (out of memory?); retry",
                                headers={"Retry-After": str(self.retry_after)}) from None

    def shutdown(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)


class StrictJSONRequest(Request):
    body_model: Optional[type[BaseModel]] = None

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            body = await self.body()
            _refuse_other_encodings(body)
            # a large body, or one of many objects and strings (its shape is walked before it is
            # validated, service.http.json_shape): in a parser process, never in the event loop
            if len(body) > LARGE_BODY_BYTES or (self.body_model is not None and worth_checking(body)):
                self._json, texts = await self.app.state.body_parser.parse(self.body_model, body)
                if texts is not None:
                    self.state.request_texts = texts   # see request_texts()
            else:
                self._json = self._parse_small(body)
        return self._json

    def _parse_small(self, body: bytes) -> Any:
        """The validated model, else the parsed JSON (JSON errors and duplicate keys raise first),
        else the strict validation errors as InvalidBody (FastAPI would validate the parsed dict
        laxly: "500" as a number)."""
        model = self.body_model
        instance, errors = validate_json(model, body) if model is not None else (None, None)
        if instance is not None and not has_duplicate_keys(body):
            self.scope["greyfit.validated_body"] = (instance, body)
            return instance
        data = loads_strict(body)
        if errors is not None:
            requests = data.get("requests") if isinstance(data, dict) else None
            errors = capped(errors, len(requests) if isinstance(requests, list) else None)
            raise InvalidBody([{**e, "loc": ("body", *e["loc"])} for e in errors], body)
        return data


# a byte-order mark, or the NUL bytes of UTF-16/32 among the first four: json.loads would decode
# these (RFC 8259 says UTF-8 without a BOM), and the docs promise 400
_BOMS = (b"\xef\xbb\xbf", b"\xff\xfe", b"\xfe\xff")


def _refuse_other_encodings(body: bytes) -> None:
    if body.startswith(_BOMS) or b"\x00" in body[:4]:
        raise HTTPException(400, "the body must be UTF-8 JSON without a byte-order mark (it looks like UTF-16 "
                            "or UTF-32, or starts with a BOM): re-encode it as UTF-8")


def _dotted(loc: tuple) -> str:
    """`requests` or `requests[0].experiments` for a location tuple (the body itself: `body`)."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "body"


def validated_text(request: Request, instance: BaseModel) -> str | dict:
    """The JSON text `instance` was validated from (the body as received), else its dump as a dict.

    Validating the same text as the same model gives the same model, so a worker handed the text
    runs exactly what the route checked. (Not model_dump_json for the rest: it writes an infinite
    float as null.)"""
    validated = request.scope.get("greyfit.validated_body")
    if validated is not None and validated[0] is instance:
        try:
            return validated[1].decode("utf-8")
        except UnicodeDecodeError:   # pydantic read it, so it is UTF-8; never guess if not
            pass
    # only what was sent: the fits read which options the user set (substeps left to the fit are chosen)
    return instance.model_dump(mode="json", exclude_unset=True)


def request_texts(request: Request, requests: list[BaseModel]) -> list[str]:
    """The JSON text of each request of a job body: made by the parser process when it parsed the
    body, else here."""
    texts = getattr(request.state, "request_texts", None)
    if texts is not None and len(texts) == len(requests):
        return texts
    return [r.model_dump_json(exclude_unset=True) for r in requests]


def body_model(route) -> Optional[type[BaseModel]]:
    """The model of the route's single JSON body parameter, if it is a StrictJSONRoute with exactly one."""
    if not isinstance(route, StrictJSONRoute):
        return None
    return _body_model(route)


def _body_model(route: APIRoute) -> Optional[type[BaseModel]]:
    """The model of the route's single JSON body parameter, if it has exactly one."""
    params = route.dependant.body_params
    if len(params) != 1 or getattr(params[0].field_info, "embed", False):
        return None
    annotation = params[0].field_info.annotation
    return annotation if isinstance(annotation, type) and issubclass(annotation, BaseModel) else None


class StrictJSONRoute(APIRoute):
    """Route class of every router: its handler sees a StrictJSONRequest that knows the body model."""

    def get_route_handler(self) -> Callable:
        handler = super().get_route_handler()
        model = _body_model(self)

        takes_json = bool(self.dependant.body_params) and not _is_form(self)

        async def strict_handler(request: Request) -> Response:
            if takes_json and _has_body(request) and not _is_json(request.headers.get("content-type")):
                raise NotJSON(request.headers.get("content-type"))
            encoding = request.headers.get("content-encoding", "identity").strip().lower()
            if takes_json and encoding != "identity":   # read as plain JSON, a gzip body would be garbage
                raise HTTPException(415, f"Content-Encoding '{encoding}' is not accepted: send the body "
                                    "uncompressed, without a Content-Encoding header")
            strict = StrictJSONRequest(request.scope, request.receive)
            strict.body_model = model
            return await handler(strict)

        return strict_handler


def _is_form(route: APIRoute) -> bool:
    return any(isinstance(p.field_info, Form) for p in route.dependant.body_params)


def _has_body(request: Request) -> bool:
    """Whether the request carries a body (an empty one is FastAPI's to answer: body required)."""
    headers = request.headers
    return "transfer-encoding" in headers or headers.get("content-length", "0").strip() not in ("", "0")


def _is_json(content_type: Optional[str]) -> bool:
    """application/json or application/<something>+json, any parameters (as FastAPI reads JSON)."""
    if not content_type:
        return False
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))
