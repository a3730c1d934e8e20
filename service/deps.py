"""Request-scoped dependencies: settings, API key."""
from __future__ import annotations

import hmac

from fastapi import HTTPException, Request

from greyfit.service.settings import Settings


def settings_of(request: Request) -> Settings:
    return request.app.state.settings


def require_api_key(request: Request) -> None:
    """The key check as a dependency (service.auth.ApiKeyGate does it for the whole app, before the body)."""
    key = request.app.state.settings.api_key
    if not key:
        return
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    # compare bytes: compare_digest refuses non-ASCII str, and a header may carry any octet
    if scheme.lower() != "bearer" or not hmac.compare_digest(token.strip().encode("latin-1"), key.encode("utf-8")):
        raise HTTPException(401, "missing or wrong API key: send 'Authorization: Bearer <key>'",
                            headers={"WWW-Authenticate": "Bearer"})
