"""Errors as application/problem+json (RFC 9457); one handler per error class."""
from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from solvers.errors import DataError, FitError, ModelDefinitionError

log = logging.getLogger("greyfit.service")
PROBLEM = "application/problem+json"
TYPE_BASE = "https://greyfit.dev/problems/"


class RequestTooLarge(Exception):
    def __init__(self, detail: str):
        self.detail = detail


class LimitExceeded(Exception):
    """A request within the schema but beyond this server's configured limits (422)."""

    def __init__(self, field: str, detail: str):
        self.field, self.detail = field, detail


def problem(status: int, title: str, detail: str, kind: str, **extra) -> JSONResponse:
    body = {"type": TYPE_BASE + kind, "title": title, "status": status, "detail": detail, **extra}
    return JSONResponse(body, status_code=status, media_type=PROBLEM)


def _loc(loc) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] == "body":
        parts = parts[1:]
    out = ""
    for p in parts:
        out += f"[{p}]" if p.isdigit() else (f".{p}" if out else p)
    return out or "body"


def validation_errors(errors) -> list[dict]:
    out = []
    for e in errors:
        msg = e.get("msg", "invalid")
        if e.get("type") == "json_invalid":
            msg = f"malformed JSON: {e.get('ctx', {}).get('error', msg)}"
        out.append({"loc": _loc(e.get("loc", ())), "msg": msg})
    return out


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError):
        errors = validation_errors(exc.errors())
        detail = "; ".join(f"{e['loc']}: {e['msg']}" for e in errors[:5])
        return problem(422, "Invalid request", detail, "validation-error", errors=errors)

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

    @app.exception_handler(RequestTooLarge)
    async def _too_large(_: Request, exc: RequestTooLarge):
        return problem(413, "Request too large", exc.detail, "request-too-large")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException):
        detail = str(exc.detail)
        if exc.status_code == 400 and detail == "There was an error parsing the body":
            detail = "the body could not be parsed: it must be UTF-8 JSON, nested at most ~1000 levels deep"
        titles = {400: "Bad request", 401: "Unauthorized", 404: "Not found", 405: "Method not allowed", 409: "Conflict",
                  413: "Request too large", 503: "Unavailable", 504: "Timeout"}
        resp = problem(exc.status_code, titles.get(exc.status_code, "Error"), detail,
                       titles.get(exc.status_code, "error").lower().replace(" ", "-"))
        for k, v in (exc.headers or {}).items():
            resp.headers[k] = v
        return resp

    @app.exception_handler(RecursionError)
    async def _deep(_: Request, exc: RecursionError):
        return problem(422, "Invalid request", "the JSON body is nested too deeply", "validation-error",
                       errors=[{"loc": "body", "msg": "nested too deeply"}])

    @app.exception_handler(Exception)
    async def _internal(_: Request, exc: Exception):
        log.exception("unhandled error")
        return problem(500, "Internal error", f"{type(exc).__name__}: the server failed; the error was logged",
                       "internal-error")
