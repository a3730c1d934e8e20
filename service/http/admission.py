"""Admission of request bodies: a size limit per body (413), a budget for all bodies at once (503)
and a deadline to receive a body (408).

Parsing JSON costs about three times the body in memory, so the bytes being received and parsed at
once are what bounds the server's memory. The budget is charged by the bytes received, not by the
declared Content-Length: two clients that declared 64 MB each and sent a byte a second held the
whole budget that way, and every other POST got 503. A body that has not arrived within
`body_read_seconds` of the request's start is cut (408): a slow sender holds a connection and its
bytes only that long.
"""
from __future__ import annotations

import asyncio
import time

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from greyfit.service.http.problems import problem


class BodyBudget:
    def __init__(self, app: ASGIApp, max_body_bytes: int, max_inflight_bytes: int, retry_after: int,
                 body_read_seconds: float = 60.0):
        self.app, self.max_body, self.max_inflight = app, max_body_bytes, max_inflight_bytes
        self.retry_after = str(retry_after)
        self.body_read_seconds = body_read_seconds
        self.inflight = 0   # one event loop: no lock needed

    def _too_large(self) -> str:
        return (f"the body exceeds this server's limit of {self.max_body} bytes (GREYFIT_MAX_BODY_BYTES); "
                "decimate the data or split it into several jobs")

    def _busy(self) -> str:
        return (f"the server is receiving {self.inflight} bytes of other requests (GREYFIT_MAX_INFLIGHT_BODY_BYTES "
                f"is {self.max_inflight}); retry after {self.retry_after} s")

    def _too_slow(self, seen: int) -> str:
        return (f"the body did not arrive within {self.body_read_seconds:g} s ({seen} bytes received; "
                "GREYFIT_BODY_READ_SECONDS): send it faster, or split the data into smaller jobs")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_body:
            return await problem(413, "Request too large", self._too_large(), "request-too-large")(
                scope, receive, send)
        deadline = time.monotonic() + self.body_read_seconds
        seen = 0
        more_body = True

        async def limited() -> Message:
            nonlocal seen, more_body
            if not more_body:   # the body is in: what follows is a disconnect, waited for as long as it takes
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), timeout=max(0.0, deadline - time.monotonic()))
            except asyncio.TimeoutError:
                raise HTTPException(408, self._too_slow(seen), headers={"Connection": "close"}) from None
            if message["type"] == "http.request":
                chunk = len(message.get("body", b""))
                more_body = bool(message.get("more_body", False))
                if seen + chunk > self.max_body:   # a chunked body without Content-Length, or a lying one
                    raise HTTPException(413, self._too_large())
                if chunk and self.inflight + chunk > self.max_inflight:
                    raise HTTPException(503, self._busy(), headers={"Retry-After": self.retry_after})
                self.inflight += chunk
                seen += chunk
            return message

        try:
            await self.app(scope, limited, send)
        finally:
            self.inflight -= seen
