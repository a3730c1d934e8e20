"""Dropping a cache's entries from a finalizer without ever waiting for the cache's lock.

A `weakref.finalize` callback runs inside whatever allocation set off the collection, possibly in
the thread that holds the cache's lock at that moment: a callback that waited for the lock would
wait for itself (a fit that stopped at 0 CPU on a futex), and one that took a reentrant lock could
change the cache in the middle of the holder's own change. So a drop is queued (a deque's append
needs no lock), done at once when the lock is free, and otherwise by the lock's next holder.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Any, Hashable, MutableMapping


class LaterDrops:
    """Keys to drop from `cache`, whose every change is made under `lock` (a non-reentrant Lock)."""

    def __init__(self, cache: MutableMapping[Any, Any], lock: threading.Lock):
        self.cache, self.lock = cache, lock
        self.pending: deque[Hashable] = deque()

    def drop(self, key: Hashable) -> None:
        """Queue `key`; drop it (and any queued before) now if nobody holds the lock.

        Parameters
        ----------
        key : hashable
            The cache's key.
        """
        self.pending.append(key)
        if self.lock.acquire(blocking=False):
            try:
                self.drain()
            finally:
                self.lock.release()

    def drain(self) -> None:
        """Drop every queued key; the caller holds the lock."""
        while self.pending:
            try:
                key = self.pending.popleft()
            except IndexError:
                return
            self.cache.pop(key, None)
