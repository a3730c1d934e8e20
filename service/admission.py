"""Admission of request bodies: a size limit per body (413) and a budget for all bodies at once (503).

Parsing JSON costs about three times the body in memory, so the bytes being received and parsed at
once are what bounds the server's memory; a body that does not fit in the budget is refused before
it is read, with Retry-After, instead of being buffered.
"""
from __future__ import annotations

from fastapi import HTTPException
from starlette.types import ASGIApp, Receive, Scope, Send

from greyfit.service.problems import problem


class BodyBudget:
    def __init__(self, app: ASGIApp, max_body_bytes: int, max_inflight_bytes: int, retry_after: int):
        self.app, self.max_body, self.max_inflight = app, max_body_bytes, max_inflight_bytes
        self.retry_after = str(retry_after)
        self.inflight = 0   # one event loop: no lock needed

    def _too_large(self) -> str:
        return (f"the body exceeds this server's limit of {self.max_body} bytes (GREYFIT_MAX_BODY_BYTES); "
                "decimate the data or split it into several jobs")

    def _busy(self) -> str:
        return (f"the server is receiving {self.inflight} bytes of other requests (GREYFIT_MAX_INFLIGHT_BODY_BYTES "
                f"is {self.max_inflight}); retry after {self.retry_after} s")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        reserved = int(declared) if declared is not None and declared.isdigit() else 0
        if reserved > self.max_body:
            return await problem(413, "Request too large", self._too_large(), "request-too-large")(
                scope, receive, send)
        if reserved and self.inflight + reserved > self.max_inflight:
            response = problem(503, "Unavailable", self._busy(), "unavailable")
            response.headers["Retry-After"] = self.retry_after
            return await response(scope, receive, send)
        self.inflight += reserved
        seen = 0

        async def limited() -> dict:
            nonlocal seen, reserved
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_body:   # a chunked body without Content-Length, or a lying one
                    raise HTTPException(413, self._too_large())
                if seen > reserved:
                    if self.inflight + seen - reserved > self.max_inflight:
                        raise HTTPException(503, self._busy(), headers={"Retry-After": self.retry_after})
                    self.inflight += seen - reserved
                    reserved = seen
            return message

        try:
            await self.app(scope, limited, send)
        finally:
            self.inflight -= reserved
