"""Clients: named API keys, stored hashed in the job store, each revocable.

A client sees, lists and cancels only the jobs it created (another client's job is answered 404,
as one that does not exist); its rate limit is its own. The single `GREYFIT_API_KEY` of before is
still accepted, as the client `LEGACY`, owner of the jobs made before clients existed. A server
whose store has never held a named key and that has no `GREYFIT_API_KEY` is open, as before: every
caller is anonymous and sees every job.

A key is `gfk_` and 43 characters of `secrets.token_urlsafe(32)` (256 random bits), stored only as
its SHA-256: a key that cannot be guessed needs no slow hash, and a store that leaks gives away no
key. The key's text is printed once, when it is made, and written nowhere else: not in the store,
the logs, the metrics or an error.
"""
from __future__ import annotations

import hashlib
import re
import secrets
import time
from dataclasses import dataclass
from typing import Optional

from sqlalchemy import func, select, update
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError

from greyfit.service.jobs.store import api_keys

KEY_PREFIX = "gfk_"
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
NAME_RULE = "1 to 64 letters, digits, '.', '_' or '-', starting with a letter or digit"


@dataclass(frozen=True)
class Client:
    """Who sent a request. `owner`: the jobs.client value of the jobs it creates and sees; `sees_all`:
    an open server's anonymous caller, who sees every job."""

    name: str
    owner: str
    sees_all: bool = False

    @property
    def job_filter(self) -> Optional[str]:
        """The `client` argument of the job store's reads: None (every job) on an open server."""
        return None if self.sees_all else self.owner


LEGACY = Client("legacy", "")                   # the single GREYFIT_API_KEY, and jobs older than clients
ANONYMOUS = Client("anonymous", "", sees_all=True)   # a server without keys


class KeyRefused(ValueError):
    """A key operation refused (a bad or taken name, no such key): the message says why."""


def digest_of(key: bytes) -> str:
    return hashlib.sha256(key).hexdigest()


class KeyStore:
    """The named keys in the job store's `api_keys` table."""

    def __init__(self, engine: Engine):
        self.engine = engine

    def add(self, name: str) -> str:
        """A new key for `name`, returned once (only its digest is stored)."""
        if not NAME.match(name):
            raise KeyRefused(f"invalid key name {name!r}: {NAME_RULE}")
        key = KEY_PREFIX + secrets.token_urlsafe(32)
        try:
            with self.engine.begin() as conn:
                conn.execute(api_keys.insert().values(name=name, digest=digest_of(key.encode()),
                                                      created_at=time.time()))
        except IntegrityError:
            raise KeyRefused(f"a key named {name!r} exists already (revoked keys keep their name, so that "
                            "nobody else sees that client's jobs): choose another name") from None
        return key

    def revoke(self, name: str) -> None:
        with self.engine.begin() as conn:
            done = conn.execute(update(api_keys).where(api_keys.c.name == name, api_keys.c.revoked_at.is_(None))
                                .values(revoked_at=time.time())).rowcount
        if not done:
            raise KeyRefused(f"no active key named {name!r} (greyfit keys list shows them)")

    def entries(self) -> list[dict]:
        """Each key's name, creation and revocation times (never the key, nor its digest)."""
        with self.engine.connect() as conn:
            rows = conn.execute(select(api_keys.c.name, api_keys.c.created_at, api_keys.c.revoked_at)
                                .order_by(api_keys.c.created_at)).mappings().all()
        return [dict(r) for r in rows]

    def client_of(self, key: bytes) -> Optional[Client]:
        """The client whose active key this is, or None."""
        with self.engine.connect() as conn:
            name = conn.execute(select(api_keys.c.name).where(api_keys.c.digest == digest_of(key),
                                                              api_keys.c.revoked_at.is_(None))).scalar_one_or_none()
        return Client(name, name) if name is not None else None

    def any_keys(self) -> bool:
        """Whether a named key was ever made here (revoked ones count: revoking the last key must
        not open the server)."""
        with self.engine.connect() as conn:
            return conn.execute(select(func.count()).select_from(api_keys)).scalar_one() > 0
