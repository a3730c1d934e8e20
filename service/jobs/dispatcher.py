"""The dispatcher thread: moves tasks from the job store (and synchronous fits) to the executor.

It never runs numerics itself; the event loop only waits on futures it resolves.

Three rules keep work honest:
- an outcome is written to the job store before the task is forgotten: if the write fails (the store
  is read-only for a while) it stays in `pending` and is written again each round;
- a task whose worker was lost (crash, kill, hang) goes back to the queue until it has been started
  `task_max_attempts` times; one that hit its CPU or wall-time limit fails at once (it would again);
  a start counts when its worker acknowledges it (written with the next outcomes), not at the claim:
  a server that dies between the two costs the task no attempt;
- job tasks keep `job_reserved_workers` workers while synchronous fits wait, so a burst of
  synchronous traffic cannot starve the jobs (with one worker the two alternate).

When fits take milliseconds, the job store's writes are what a batch waits for, so a free worker
gets its next task before anything is written: while tasks are short, about AHEAD_SECONDS of work
per worker is claimed ahead into `ready`, several tasks a transaction (long tasks stay in the store,
where any replica's free worker can take them), and about QUEUE_SECONDS of work (at least one task,
at most MAX_QUEUED) is queued behind the task each local worker runs, handed over in one message
per worker (`submit_batch`): a worker goes from one small fit to the next without waiting for this
thread, whose rounds then read several outcomes each. Outcomes are written together, at most
FLUSH_SECONDS after they arrived. A synchronous fit that arrives meanwhile waits for a worker's
queue to run out: about QUEUE_SECONDS (nothing more is queued while one waits).

A synchronous fit that finds a local worker idle (and nothing the dispatcher would give it first)
goes to it from the caller's thread: waking the dispatcher thread first, which then waits for the
interpreter lock the event loop holds, costs a good part of a millisecond, often several. The
dispatcher's rounds hold `_lock`; the caller only tries it and queues the fit as before if a round
(perhaps writing to the store) is under way: the event loop never waits for the store.
"""
from __future__ import annotations

import concurrent.futures as cf
import logging
import queue
import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass
from typing import Optional

from greyfit.service.jobs.outcome import Outcome, TaskError, lost
from greyfit.service.jobs.pool import QueueingPool, TaskRequest, WorkerPool
from greyfit.service.jobs.store import STORE_ERRORS, JobStore, TaskRow
from greyfit.service.metrics import Metrics
from greyfit.service.settings import Settings

log = logging.getLogger("greyfit.dispatcher")

FLUSH_SECONDS = 0.05      # longest an outcome waits to be written with others
FLUSH_COUNT = 32          # ... or until this many wait
AHEAD_SECONDS = 0.25      # work per worker claimed ahead while tasks are short (two or more fit in it)
MAX_AHEAD = 16            # tasks per worker claimed ahead at most
QUEUE_SECONDS = 0.1       # work queued on a local worker behind the task it runs, while tasks are short
MAX_QUEUED = 8            # tasks queued on a worker at most


CANCELLED = Outcome("cancelled", error=TaskError("Cancelled", "the job was cancelled"))


@dataclass(frozen=True)
class RunningTask:
    """A task handed to the executor: a job's (`task`, its row in the store) or a synchronous
    fit's (`future`, which its caller waits on)."""

    kind: str
    submitted: float   # monotonic time it was handed over: its duration when the worker gives none
    task: Optional[TaskRow] = None
    future: Optional[cf.Future[Outcome]] = None

    @property
    def job_id(self) -> Optional[str]:
        """The job it belongs to; None for a synchronous fit."""
        return None if self.task is None else self.task.job_id


def _key(task: TaskRow) -> str:
    return f"{task.job_id}:{task.idx}"


class Dispatcher:
    def __init__(self, store: JobStore, executor: WorkerPool, settings: Settings, metrics: Metrics):
        self.store, self.executor, self.settings, self.metrics = store, executor, settings, metrics
        # the executor's optional abilities, asked once: a local pool's queues and direct starts
        self._queueing: Optional[QueueingPool] = executor.queueing()
        self.owner = str(uuid.uuid4())
        self.sync: queue.Queue[tuple[str, str, TaskRequest, cf.Future[Outcome]]] = queue.Queue()
        self.running: dict[str, RunningTask] = {}
        self.pending: list[tuple[str, int, Outcome]] = []   # job outcomes not yet written to the store
        self.starts: list[tuple[str, int, float]] = []   # acknowledged starts not yet written (attempts)
        self._pending_since = 0.0
        self._flush_now = False
        self.ready: deque[TaskRow] = deque()   # job tasks claimed (leased to us) but not on a worker yet
        self._task_seconds: Optional[float] = None   # moving average of job tasks' wall time
        self._cancels: queue.Queue[cf.Future[Outcome]] = queue.Queue()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._lock = threading.Lock()   # the executor's workers and `running`: a round, or a direct start
        self._thread: Optional[threading.Thread] = None
        self._last_pick = "job"
        self._no_jobs_until = 0.0

    # --- called from the web layer -------------------------------------------------------------
    def submit_sync(self, kind: str, request: TaskRequest) -> cf.Future[Outcome]:
        fut: cf.Future[Outcome] = cf.Future()
        reason = self.executor.unready()
        if reason is not None:   # nothing would run it (a Dask cluster without workers): say so now
            fut.set_exception(RuntimeError(reason))
            return fut
        key = f"sync-{uuid.uuid4()}"
        if self._start_sync_now(key, kind, request, fut):
            return fut
        self.sync.put((key, kind, request, fut))
        self._wake.set()              # not wake(): no new job, so no need to look in the store
        self.executor.wake()
        return fut

    def _start_sync_now(self, key: str, kind: str, request: TaskRequest, fut: cf.Future[Outcome]) -> bool:
        """Start a synchronous fit on an idle worker now, where the dispatcher would: with a
        synchronous fit waiting it gives a free worker to a job task only if one is already claimed
        (`ready`), and to the first fit queued."""
        pool = self._queueing   # local workers only
        if pool is None or not self._lock.acquire(blocking=False):
            return False
        try:
            if self._stop.is_set() or not self.is_alive() or self.ready or not self.sync.empty() \
                    or not pool.can_start_now():
                return False
            fut.set_running_or_notify_cancel()
            self.running[key] = RunningTask(kind, time.monotonic(), future=fut)
            self._last_pick = "sync"
            try:
                self.executor.submit(key, kind, request)
            except OSError:   # the worker has just died: the next poll fails the fit (WorkerLost, 503)
                log.warning("synchronous fit %s: its worker was gone", key, extra={"task_id": key})
        finally:
            self._lock.release()
        return True   # no wake-up: the dispatcher waits on idle workers too (LocalWorkerPool.wait)

    def sync_waiting(self) -> int:
        """Synchronous fits waiting for a worker; one its caller gave up on no longer counts (the
        dispatcher drops it when it gets to it)."""
        with self.sync.mutex:
            return sum(1 for item in self.sync.queue if not item[3].cancelled())

    def cancel_sync(self, fut: cf.Future[Outcome], kind: str = "fit") -> None:
        """The caller gave up (timeout, disconnect): free the worker instead of finishing the fit."""
        if fut.cancel():              # still queued: it will never start
            self.metrics.count_fit(kind, "abandoned", None)
        else:                         # already running: the dispatcher thread stops it
            self._cancels.put(fut)
            self.wake()

    def wake(self) -> None:
        """A job was created or cancelled here: look at the store now."""
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
        # no synchronous fit starts directly from here on (_stop is set); a round that outlived the
        # join (a store that hangs) does not hold the shutdown longer
        locked = self._lock.acquire(timeout=10)
        try:
            self._stop_workers()
        finally:
            if locked:
                self._lock.release()

    def _stop_workers(self) -> None:
        try:
            self._collect()           # outcomes that arrived meanwhile are kept, not re-run
            self._write_pending()
        except Exception:
            log.exception("could not record the last outcomes at shutdown")
        self.executor.shutdown()
        # tasks we were running (or had claimed for the next free worker) go back to the queue at
        # once, without counting an attempt; another server (or our restart) runs them
        self.ready.clear()
        try:
            self.metrics.give_backs.labels("shutdown").inc(self.store.requeue_owned(self.owner))
        except STORE_ERRORS:
            # a store that is gone (an SQLite file deleted under the server) cannot take them back:
            # their leases run out and a live server requeues them; the shutdown itself must finish
            log.exception("could not hand the running tasks back at shutdown")
        for item in list(self.running.values()):
            if item.future is not None and not item.future.done():
                item.future.set_exception(RuntimeError("the server is shutting down"))

    # --- the loop --------------------------------------------------------------------------------
    def _loop(self) -> None:
        last_lease = last_cancel_check = 0.0
        while not self._stop.is_set():
            try:
                with self._lock:
                    now = time.monotonic()
                    self._collect()
                    self._cancel_abandoned()
                    self._fill()          # free workers first: what follows writes to the store
                    if now - last_lease > self.settings.lease_seconds / 3:
                        released = self.store.renew(self.owner, self.settings.lease_seconds, self._held())
                        if released:
                            log.warning("gave back %d task(s) claimed by a claim whose outcome was lost", released)
                            self.metrics.give_backs.labels("lost_claim").inc(released)
                        self.metrics.give_backs.labels("expired").inc(self.store.requeue_expired())
                        last_lease = now
                    if now - last_cancel_check > 0.25:
                        self._stop_cancelled()
                        last_cancel_check = now
                    self._write_pending(flush=False)
                    self._claim_more()
            except Exception as exc:  # the loop must survive a database hiccup
                log.exception("dispatcher iteration failed")
                if isinstance(exc, STORE_ERRORS):
                    self.metrics.store_errors.labels("dispatcher").inc()
                self._stop.wait(min(1.0, self.settings.poll_seconds * 10))
            if not self._wake.is_set():
                timeout = self.settings.poll_seconds
                if self.pending or self.starts:   # wake up in time to write them (a failed write: after the pause)
                    timeout = max(0.0, min(timeout, self._pending_since + FLUSH_SECONDS - time.monotonic()))
                try:
                    self.executor.wait(timeout)
                except Exception:  # e.g. a Dask timeout: just loop again
                    pass
            self._wake.clear()

    def _jobs_first(self) -> bool:
        """Whether the next free worker should look for a job task before a synchronous fit."""
        reserve = self.settings.job_reserved_workers
        if self.sync.empty() or reserve == 0:
            return self.sync.empty()
        capacity = self.executor.capacity()
        jobs_running = sum(1 for item in self.running.values() if item.task is not None)
        if capacity > 1:
            return jobs_running < min(reserve, capacity - 1)
        return self._last_pick == "sync"   # one worker: alternate

    def _fill(self) -> None:
        while self.executor.free() > 0:
            order = (self._start_job_task, self._start_sync) if self._jobs_first() else \
                (self._start_sync, self._start_job_task)
            if not (order[0]() or order[1]()):
                break
        # job tasks shorter than AHEAD_SECONDS also queue behind running ones (the hand-over is then
        # no longer a few per cent of a task), unless synchronous fits wait for a worker
        self._set_depth()
        if self._ahead_per_worker() >= 1 and self.sync.empty():
            room = self.executor.queue_room()
            if room > 0:
                if not self.ready:
                    self._claim(room)
                self._queue_job_tasks(room)

    def _set_depth(self) -> None:
        """Tasks a local worker holds: the one it runs and about QUEUE_SECONDS of work behind it."""
        pool = self._queueing
        if pool is None:
            return
        queued = 1   # one behind, while the tasks' length is not known or they are long
        if self._task_seconds is not None and self._ahead_per_worker() >= 1:
            queued = max(1, min(MAX_QUEUED, int(QUEUE_SECONDS / max(self._task_seconds, 1e-6))))
        pool.depth = 1 + queued
        pool.task_seconds = self._task_seconds

    def _queue_job_tasks(self, room: int) -> None:
        """Up to `room` claimed tasks behind the running ones, one message per worker where the
        executor takes batches."""
        batch = [self.ready.popleft() for _ in range(min(room, len(self.ready)))]
        if not batch:
            return
        now = time.monotonic()
        for task in batch:
            self.running[_key(task)] = RunningTask(task.kind, now, task=task)
        self._last_pick = "job"
        pool = self._queueing
        if pool is None:
            for task in batch:
                self.executor.submit(_key(task), task.kind, task.request)
            return
        left = pool.submit_batch([(_key(task), task.kind, task.request) for task in batch])
        for key, _, _ in reversed(left):   # no room after all (a worker was replaced): back in line
            row = self.running.pop(key).task
            assert row is not None   # (the batch holds job tasks only)
            self.ready.appendleft(row)

    def _start_sync(self) -> bool:
        while True:
            try:
                key, kind, request, fut = self.sync.get_nowait()
            except queue.Empty:
                return False
            if fut.set_running_or_notify_cancel():     # False: the caller gave up while it waited
                self.running[key] = RunningTask(kind, time.monotonic(), future=fut)
                self.executor.submit(key, kind, request)
                self._last_pick = "sync"
                return True

    def _claim(self, limit: int) -> None:
        if limit <= 0 or time.monotonic() < self._no_jobs_until:
            return
        claimed = self.store.claim_many(self.owner, self.settings.lease_seconds, self.settings.task_max_attempts,
                                        limit)
        if not claimed:
            # look again at the next wake-up (a job created here) or poll (one created by a replica)
            self._no_jobs_until = time.monotonic() + self.settings.poll_seconds
        self.ready.extend(claimed)

    def _ahead_per_worker(self) -> int:
        """Job tasks per worker worth claiming ahead: 0 for long tasks (or not known yet); 1, just
        the one queued behind a worker's task; 2 or more, also some in `ready`. A claim per task
        costs little beside long tasks, and claiming ahead holds tasks other replicas could run."""
        if self._task_seconds is None:
            return 0
        return min(MAX_AHEAD, int(AHEAD_SECONDS / max(self._task_seconds, 1e-6)))

    def _claim_more(self) -> None:
        """After the free workers got their tasks: look in the store for job tasks if synchronous
        fits wait (they did not wait for that), and while tasks are short keep about AHEAD_SECONDS
        of work per worker claimed, so that a worker that finishes starts its next task without
        waiting for the store; refilled when half of it is gone, so each claim takes several tasks."""
        per_worker = self._ahead_per_worker()
        if per_worker < 2:
            if not self.ready and not self.sync.empty():
                self._claim(1)   # a job task found gets the next free worker (job_reserved_workers)
            return
        target = per_worker * self.executor.capacity()
        if len(self.ready) <= target // 2:
            self._claim(target - len(self.ready))
            self._fill()

    def _start_job_task(self) -> bool:
        if not self.ready:
            if not self.sync.empty():   # no store read before a waiting synchronous fit: _claim_more
                return False
            self._claim(self.executor.free())
            if not self.ready:
                return False
        task = self.ready.popleft()
        self.running[_key(task)] = RunningTask(task.kind, time.monotonic(), task=task)
        self.executor.submit(_key(task), task.kind, task.request)
        self._last_pick = "job"
        return True

    def _collect(self) -> None:
        outcomes = self.executor.poll()
        for key in self.executor.started():   # before the outcomes: a start is charged before its release
            self._add_start(key)
        for key, outcome in outcomes:
            item = self.running.pop(key, None)
            if item is None:
                continue
            if outcome.status == "not_started":   # its worker was replaced before it began
                if item.task is not None:
                    self.ready.appendleft(item.task)
                    continue
                # (synchronous fits only go to a free worker, so never queue behind another)
                outcome = lost("the worker process was replaced; retry")
            if outcome.is_retry:
                self.metrics.worker_losses.labels(item.kind).inc()
            # the worker's count: not queued time
            seconds = outcome.seconds if outcome.seconds is not None else time.monotonic() - item.submitted
            self.metrics.count_fit(item.kind, outcome.status, seconds)
            error = outcome.error
            if error is not None and error.type == "InternalError":
                log.error("task %s (%s) failed with an internal error: %s\n%s", key, item.kind,
                          error.detail, error.trace or "", extra={"task_id": key})
            if item.future is not None:
                if not item.future.done():
                    item.future.set_result(outcome)
            elif item.task is not None:
                self._task_seconds = seconds if self._task_seconds is None else \
                    0.8 * self._task_seconds + 0.2 * seconds
                self._add_pending(item.task.job_id, item.task.idx, outcome)
                if not self._has_tasks(item.task.job_id):   # perhaps the job's last: its caller waits for it
                    self._flush_now = True

    def _add_start(self, key: str) -> None:
        item = self.running.get(key)
        if item is None or item.task is None:
            return
        if not self.pending and not self.starts:
            self._pending_since = time.monotonic()
        self.starts.append((item.task.job_id, item.task.idx, time.time()))

    def _running_jobs(self) -> list[TaskRow]:
        return [item.task for item in self.running.values() if item.task is not None]

    def _held(self) -> list[tuple[str, int]]:
        """The job tasks this dispatcher knows it owns: on a worker, claimed ahead, or not yet written."""
        return ([(t.job_id, t.idx) for t in self._running_jobs()]
                + [(t.job_id, t.idx) for t in self.ready] + [(job_id, idx) for job_id, idx, _ in self.pending])

    def _has_tasks(self, job_id: str) -> bool:
        return any(item.job_id == job_id for item in self.running.values()) or \
            any(t.job_id == job_id for t in self.ready)

    def _add_pending(self, job_id: str, idx: int, outcome: Outcome) -> None:
        if not self.pending:
            self._pending_since = time.monotonic()
        self.pending.append((job_id, idx, outcome))

    def _write_pending(self, flush: bool = True) -> None:
        """Write job outcomes; what cannot be written now is kept for the next round.

        Unless `flush`, they wait until FLUSH_COUNT of them wait, the oldest is FLUSH_SECONDS old,
        or one may be its job's last: one transaction for several outcomes."""
        if not (self.pending or self.starts) or (
                not flush and not self._flush_now and len(self.pending) < FLUSH_COUNT
                and time.monotonic() - self._pending_since < FLUSH_SECONDS):
            return
        self._flush_now = False
        retried = [p for p in self.pending if p[2].is_retry]
        finished = [p for p in self.pending if not p[2].is_retry]
        # the starts with the outcomes, in one transaction, before the releases: a release reads the attempts
        self.store.finish_many(self.owner, [(job_id, idx, o.status, o.result_json, o.error_dict())
                                            for job_id, idx, o in finished], started=self.starts)
        self.starts = []
        self.pending = retried
        for job_id, idx, outcome in retried:
            error = outcome.error
            assert error is not None   # (a retry is a failure)
            status = self.store.release(job_id, idx, self.owner, self.settings.task_max_attempts, error.as_dict())
            if status == "queued":
                self.metrics.give_backs.labels("lost_worker").inc()
                log.warning("task %s:%s re-queued: %s", job_id, idx, error.detail,
                            extra={"task_id": f"{job_id}:{idx}"})
            self.pending.remove((job_id, idx, outcome))
        self._pending_since = time.monotonic()

    def _cancel_abandoned(self) -> None:
        while True:
            try:
                fut = self._cancels.get_nowait()
            except queue.Empty:
                return
            for key, item in list(self.running.items()):
                if item.future is fut:
                    self.executor.cancel(key)
                    self.running.pop(key)
                    self.metrics.count_fit(item.kind, "abandoned", None)

    def _stop_cancelled(self) -> None:
        jobs = {t.job_id for t in self._running_jobs()} | {t.job_id for t in self.ready}
        for job_id in jobs:
            if self.store.is_cancelled(job_id):
                for key, item in list(self.running.items()):
                    if item.task is not None and item.task.job_id == job_id:
                        self.executor.cancel(key)
                        self.running.pop(key)
                        self._add_pending(job_id, item.task.idx, CANCELLED)
                for task in [t for t in self.ready if t.job_id == job_id]:
                    self.ready.remove(task)
                    self._add_pending(job_id, task.idx, CANCELLED)
                self._write_pending()
