"""Errors as application/problem+json (RFC 9457); one handler per error class."""
from __future__ import annotations

import logging
from typing import Any, Optional, Sequence

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from sqlalchemy.exc import InterfaceError, InternalError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from greyfit.service.http.deps import carries_api_key
from greyfit.service.http.error_text import describe
from greyfit.service.http.json_body import BodyLimitExceeded, InvalidBody, body_model
from greyfit.service.http.json_parsing import capped
from greyfit.service.http.logs import REQUEST_ID
from greyfit.service.jobs.store import StoreUnavailable
from greyfit.solvers.errors import DataError, FitError, ModelDefinitionError

log = logging.getLogger("greyfit.service")
PROBLEM = "application/problem+json"
TYPE_BASE = "https://greyfit.dev/problems/"


class ProblemError(BaseModel):
    loc: str = Field(description="where in the request: experiments[0].outputs.x, equations.v, body")
    msg: str = Field(description="what is wrong there and the fix")


class Problem(BaseModel):
    """application/problem+json (RFC 9457): every error this service answers."""

    type: str = Field(description="a URI naming the kind of problem (RFC 9457)")
    title: str = Field(description="the kind of problem, in words")
    status: int = Field(description="the HTTP status code")
    detail: str = Field(description="what went wrong and what to do, in words")
    errors: Optional[list[ProblemError]] = Field(default=None, description="validation errors, by location")
    request_id: Optional[str] = Field(default=None, description="the id of the request (also its X-Request-ID "
                                      "header), which the server's log lines about it carry")


class Overloaded(Exception):
    """The server is at a configured capacity limit: 503 with Retry-After."""

    def __init__(self, detail: str):
        self.detail = detail


class RequestTooLarge(Exception):
    def __init__(self, detail: str):
        self.detail = detail


class LimitExceeded(Exception):
    """A request within the schema but beyond this server's configured limits (422)."""

    def __init__(self, field: str, detail: str):
        self.field, self.detail = field, detail


def problem(status: int, title: str, detail: str, kind: str, **extra) -> JSONResponse:
    """The problem+json answer; it carries the request's id (as its X-Request-ID header does)."""
    body = {"type": TYPE_BASE + kind, "title": title, "status": status, "detail": detail,
            "request_id": REQUEST_ID.get(), **extra}
    return JSONResponse(body, status_code=status, media_type=PROBLEM)


def _json_position(doc, pos) -> str:
    if not isinstance(pos, int) or not isinstance(doc, (str, bytes)):
        return ""
    text = doc if isinstance(doc, str) else doc.decode("utf-8", "replace")
    line = text.count("\n", 0, pos) + 1
    column = pos - (text.rfind("\n", 0, pos) + 1) + 1
    return f" at line {line} column {column} (character {pos})"


def validation_errors(errors, body=None, model: Optional[type[BaseModel]] = None) -> list[dict]:
    """Errors by location in one syntax (`experiments[0].time`), in words (service.http.error_text);
    `model`, the route's body model, finds the field meant by a misspelt one."""
    out = []
    for e in errors:
        if e.get("type") == "json_invalid":   # FastAPI puts the character offset into loc: say it in words
            pos = (e.get("loc") or (None, None))[-1]
            msg = f"malformed JSON: {e.get('ctx', {}).get('error', e.get('msg'))}{_json_position(body, pos)}"
            out.append({"loc": "body", "msg": msg})
            continue
        body_error = tuple(e.get("loc", ()))[:1] == ("body",)
        out.extend(describe([e], model if body_error else None))
    return out


def retry_later(status: int, title: str, detail: str, kind: str, retry_after: int) -> JSONResponse:
    resp = problem(status, title, detail, kind)
    resp.headers["Retry-After"] = str(retry_after)
    return resp


def route_methods(routes: Sequence[Any]) -> list[tuple[Any, frozenset[str]]]:
    """(path pattern, methods) of each route that has methods (create_app passes the app's routes
    and those of each router it includes, which FastAPI may keep behind a wrapper)."""
    return [(route.path_regex, frozenset(route.methods)) for route in routes if getattr(route, "methods", None)]


def allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at the request's path. Starlette's 405 names only the methods
    of the first route whose path matched, while a path can have one route per method."""
    path = request.scope["path"]
    root = request.scope.get("root_path", "")
    if root and path.startswith(root):
        path = path[len(root):]
    table = getattr(request.app.state, "route_methods", [])
    return sorted({m for pattern, methods in table if pattern.match(path) for m in methods})


# a database error's condition in words of our own, for callers who may not read its text
STORE_CONDITIONS = (("is read-only", ("readonly database", "read-only transaction")),
                    ("is full", ("disk is full", "no space left", "could not extend file")),
                    ("is locked", ("database is locked",)),
                    ("cannot be reached", ("connection", "could not connect", "timeout")))


def store_error_detail(exc: Exception, full: bool = True) -> str:
    """What a store error says. The database's own text names files, hosts and ports (the SQLite
    path; 'connection to server at "10.0.0.5", port 5432'): only with `full`; else the component,
    its condition where known and the error's class, as /readyz answers a caller without the API key."""
    if isinstance(exc, StoreUnavailable):
        return str(exc) if full else exc.public
    cause = getattr(exc, "orig", None) or exc
    first = (str(cause).splitlines() or [""])[0][:300]
    if not full:
        text = str(cause).lower()
        condition = next((words for words, marks in STORE_CONDITIONS if any(m in text for m in marks)), "failed")
        return f"the job store {condition} ({type(cause).__name__}); retry later"
    return f"the job store failed ({type(cause).__name__}: {first}); retry later"


def install_handlers(app: FastAPI) -> None:
    def invalid_request(errors: Sequence[Any], body, model: Optional[type[BaseModel]] = None) -> JSONResponse:
        errors = validation_errors(capped(list(errors)), body, model)
        detail = "; ".join(f"{e['loc']}: {e['msg']}" for e in errors[:5])
        return problem(422, "Invalid request", detail, "validation-error", errors=errors)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        return invalid_request(exc.errors(), exc.body, body_model(request.scope.get("route")))

    @app.exception_handler(InvalidBody)       # the same, for a body validated strictly or in a parser process
    async def _invalid_body(request: Request, exc: InvalidBody):
        return invalid_request(exc.errors, exc.body, body_model(request.scope.get("route")))

    # the solver's error tree: one problem type per class, 422 for all (the input must change)
    kinds = {ModelDefinitionError: ("Invalid model", "model-definition-error", "model"),
             DataError: ("Invalid data", "data-error", "experiments"),
             FitError: ("Cannot fit", "fit-error", "body")}

    @app.exception_handler(FitError)
    async def _fit(_: Request, exc: FitError):
        title, kind, default_loc = next(v for cls, v in kinds.items() if isinstance(exc, cls))
        return problem(422, title, str(exc), kind, errors=[{"loc": exc.field or default_loc, "msg": exc.message}])

    @app.exception_handler(LimitExceeded)
    async def _limit(_: Request, exc: LimitExceeded):
        return problem(422, "Limit exceeded", f"{exc.field}: {exc.detail}", "limit-exceeded",
                       errors=[{"loc": exc.field, "msg": exc.detail}])

    @app.exception_handler(BodyLimitExceeded)   # the same, found by the body's shape before validation
    async def _body_limit(_: Request, exc: BodyLimitExceeded):
        return problem(422, "Limit exceeded", str(exc.detail), "limit-exceeded",
                       errors=[{"loc": exc.field, "msg": str(exc.detail).partition(": ")[2]}])

    @app.exception_handler(Overloaded)
    async def _overloaded(request: Request, exc: Overloaded):
        return retry_later(503, "Unavailable", exc.detail, "unavailable",
                           request.app.state.settings.retry_after_seconds)

    # a store that cannot be written is the server's state, not the request's fault: 503, retry
    # (read-only is InternalError on PostgreSQL, OperationalError on SQLite; unreachable is either)
    @app.exception_handler(StoreUnavailable)
    @app.exception_handler(OperationalError)
    @app.exception_handler(InternalError)
    @app.exception_handler(InterfaceError)
    @app.exception_handler(PoolTimeout)
    async def _store(request: Request, exc: Exception):
        log.error("job store error on %s %s: %s", request.method, request.url.path, store_error_detail(exc))
        request.app.state.metrics.store_errors.labels("http").inc()
        # the database's text only for a caller with the API key (the same rule as /readyz)
        return retry_later(503, "Job store unavailable", store_error_detail(exc, carries_api_key(request)),
                           "store-unavailable", request.app.state.settings.retry_after_seconds)

    @app.exception_handler(RequestTooLarge)
    async def _too_large(_: Request, exc: RequestTooLarge):
        return problem(413, "Request too large", exc.detail, "request-too-large")

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        detail = str(exc.detail)
        if exc.status_code == 400 and detail == "There was an error parsing the body":
            detail = "the body could not be parsed: it must be UTF-8 JSON, nested at most ~1000 levels deep"
        titles = {400: "Bad request", 401: "Unauthorized", 404: "Not found", 405: "Method not allowed",
                  408: "Request timeout", 409: "Conflict", 413: "Request too large", 415: "Unsupported media type",
                  429: "Too many requests", 501: "Not implemented", 503: "Unavailable", 504: "Timeout"}
        resp = problem(exc.status_code, titles.get(exc.status_code, "Error"), detail,
                       titles.get(exc.status_code, "error").lower().replace(" ", "-"))
        for k, v in (exc.headers or {}).items():
            resp.headers[k] = v
        if exc.status_code == 405:
            resp.headers["Allow"] = ", ".join(allowed_methods(request))
        return resp

    @app.exception_handler(RecursionError)
    async def _deep(_: Request, exc: RecursionError):
        return problem(422, "Invalid request", "the JSON body is nested too deeply", "validation-error",
                       errors=[{"loc": "body", "msg": "nested too deeply"}])

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        # last resort: a bug. Logged with the request id that the answer carries; the tests demand none.
        request_id = request.scope.get("greyfit.request_id", "-")
        log.exception("unhandled error in %s %s (request %s)", request.method, request.url.path, request_id)
        return problem(500, "Internal error", f"{type(exc).__name__}: the server failed; the error was logged "
                       f"with request id {request_id}", "internal-error", request_id=request_id)
