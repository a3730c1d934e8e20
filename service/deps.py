"""Request-scoped dependencies: settings, store, dispatcher, API key."""
from __future__ import annotations

import hmac

from fastapi import HTTPException, Request

from service.settings import Settings


def settings_of(request: Request) -> Settings:
    return request.app.state.settings


def require_api_key(request: Request) -> None:
    key = request.app.state.settings.api_key
    if not key:
        return
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not hmac.compare_digest(token.strip(), key):
        raise HTTPException(401, "missing or wrong API key: send 'Authorization: Bearer <key>'",
                            headers={"WWW-Authenticate": "Bearer"})
