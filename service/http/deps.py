"""Request-scoped dependencies: settings, API key."""
from __future__ import annotations

import hmac

from fastapi import HTTPException, Request

from greyfit.service.http.clients import ANONYMOUS, Client
from greyfit.service.settings import Settings


def settings_of(request: Request) -> Settings:
    return request.app.state.settings


def carries_api_key(request: Request) -> bool:
    """Whether the server has a key and the request carries it (public routes show more to such callers)."""
    key = request.app.state.settings.api_key
    if not key:
        return False
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    # compare bytes: compare_digest refuses non-ASCII str, and a header may carry any octet
    return scheme.lower() == "bearer" and hmac.compare_digest(token.strip().encode("latin-1"), key.encode("utf-8"))


def client_of(request: Request) -> Client:
    """The client the key gate (service.http.auth.ApiKeyGate) found for the request; ANONYMOUS without one
    (an app built without the gate: a server without keys)."""
    return getattr(request.state, "client", ANONYMOUS)


def require_api_key(request: Request) -> None:
    """The key check as a dependency (service.http.auth.ApiKeyGate does it for the whole app, before the body)."""
    if not request.app.state.settings.api_key or "client" in request.scope.get("state", {}):
        return
    if not carries_api_key(request):
        raise HTTPException(401, "missing or wrong API key: send 'Authorization: Bearer <key>'",
                            headers={"WWW-Authenticate": "Bearer"})
