"""Fits as tasks on a Dask distributed cluster (GREYFIT_EXECUTOR=dask): the scale-out executor.

It answers the dispatcher's `WorkerPool` Protocol (service/jobs/pool.py), as the local worker pool does. Three things
a Dask cluster does not tell a client by itself are made explicit here:

- **When a task starts.** The scheduler queues a task until a worker thread is free, which may be
  long after its submission. The task, once on a worker, logs an event on START_TOPIC; the client
  receives it (pub/sub through the scheduler) and only then starts the task's wall clock and reports
  the start (the attempt is charged). A task waiting for a worker therefore never fails as
  `Timeout`, whatever it waits for.
- **That nothing can run it.** With the scheduler out of reach or no worker in the cluster, tasks not
  started yet are answered at once as lost workers (`retry`): a job task goes back to the queue without
  an attempt charged (it never started), a synchronous fit gets 503 + Retry-After instead of waiting.
  `free()` is 0 meanwhile, so nothing new is handed to the cluster.
- **That the scheduler came back.** A client gives up reconnecting after its timeout and stays closed;
  a closed client is replaced by a new one, made in a background thread (the dispatcher never blocks
  on it), until the scheduler answers. Dask workers end when their scheduler is lost:
  `python -m greyfit.service.dask_worker` runs one that starts again and waits for its scheduler.

The worker's CPU time cannot be capped per task inside a shared Dask worker, so the fit's own
Ipopt `max_cpu_time` and the wall-time limit (the future is cancelled) bound it instead.
"""
from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Any, Optional

from greyfit.service.jobs.outcome import Outcome, lost, timed_out
from greyfit.service.jobs.pool import QueueingPool, TaskRequest
from greyfit.service.jobs.tasks import run_task

log = logging.getLogger("greyfit.dask")

START_TOPIC = "greyfit-task-start"
RECONNECT_PAUSE = 1.0     # between two attempts of the background reconnection
CLUSTER_INFO_SECONDS = 1.0   # the cluster's worker and thread counts are read from the scheduler this often


def run_on_worker(dask_key: str, kind: str, request: TaskRequest, cpu_seconds: float) -> Outcome:
    """Run one task on a Dask worker, saying first that it started.

    Parameters
    ----------
    dask_key : str
        The task's Dask key, which the start event names (the client maps it back to its task).
    kind : str
        The task kind (service/task_kinds.py).
    request : dict or str
        The task's request, as JSON text or a dict.
    cpu_seconds : float
        The CPU-time limit, passed to the fit's own Ipopt `max_cpu_time`.

    Returns
    -------
    Outcome
        The task's outcome, with the seconds it ran.
    """
    from distributed import get_worker

    get_worker().log_event(START_TOPIC, {"key": dask_key})
    started = time.monotonic()
    return replace(run_task(kind, request, cpu_seconds), seconds=time.monotonic() - started)


@dataclass
class _Submitted:
    future: Any
    dask_key: str
    started: Optional[float] = None   # monotonic time its start event arrived; None while it waits


class DaskExecutor:
    """Fits as tasks on a Dask distributed cluster (scheduler address from the settings)."""

    replaced = 0   # the cluster replaces its own workers: none here (/metrics)

    def __init__(self, address: str, cpu_seconds: float, wall_seconds: float, capacity: int | None = None,
                 connect_seconds: float = 30.0):
        self.address, self.connect_seconds = address, connect_seconds
        self.cpu_seconds, self.wall_seconds = cpu_seconds, wall_seconds
        self._capacity = capacity
        self.futures: dict[str, _Submitted] = {}
        self._by_dask_key: dict[str, str] = {}
        self._start_events: deque[str] = deque()   # appended by the client's thread, read by the dispatcher's
        self._started: list[str] = []
        self._subscribed_comm: Any = None
        self._counter = itertools.count()
        self._closing = threading.Event()
        self._reconnecting: Optional[threading.Thread] = None
        self._info: dict = {}
        self._info_at = -CLUSTER_INFO_SECONDS
        self.client = self._connect()   # the first connection fails the server's start: a wrong address
        self._subscribe()

    # --- the connection ---------------------------------------------------------------------------
    def _connect(self):
        from distributed import Client
        return Client(self.address, set_as_default=False, timeout=self.connect_seconds)

    def _on_start(self, event: tuple) -> None:
        self._start_events.append(event[1]["key"])

    def _subscribe(self) -> None:
        """Subscribe to the start events on the current connection: a restarted scheduler knows no
        subscription, and a reconnected client does not renew its own."""
        comm = self.client.scheduler_comm
        if self.client.status == "running" and comm is not self._subscribed_comm:
            self.client.subscribe_topic(START_TOPIC, self._on_start)
            self._subscribed_comm = comm

    def _reconnect_in_background(self) -> None:
        if self._closing.is_set() or (self._reconnecting and self._reconnecting.is_alive()):
            return

        def reconnect() -> None:
            while not self._closing.is_set():
                try:
                    client = self._connect()
                except (OSError, TimeoutError) as exc:
                    log.warning("the Dask scheduler does not answer yet (%s); trying again", exc)
                    self._closing.wait(RECONNECT_PAUSE)
                    continue
                if self._closing.is_set():
                    client.close()
                    return
                self.client, self._info_at = client, -CLUSTER_INFO_SECONDS
                log.warning("connected to the Dask scheduler again")
                return

        self._reconnecting = threading.Thread(target=reconnect, name="greyfit-dask-reconnect", daemon=True)
        self._reconnecting.start()

    def _cluster(self) -> dict:
        """The scheduler's counts of workers and threads, asked for at most every CLUSTER_INFO_SECONDS
        (the dispatcher asks several times a round, readiness probes too; each ask is a round trip)."""
        now = time.monotonic()
        # (without a scheduler the ask would wait for the connection timeout: the last answer stands)
        if now - self._info_at >= CLUSTER_INFO_SECONDS and self.client.status == "running":
            self._info = dict(self.client.scheduler_info(n_workers=0))
            self._info_at = now
        return self._info

    # --- what the dispatcher asks -----------------------------------------------------------------
    def unready(self) -> Optional[str]:
        """Why the cluster cannot run tasks now (readiness), or None: its scheduler out of reach
        (the client's own state: no round trip), or no workers."""
        if self.client.status != "running":
            return f"the Dask scheduler does not answer (client {self.client.status})"
        if not self._cluster().get("n_workers"):
            return "the Dask cluster has no workers"
        return None

    def capacity(self) -> int:
        if self._capacity:
            return self._capacity
        return max(1, int(self._cluster().get("total_threads") or 1))

    def free(self) -> int:
        if self.unready() is not None:   # nothing handed out that nothing would run
            return 0
        return self.capacity() - len(self.futures)

    def queue_room(self) -> int:
        return 0   # the scheduler queues; a task is submitted when a thread is free

    def queueing(self) -> Optional[QueueingPool]:
        """None: the scheduler queues the tasks, a worker holds none behind its own."""
        return None

    def submit(self, key: str, kind: str, request: TaskRequest) -> None:
        self._subscribe()   # before the task: its start event must find the subscription
        dask_key = f"greyfit-{key}-{time.time_ns()}-{next(self._counter)}"
        fut = self.client.submit(run_on_worker, dask_key, kind, request, self.cpu_seconds, pure=False,
                                 key=dask_key)
        self.futures[key] = _Submitted(fut, dask_key)
        self._by_dask_key[dask_key] = key

    def started(self) -> list[str]:
        """The keys whose start a worker reported since the last call (read by poll())."""
        keys, self._started = self._started, []
        return keys

    def _take_starts(self) -> None:
        now = time.monotonic()
        while self._start_events:
            key = self._by_dask_key.get(self._start_events.popleft())
            entry = self.futures.get(key) if key else None
            if key and entry is not None and entry.started is None:   # (a forgotten submission's: ignored)
                entry.started = now
                self._started.append(key)

    def _forget(self, key: str) -> _Submitted:
        entry = self.futures.pop(key)
        self._by_dask_key.pop(entry.dask_key, None)
        return entry

    def poll(self) -> list[tuple[str, Outcome]]:
        if self.client.status == "closed" and not self._closing.is_set():
            self._reconnect_in_background()
        self._subscribe()
        self._take_starts()
        unready = self.unready()
        done: list[tuple[str, Outcome]] = []
        for key, entry in list(self.futures.items()):
            fut = entry.future
            if fut.done():
                self._forget(key)
                try:
                    done.append((key, fut.result()))
                except Exception as exc:  # the worker died, the scheduler was lost, or the task errored there
                    done.append((key, lost(f"dask: {type(exc).__name__}: {exc}")))
            elif entry.started is None and unready is not None:
                self._cancel_quietly(fut)
                self._forget(key)
                done.append((key, lost(f"{unready}: nothing can start the task now")))
            elif entry.started is not None and time.monotonic() - entry.started > self.wall_seconds:
                self._cancel_quietly(fut)
                self._forget(key)
                done.append((key, timed_out(f"exceeded the wall-time limit of {self.wall_seconds:g} s")))
        return done

    def wait(self, timeout: float) -> None:
        futures = [entry.future for entry in self.futures.values()]
        if futures and self.client.status == "running":
            from distributed import wait as dask_wait
            try:
                dask_wait(futures, timeout=timeout, return_when="FIRST_COMPLETED")
            except TimeoutError:
                pass
        else:
            time.sleep(timeout)

    def wake(self) -> None:
        pass

    @staticmethod
    def _cancel_quietly(fut) -> None:
        try:
            fut.cancel()
        except Exception:   # a client that lost its scheduler cannot tell it; the task is forgotten anyway
            log.debug("could not cancel %s on the Dask cluster", fut.key, exc_info=True)

    def cancel(self, key: str) -> bool:
        if key not in self.futures:
            return False
        self._cancel_quietly(self._forget(key).future)
        return True

    def shutdown(self) -> None:
        self._closing.set()
        for entry in self.futures.values():
            self._cancel_quietly(entry.future)
        self.client.close()
