"""JSON bodies parsed strictly and off the event loop.

- A key twice in one object is an error (json.loads would silently keep the last value, so a
  request could carry two different `experiments` and the reader of the JSON would see the first).
- Bodies above a megabyte are parsed in a thread, so a large upload does not stall /healthz.
"""
from __future__ import annotations

import json
import re
from typing import Any, Callable

import anyio
from fastapi import Request, Response
from fastapi.routing import APIRoute

PARSE_IN_THREAD_BYTES = 1 << 20


def _refuse_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(key)
        out[key] = value
    return out


def loads_strict(body: bytes) -> Any:
    """json.loads that raises JSONDecodeError on a duplicate key (FastAPI reports it as a 422)."""
    try:
        return json.loads(body, object_pairs_hook=_refuse_duplicates)
    except ValueError as exc:
        if isinstance(exc, json.JSONDecodeError):
            raise
        text = body.decode("utf-8", "replace")
        key = str(exc)
        # point at the second occurrence of the key (the first one that is a key, not a value)
        hits = [m.start() for m in re.finditer(re.escape(json.dumps(key)) + r"\s*:", text)]
        raise json.JSONDecodeError(f"duplicate key {key!r} in one object: send each key once",
                                   text, hits[1] if len(hits) > 1 else 0) from None


class StrictJSONRequest(Request):
    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            body = await self.body()
            if len(body) > PARSE_IN_THREAD_BYTES:
                self._json = await anyio.to_thread.run_sync(loads_strict, body)
            else:
                self._json = loads_strict(body)
        return self._json


class StrictJSONRoute(APIRoute):
    """Route class of every router: its handler sees a StrictJSONRequest."""

    def get_route_handler(self) -> Callable:
        handler = super().get_route_handler()

        async def strict_handler(request: Request) -> Response:
            return await handler(StrictJSONRequest(request.scope, request.receive))

        return strict_handler
