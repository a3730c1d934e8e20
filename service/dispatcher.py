"""The dispatcher thread: moves tasks from the job store (and synchronous fits) to the executor.

It never runs numerics itself; the event loop only waits on futures it resolves.

Three rules keep work honest:
- an outcome is written to the job store before the task is forgotten: if the write fails (the store
  is read-only for a while) it stays in `pending` and is written again each round;
- a task whose worker was lost (crash, kill) goes back to the queue until it has been started
  `task_max_attempts` times; one that hit its CPU or wall-time limit fails at once (it would again);
- job tasks keep `job_reserved_workers` workers while synchronous fits wait, so a burst of
  synchronous traffic cannot starve the jobs (with one worker the two alternate).
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
        self.pending: list[tuple[str, int, dict]] = []   # job outcomes not yet written to the store
        self._cancels: "queue.Queue[cf.Future]" = queue.Queue()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._last_pick = "job"
        self._no_jobs_until = 0.0

    # --- called from the web layer -------------------------------------------------------------
    def submit_sync(self, kind: str, request: dict) -> cf.Future:
        fut: cf.Future = cf.Future()
        self.sync.put((f"sync-{uuid.uuid4()}", kind, request, fut))
        self.wake()
        return fut

    def sync_waiting(self) -> int:
        return self.sync.qsize()

    def cancel_sync(self, fut: cf.Future, kind: str = "fit") -> None:
        """The caller gave up (timeout, disconnect): free the worker instead of finishing the fit."""
        if fut.cancel():              # still queued: it will never start
            self.metrics.count_fit(kind, "abandoned", None)
        else:                         # already running: the dispatcher thread stops it
            self._cancels.put(fut)
            self.wake()

    def wake(self) -> None:
        self._no_jobs_until = 0.0     # a new job may be waiting
        self._wake.set()
        self.executor.wake()

    def running_count(self) -> int:
        return len(self.running)

    def is_alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

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
        try:
            self._collect()           # outcomes that arrived meanwhile are kept, not re-run
        except Exception:
            log.exception("could not record the last outcomes at shutdown")
        self.executor.shutdown()
        # tasks we were running go back to the queue at once, without counting an attempt;
        # another server (or our restart) runs them
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
                self._stop.wait(min(1.0, self.settings.poll_seconds * 10))
            if not self._wake.is_set():
                try:
                    self.executor.wait(self.settings.poll_seconds)
                except Exception:  # e.g. a Dask timeout: just loop again
                    pass
            self._wake.clear()

    def _jobs_first(self) -> bool:
        """Whether the next free worker should look for a job task before a synchronous fit."""
        reserve = self.settings.job_reserved_workers
        if self.sync.empty() or reserve == 0:
            return self.sync.empty()
        capacity = self.executor.capacity()
        jobs_running = sum(1 for item in self.running.values() if item[0] == "job")
        if capacity > 1:
            return jobs_running < min(reserve, capacity - 1)
        return self._last_pick == "sync"   # one worker: alternate

    def _fill(self) -> None:
        while self.executor.free() > 0:
            order = (self._start_job_task, self._start_sync) if self._jobs_first() else \
                (self._start_sync, self._start_job_task)
            if not (order[0]() or order[1]()):
                return

    def _start_sync(self) -> bool:
        while True:
            try:
                key, kind, request, fut = self.sync.get_nowait()
            except queue.Empty:
                return False
            if fut.set_running_or_notify_cancel():     # False: the caller gave up while it waited
                self.running[key] = ("sync", fut, kind, time.monotonic())
                self.executor.submit(key, kind, request)
                self._last_pick = "sync"
                return True

    def _start_job_task(self) -> bool:
        if time.monotonic() < self._no_jobs_until:
            return False
        task = self.store.claim(self.owner, self.settings.lease_seconds, self.settings.task_max_attempts)
        if task is None:
            # look again at the next wake-up (a job created here) or poll (one created by a replica)
            self._no_jobs_until = time.monotonic() + self.settings.poll_seconds
            return False
        key = f"{task.job_id}:{task.idx}"
        self.running[key] = ("job", task.job_id, task.idx, task.kind, time.monotonic())
        self.executor.submit(key, task.kind, task.request)
        self._last_pick = "job"
        return True

    def _collect(self) -> None:
        for key, outcome in self.executor.poll():
            item = self.running.pop(key, None)
            if item is None:
                continue
            kind, t0 = item[-2], item[-1]
            self.metrics.count_fit(kind, outcome["status"], time.monotonic() - t0)
            error = outcome.get("error") or {}
            if error.get("type") == "InternalError":
                log.error("task %s (%s) failed with an internal error: %s\n%s", key, kind,
                          error.get("detail"), error.get("trace", ""))
            if item[0] == "sync":
                if not item[1].done():
                    item[1].set_result(outcome)
            else:
                self.pending.append((item[1], item[2], outcome))
        self._write_pending()

    def _write_pending(self) -> None:
        """Write job outcomes in order; what cannot be written now is kept for the next round."""
        while self.pending:
            job_id, idx, outcome = self.pending[0]
            error = outcome.get("error")
            if outcome["status"] == "failed" and error and error.get("retry"):
                status = self.store.release(job_id, idx, self.owner, self.settings.task_max_attempts, error)
                if status == "queued":
                    log.warning("task %s:%s re-queued: %s", job_id, idx, error.get("detail"))
            else:
                self.store.finish(job_id, idx, self.owner, outcome["status"], outcome.get("result_json"), error)
            self.pending.pop(0)

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
                        self.pending.append((job_id, item[2], {"status": "cancelled", "error": {
                            "type": "Cancelled", "field": None, "detail": "the job was cancelled"}}))
                self._write_pending()
