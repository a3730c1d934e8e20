"""The dispatcher thread: moves tasks from the job store (and synchronous fits) to the executor.

It never runs numerics itself; the event loop only waits on futures it resolves.
"""
from __future__ import annotations

import concurrent.futures as cf
import logging
import queue
import threading
import time
import uuid
from typing import Optional

from service.metrics import Metrics
from service.settings import Settings
from service.store import JobStore

log = logging.getLogger("greyfit.dispatcher")


class Dispatcher:
    def __init__(self, store: JobStore, executor, settings: Settings, metrics: Metrics):
        self.store, self.executor, self.settings, self.metrics = store, executor, settings, metrics
        self.owner = str(uuid.uuid4())
        self.sync: "queue.Queue[tuple[str, str, dict, cf.Future]]" = queue.Queue()
        self.running: dict[str, tuple] = {}   # key -> ("job", job_id, idx, kind, t0) | ("sync", future, kind, t0)
        self._cancels: "queue.Queue[cf.Future]" = queue.Queue()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: Optional[threading.Thread] = None

    # --- called from the web layer -------------------------------------------------------------
    def submit_sync(self, kind: str, request: dict) -> cf.Future:
        fut: cf.Future = cf.Future()
        self.sync.put((f"sync-{uuid.uuid4()}", kind, request, fut))
        self.wake()
        return fut

    def cancel_sync(self, fut: cf.Future) -> None:
        """The caller gave up (timeout, disconnect): free the worker instead of finishing the fit."""
        if not fut.cancel():          # already running: the dispatcher thread stops it
            self._cancels.put(fut)
            self.wake()

    def wake(self) -> None:
        self._wake.set()
        self.executor.wake()

    def running_count(self) -> int:
        return len(self.running)

    # --- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        requeued = self.store.requeue_expired()
        if requeued:
            log.warning("re-queued %d task(s) whose server had stopped", requeued)
        self._thread = threading.Thread(target=self._loop, name="greyfit-dispatcher", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.wake()
        if self._thread:
            self._thread.join(timeout=10)
        self.executor.shutdown()
        # tasks we were running go back to the queue at once; another server (or our restart) runs them
        self.store.requeue_owned(self.owner)
        for item in list(self.running.values()):
            if item[0] == "sync" and not item[1].done():
                item[1].set_exception(RuntimeError("the server is shutting down"))

    # --- the loop --------------------------------------------------------------------------------
    def _loop(self) -> None:
        last_lease = last_cancel_check = 0.0
        while not self._stop.is_set():
            try:
                now = time.monotonic()
                self._collect()
                self._cancel_abandoned()
                if now - last_lease > self.settings.lease_seconds / 3:
                    self.store.renew(self.owner, self.settings.lease_seconds)
                    self.store.requeue_expired()
                    last_lease = now
                if now - last_cancel_check > 0.25:
                    self._stop_cancelled()
                    last_cancel_check = now
                self._fill()
            except Exception:  # the loop must survive a database hiccup
                log.exception("dispatcher iteration failed")
                time.sleep(1.0)
            if not self._wake.is_set():
                try:
                    self.executor.wait(self.settings.poll_seconds)
                except Exception:  # e.g. a Dask timeout: just loop again
                    pass
            self._wake.clear()

    def _fill(self) -> None:
        while self.executor.free() > 0:
            try:
                key, kind, request, fut = self.sync.get_nowait()
                if fut.set_running_or_notify_cancel():
                    self.running[key] = ("sync", fut, kind, time.monotonic())
                    self.executor.submit(key, kind, request)
                continue
            except queue.Empty:
                pass
            task = self.store.claim(self.owner, self.settings.lease_seconds, self.settings.task_max_attempts)
            if task is None:
                return
            key = f"{task.job_id}:{task.idx}"
            self.running[key] = ("job", task.job_id, task.idx, task.kind, time.monotonic())
            self.executor.submit(key, task.kind, task.request)

    def _collect(self) -> None:
        for key, outcome in self.executor.poll():
            item = self.running.pop(key, None)
            if item is None:
                continue
            kind, t0 = item[-2], item[-1]
            self.metrics.count_fit(kind, outcome["status"], time.monotonic() - t0)
            if item[0] == "sync":
                if not item[1].done():
                    item[1].set_result(outcome)
            else:
                self.store.finish(item[1], item[2], self.owner, outcome["status"],
                                  outcome.get("result_json"), outcome.get("error"))

    def _cancel_abandoned(self) -> None:
        while True:
            try:
                fut = self._cancels.get_nowait()
            except queue.Empty:
                return
            for key, item in list(self.running.items()):
                if item[0] == "sync" and item[1] is fut:
                    self.executor.cancel(key)
                    self.running.pop(key)
                    self.metrics.count_fit(item[2], "abandoned", None)

    def _stop_cancelled(self) -> None:
        jobs = {item[1] for item in self.running.values() if item[0] == "job"}
        for job_id in jobs:
            if self.store.is_cancelled(job_id):
                for key, item in list(self.running.items()):
                    if item[0] == "job" and item[1] == job_id:
                        self.executor.cancel(key)
                        self.running.pop(key)
                        self.store.finish(job_id, item[2], self.owner, "cancelled", None,
                                          {"type": "Cancelled", "field": None, "detail": "the job was cancelled"})
