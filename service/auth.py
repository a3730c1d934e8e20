"""API key and rate limit, checked on the raw request before any byte of the body is read.

Every path but the probes needs the key when GREYFIT_API_KEY is set — including /docs, /redoc and
/openapi.json — so an unauthenticated client costs no memory and learns nothing about the API.
"""
from __future__ import annotations

import hmac
import math
import time
from typing import Optional

from starlette.types import ASGIApp, Receive, Scope, Send

from greyfit.service.problems import problem

PUBLIC_PATHS = frozenset({"/healthz", "/readyz"})


def bearer_token(scope: Scope) -> Optional[bytes]:
    """The token of 'Authorization: Bearer <token>' as raw bytes (headers may hold any octet)."""
    for name, value in scope.get("headers") or []:
        if name == b"authorization":
            scheme, _, token = value.partition(b" ")
            return token.strip() if scheme.lower() == b"bearer" else None
    return None


class RateLimiter:
    """A token bucket per client: `per_minute` requests a minute, bursts up to the same number."""

    MAX_CLIENTS = 10_000

    def __init__(self, per_minute: int):
        self.rate, self.capacity = per_minute / 60.0, float(per_minute)
        self.buckets: dict[bytes, tuple[float, float]] = {}

    def take(self, client: bytes) -> float:
        """0 if the request may go, else the seconds until it may."""
        now = time.monotonic()
        if len(self.buckets) > self.MAX_CLIENTS:   # bounded memory: forget clients whose bucket is full again
            full_after = self.capacity / self.rate
            self.buckets = {k: v for k, v in self.buckets.items() if now - v[1] < full_after}
        tokens, last = self.buckets.get(client, (self.capacity, now))
        tokens = min(self.capacity, tokens + (now - last) * self.rate)
        if tokens < 1:
            self.buckets[client] = (tokens, now)
            return (1 - tokens) / self.rate
        self.buckets[client] = (tokens - 1, now)
        return 0.0


class ApiKeyGate:
    """401 without the right key, 429 beyond the rate limit; pure ASGI, so nothing is parsed first."""

    def __init__(self, app: ASGIApp, api_key: Optional[str], rate_limit_per_minute: Optional[int] = None):
        self.app = app
        self.key = api_key.encode("utf-8") if api_key else None
        self.limiter = RateLimiter(rate_limit_per_minute) if rate_limit_per_minute else None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in PUBLIC_PATHS:
            return await self.app(scope, receive, send)
        token = bearer_token(scope)
        if self.key is not None and (token is None or not hmac.compare_digest(token, self.key)):
            response = problem(401, "Unauthorized", "missing or wrong API key: send 'Authorization: Bearer <key>'",
                               "unauthorized")
            response.headers["WWW-Authenticate"] = "Bearer"
            return await response(scope, receive, send)
        if self.limiter is not None:
            client = token if self.key is not None else (scope.get("client") or ("?",))[0].encode()
            wait = self.limiter.take(client)
            if wait > 0:
                response = problem(429, "Too many requests", f"more than {self.limiter.capacity:g} requests a "
                                   "minute (GREYFIT_RATE_LIMIT_PER_MINUTE); retry later", "too-many-requests")
                response.headers["Retry-After"] = str(max(1, math.ceil(wait)))
                return await response(scope, receive, send)
        await self.app(scope, receive, send)
