"""API keys and rate limit, checked on the raw request before any byte of the body is read.

Every path but the probes needs a key when GREYFIT_API_KEY is set or the store holds named keys
(service/http/clients.py) — including /docs, /redoc and /openapi.json — so an unauthenticated client
costs no memory and learns nothing about the API. The client a key names goes on the request
(`request.state.client`): the job routes show it its own jobs only, and its rate limit is its own.
"""
from __future__ import annotations

import hmac
import logging
import math
import time
from typing import Optional

from anyio import to_thread
from starlette.types import ASGIApp, Receive, Scope, Send

from greyfit.service.http.clients import ANONYMOUS, KEY_PREFIX, LEGACY, Client, KeyStore
from greyfit.service.http.problems import problem

log = logging.getLogger("greyfit.service")
# how long "this store has no named keys" is believed before it is read again: the first key made
# while a server runs is required within this time (a revoked one at once: each key is read per request)
NO_KEYS_RECHECK_SECONDS = 1.0

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
    """401 without a valid key, 429 beyond the client's rate limit; pure ASGI, so nothing is parsed first.

    The named keys are read from the store the app's lifespan opened (`app.state.keys`, a KeyStore),
    one indexed read a request in a thread, so that a key revoked by any replica is refused at once."""

    def __init__(self, app: ASGIApp, api_key: Optional[str], rate_limit_per_minute: Optional[int] = None):
        self.app = app
        self.key = api_key.encode("utf-8") if api_key else None
        self.limiter = RateLimiter(rate_limit_per_minute) if rate_limit_per_minute else None
        self._named_keys, self._checked = False, -math.inf   # once any named key exists, for good

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in PUBLIC_PATHS:
            return await self.app(scope, receive, send)
        try:
            client = await self._client(scope)
        except Exception as exc:   # the database's text could carry a key's digest: only its type goes out
            log.warning("could not read the API keys from the job store (%s)", type(exc).__name__)
            response = problem(503, "Job store unavailable", f"the API keys cannot be read from the job store "
                               f"({type(exc).__name__}); retry later", "store-unavailable")
            return await response(scope, receive, send)
        if client is None:
            response = problem(401, "Unauthorized", "missing, wrong or revoked API key: send "
                               "'Authorization: Bearer <key>'", "unauthorized")
            response.headers["WWW-Authenticate"] = "Bearer"
            return await response(scope, receive, send)
        scope.setdefault("state", {})["client"] = client
        if self.limiter is not None:
            # a client's own bucket; on an open server, one per address
            bucket = (scope.get("client") or ("?",))[0] if client.sees_all else f"key:{client.owner}"
            wait = self.limiter.take(bucket.encode())
            if wait > 0:
                response = problem(429, "Too many requests", f"more than {self.limiter.capacity:g} requests a "
                                   "minute (GREYFIT_RATE_LIMIT_PER_MINUTE); retry later", "too-many-requests")
                response.headers["Retry-After"] = str(max(1, math.ceil(wait)))
                return await response(scope, receive, send)
        await self.app(scope, receive, send)

    async def _client(self, scope: Scope) -> Optional[Client]:
        """Who sent the request: the client of its key; ANONYMOUS on a server without keys; None
        (401) for a missing, unknown or revoked key."""
        token = bearer_token(scope)
        if self.key is not None and token is not None and hmac.compare_digest(token, self.key):
            return LEGACY
        keys: Optional[KeyStore] = getattr(scope["app"].state, "keys", None)
        if keys is None:   # no store (the lifespan has not run): only the single key is known
            return ANONYMOUS if self.key is None else None
        if token is not None and token.startswith(KEY_PREFIX.encode()):
            client = await to_thread.run_sync(keys.client_of, token)
            if client is not None:
                return client
        if self.key is None and not await self._any_named_keys(keys):
            return ANONYMOUS
        return None

    async def _any_named_keys(self, keys: KeyStore) -> bool:
        """Whether the store holds named keys. A store that cannot be read leaves an open server
        open (its synchronous fits need no store), as it was before any key existed."""
        now = time.monotonic()
        if not self._named_keys and now - self._checked > NO_KEYS_RECHECK_SECONDS:
            self._checked = now
            try:
                self._named_keys = await to_thread.run_sync(keys.any_keys)
            except Exception as exc:
                log.warning("could not read the API keys from the job store (%s)", type(exc).__name__)
        return self._named_keys
