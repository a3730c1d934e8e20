"""uvicorn's HTTP protocol (httptools) with the edges of a connection bounded and answered as the
rest of the service answers.

- A connection must send a complete request head (request line and headers) within
  `head_seconds` of opening, or of the first byte of its next request; else it is closed. uvicorn
  times out a connection only between requests (`timeout_keep_alive`): one that sends nothing, or
  a header a byte at a time, was held open for ever.
- A request uvicorn cannot parse (bytes after a body shorter than its lying `Content-Length`, a
  malformed request line) is answered 400 as application/problem+json (RFC 9457), like every other
  error of the service, not uvicorn's text/plain.
"""
from __future__ import annotations

import asyncio
import json
from typing import Optional

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

PROBLEM_400 = {"type": "https://greyfit.dev/problems/bad-request", "title": "Bad request", "status": 400,
               "detail": "the request could not be parsed as HTTP/1.1 (a malformed request line or header, or "
                         "bytes beyond the body's Content-Length); the connection is closed"}


class BoundedHttpToolsProtocol(HttpToolsProtocol):
    head_seconds: float = 10.0

    _head_deadline: Optional[asyncio.TimerHandle] = None

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._arm_head_deadline()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._arm_head_deadline()

    def on_headers_complete(self) -> None:
        self._disarm_head_deadline()
        super().on_headers_complete()

    def connection_lost(self, exc: Optional[Exception]) -> None:
        self._disarm_head_deadline()
        super().connection_lost(exc)

    def _arm_head_deadline(self) -> None:
        self._disarm_head_deadline()
        self._head_deadline = self.loop.call_later(self.head_seconds, self._head_too_slow)

    def _disarm_head_deadline(self) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
            self._head_deadline = None

    def _head_too_slow(self) -> None:
        # no request is being answered (its head is incomplete): nothing is cut but the connection
        if not self.transport.is_closing():
            self.transport.close()

    def send_400_response(self, msg: str) -> None:
        body = json.dumps(PROBLEM_400).encode()
        self.transport.write(b"".join([
            b"HTTP/1.1 400 Bad Request\r\ncontent-type: application/problem+json\r\n",
            b"content-length: " + str(len(body)).encode() + b"\r\nconnection: close\r\n\r\n", body]))
        self.transport.close()


def bounded_protocol(head_seconds: float) -> type[BoundedHttpToolsProtocol]:
    """The protocol class uvicorn is given (`http=`), with this server's deadline for a request head."""
    return type("BoundedHttpToolsProtocol", (BoundedHttpToolsProtocol,), {"head_seconds": head_seconds})
