"""Where fits run: persistent local worker processes (default) or a Dask cluster (scale-out).

Both answer the dispatcher's `WorkerPool` Protocol (service/jobs/pool.py): `capacity()`, `free()`,
`queue_room()`, `submit(key, kind, request)`, `poll() -> [(key, Outcome)]`, `started() -> [key]`,
`cancel(key)`, `shutdown()`; the local pool is also a `QueueingPool` (`queueing()` says so).

A failed outcome whose error carries `retry` lost its worker to something outside the task
(a crash, a kill, a lost Dask worker): the dispatcher runs the task again. A task that hit its CPU
or wall-time limit is not retried: it would hit it again.

A local worker can hold tasks queued behind the one it runs, up to `depth` in all (`queue_room()`
counts the places left in busy workers), so that it starts the next the moment it finishes, not
after the dispatcher has read its answer: with fits of milliseconds that hand-over is a good part
of the time. `submit_batch` hands several tasks to a worker in one message, and a worker's answer
to one task carries the start of the next, so a batch of small fits costs one message per task and
its outcomes are read together. Each outcome is sent the moment its task ends: a worker lost
mid-batch loses only the task it was running (retried, its start already charged), and the tasks
queued behind it come back as `Outcome("not_started")`, for the dispatcher to hand out again,
uncharged. A queued task can be withdrawn.
"""
from __future__ import annotations

import multiprocessing as mp
import multiprocessing.connection as mp_connection
import os
import resource
import signal
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional, Union

from greyfit.service.jobs.lifeline import WorkerRegistry, die_with_parent, start_process
from greyfit.service.jobs.outcome import Outcome, lost, timed_out
from greyfit.service.jobs.pool import QueueingPool, Submission, TaskRequest, WorkerPool
from greyfit.service.jobs.tasks import run_task
from greyfit.service.settings import Settings

# a worker's message to the pool: (key, STARTED) when it begins a task, (key, outcome) when it ends
STARTED = "started"
Reply = tuple[str, Union[Outcome, str]]

# one worker process per core does the parallel work: BLAS threads of their own would only fight
# over the same cores (an operator's own setting wins)
SINGLE_THREADED = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _take(msg: Any, todo: deque[Submission], conn: mp_connection.Connection) -> bool:
    """A message to a worker: a task (key, kind, request), a list of tasks (a batch), (key,) to
    withdraw a task not started yet, or None to stop (returns False)."""
    if msg is None:
        return False
    if isinstance(msg, list):
        todo.extend(msg)
    elif len(msg) == 1:
        for task in todo:
            if task[0] == msg[0]:
                todo.remove(task)
                conn.send((msg[0], Outcome("withdrawn")))
                break
    else:
        todo.append(msg)
    return True


def _worker_main(conn: mp_connection.Connection, cpu_seconds: float, parent_pid: Optional[int] = None) -> None:
    """Loop of one local worker process: receive tasks, run each under a CPU-time limit, reply."""
    if parent_pid is not None:
        die_with_parent(parent_pid)   # a server killed with SIGKILL takes its workers with it
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C stops the server, which stops us
    import greyfit.solvers.fit  # noqa: F401  (import CasADi once, not per task)
    todo: deque[Submission] = deque()
    done: list[Reply] = []   # the last outcome, sent with the next start: one message per task of a batch
    while True:
        try:
            while conn.poll():        # read everything sent meanwhile: a withdrawal comes after its task
                if not _take(conn.recv(), todo, conn):
                    _stop(conn, done)
                    return
            if not todo:
                if done:              # nothing next: the outcome goes alone, now
                    conn.send(done)
                    done = []
                if not _take(conn.recv(), todo, conn):
                    _stop(conn, done)
                    return
                continue
        except EOFError:
            return
        key, kind, request = todo.popleft()
        # the acknowledged start (the attempt is charged now), with the outcome before it
        conn.send([*done, (key, STARTED)])
        done = []
        used = resource.getrusage(resource.RUSAGE_SELF)
        spent = used.ru_utime + used.ru_stime
        soft = int(spent + cpu_seconds) + 1
        # only the soft limit moves (raising a hard limit needs privileges): SIGXCPU ends the worker
        hard = resource.getrlimit(resource.RLIMIT_CPU)[1]
        if hard != resource.RLIM_INFINITY:
            soft = min(soft, hard)
        resource.setrlimit(resource.RLIMIT_CPU, (soft, hard))
        started = time.monotonic()
        outcome = run_task(kind, request, cpu_seconds)
        done = [(key, replace(outcome, seconds=time.monotonic() - started))]


def _stop(conn: mp_connection.Connection, done: list[Reply]) -> None:
    """A graceful stop: the last outcome goes, and compiles started in the background finish, so
    the next process finds their libraries on disk (the pool waits for that as long as its
    `shutdown(grace)` says; the server's 2 s, `greyfit batch` a compile's own limit)."""
    if done:
        conn.send(done)
    from greyfit.solvers.dynamics.compiled import COMPILE_TIMEOUT_S, wait_for_builds
    wait_for_builds(COMPILE_TIMEOUT_S)


def _death_reason(code: Optional[int], cpu_seconds: float) -> Outcome:
    """Why a worker ended mid-task. RLIMIT_CPU's soft limit sends SIGXCPU (the hard limit is not
    set), so SIGKILL is someone else: the OOM killer or an operator. That, and any crash, is retried."""
    if code == -signal.SIGXCPU:
        return timed_out(f"exceeded the CPU-time limit of {cpu_seconds:g} s")
    how = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 and \
        -code in signal.valid_signals() else f"exit code {code}"
    return lost(f"the worker process died ({how}): killed or crashed, not a fault of this request")


def _cpu_seconds_of(pid: int) -> Optional[float]:
    """A process's CPU time (user + system) from /proc, or None where there is no /proc."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS   # utime, stime (fields 14, 15)


_CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
STALL_CHECK_SECONDS = 1.0   # how often a busy worker's CPU clock is read


@dataclass
class _Slot:
    process: Any   # a multiprocessing Process of the spawn context
    conn: mp_connection.Connection
    keys: list[str] = field(default_factory=list)   # the task it runs, then those queued behind (`depth`)
    started: float = 0.0                        # when the task it runs started (about; exact once acknowledged)
    cpu: Optional[float] = None                 # the worker's CPU time when last read ...
    progressed: float = 0.0                     # ... and when it last had moved
    checked: float = 0.0


class LocalWorkerPool:
    """A fixed number of worker processes; a task that overruns or crashes costs only its worker."""

    def __init__(self, workers: int, cpu_seconds: float, wall_seconds: float,
                 stall_seconds: Optional[float] = 60.0, registry: Optional[WorkerRegistry] = None):
        self.ctx = mp.get_context("spawn")
        self.registry = registry
        if registry is not None:
            registry.sweep()   # workers a killed server on this data folder left running
        self.stall_seconds = stall_seconds
        for name, value in SINGLE_THREADED.items():   # spawned workers inherit the environment
            os.environ.setdefault(name, value)
        self.cpu_seconds = cpu_seconds
        self.wall_seconds = wall_seconds
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._returned: list[tuple[str, Outcome]] = []   # tasks given back by a replaced worker
        self._started: list[str] = []                    # starts acknowledged, not yet taken (started())
        # tasks a worker holds: the one it runs and those queued behind it (the dispatcher raises it
        # for short tasks; 2, one queued, while their length is not known)
        self.depth = 2
        self.task_seconds: Optional[float] = None   # a task's usual length, when the dispatcher knows it
        self.slots = [self._spawn() for _ in range(workers)]

    def wait(self, timeout: float) -> None:
        """Block until a worker replies or dies, `wake()` is called, or the timeout passes.

        Idle workers too: a task handed to one meanwhile (a synchronous fit started by the web
        thread) is then heard from without a wake-up, which would cost the running fit CPU on a
        busy machine; an idle worker that dies is replaced at once. (An idle worker sends nothing:
        every reply answers a key of its slot.) A worker with more than one task queued behind its
        own is not listened to while `task_seconds` says it has work left: its outcomes are read
        together, a round of the dispatcher for several of them, not one each."""
        handles = [s.process.sentinel for s in self.slots] + [self._wake_r]
        for s in self.slots:
            if self.task_seconds and len(s.keys) > 2:
                # a deep queue: its outcomes are read together, before the worker can run dry
                timeout = min(timeout, (len(s.keys) - 2) * self.task_seconds)
            else:
                handles.append(s.conn)
        ready = mp_connection.wait(handles, timeout=0 if self._returned else timeout)
        if self._wake_r in ready:
            os.read(self._wake_r, 4096)

    def wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except BlockingIOError:
            pass   # the pipe is full of wake-ups already

    def _spawn(self) -> _Slot:
        parent, child = self.ctx.Pipe()
        proc = self.ctx.Process(target=_worker_main, args=(child, self.cpu_seconds, os.getpid()), daemon=True)
        start_process(proc)
        child.close()
        if self.registry is not None and proc.pid is not None:   # (a started process has its pid)
            self.registry.record(proc.pid)
        return _Slot(proc, parent)

    def capacity(self) -> int:
        return len(self.slots)

    def free(self) -> int:
        return sum(1 for s in self.slots if not s.keys)

    def queue_room(self) -> int:
        """Places left behind the tasks of busy workers: each holds up to `depth` tasks in all."""
        return sum(max(0, self.depth - len(s.keys)) for s in self.slots if s.keys)

    def submit_batch(self, tasks: list[Submission]) -> list[Submission]:
        """Hand out several tasks, one message per worker: free workers first (a live one first),
        then behind busy ones, up to `depth` tasks a worker; returns the tasks nothing had room for."""
        if not tasks:
            return []
        slots = sorted(self.slots, key=lambda s: (len(s.keys), not s.process.is_alive()))
        given: dict[int, list[Submission]] = {}
        rest = list(tasks)
        while rest:   # round robin, the emptiest first: two workers share a batch, not one takes it all
            placed = False
            for slot in slots:
                if rest and len(slot.keys) < self.depth:
                    if not slot.keys:
                        slot.started = slot.progressed = time.monotonic()
                        slot.cpu = None
                    slot.keys.append(rest[0][0])
                    given.setdefault(id(slot), []).append(rest.pop(0))
                    placed = True
            if not placed:
                break
        for slot in slots:
            if id(slot) in given:
                try:
                    slot.conn.send(given[id(slot)])
                except OSError:   # the worker has just died: the next poll() gives its tasks back
                    pass
        return rest

    def _idle(self) -> Optional[_Slot]:
        """A free worker that is alive (one that died idle is replaced by the next poll())."""
        return next((s for s in self.slots if not s.keys and s.process.is_alive()), None)

    def unready(self) -> Optional[str]:
        """Why this executor cannot run tasks now (readiness), or None: local workers are replaced
        when they die, so the pool is always able to."""
        return None

    def queueing(self) -> QueueingPool:
        """Its workers hold queued tasks and take batches: the pool itself."""
        return self

    def can_start_now(self) -> bool:
        """Whether submit() would start a task at once; quick, so a caller's thread may ask (Dispatcher)."""
        return self._idle() is not None

    def submit(self, key: str, kind: str, request: TaskRequest) -> None:
        """To a free worker (a live one first), else behind the tasks of a worker with room (`depth`)."""
        slot = self._idle() or next((s for s in self.slots if not s.keys), None) or \
            min((s for s in self.slots if len(s.keys) < self.depth), key=lambda s: len(s.keys))
        if not slot.keys:
            slot.started = slot.progressed = time.monotonic()
            slot.cpu = None
        slot.keys.append(key)
        slot.conn.send((key, kind, request))

    replaced = 0   # workers replaced (lost, stalled or ended for a cancel): /metrics

    def _replace(self, i: int) -> None:
        """End worker i (if alive) and start another; the tasks queued behind its own were never
        started: they come back from the next poll()."""
        self.replaced += 1
        slot = self.slots[i]
        if slot.process.is_alive():
            slot.process.kill()
        slot.process.join(timeout=5)
        slot.conn.close()
        self._returned += [(key, Outcome("not_started")) for key in slot.keys[1:]]
        self.slots[i] = self._spawn()

    def poll(self) -> list[tuple[str, Outcome]]:
        done, self._returned = self._returned, []
        for i, slot in enumerate(self.slots):
            if not slot.keys:
                if not slot.process.is_alive():
                    self._replace(i)
                continue
            try:
                while slot.keys and slot.conn.poll():
                    msg = slot.conn.recv()
                    for key, outcome in msg if isinstance(msg, list) else [msg]:
                        if not isinstance(outcome, Outcome):   # STARTED
                            slot.started = slot.progressed = time.monotonic()   # its wall clock starts now
                            self._started.append(key)
                            continue
                        if key == slot.keys[0]:
                            slot.started = slot.progressed = time.monotonic()   # the next one starts now
                        if key in slot.keys:
                            slot.keys.remove(key)
                        done.append((key, outcome))
            except (OSError, EOFError):
                pass
            if not slot.keys:
                continue
            if not slot.process.is_alive():
                done.append((slot.keys[0], _death_reason(slot.process.exitcode, self.cpu_seconds)))
                self._replace(i)
            elif self._stalled(slot):
                done.append((slot.keys[0], lost(
                    f"the worker process used no CPU for {self.stall_seconds:g} s mid-task (stopped or "
                    "hung): replaced, not a fault of this request")))
                self._replace(i)
            elif time.monotonic() - slot.started > self.wall_seconds:
                done.append((slot.keys[0], timed_out(f"exceeded the wall-time limit of {self.wall_seconds:g} s")))
                self._replace(i)
        done += self._returned
        self._returned = []
        return done

    def started(self) -> list[str]:
        """The keys whose worker acknowledged the start since the last call (read by poll())."""
        keys, self._started = self._started, []
        return keys

    def _stalled(self, slot: _Slot) -> bool:
        """Whether a busy worker's CPU clock has stood still for `stall_seconds` (read once a second)."""
        now = time.monotonic()
        if self.stall_seconds is None or now - slot.checked < STALL_CHECK_SECONDS:
            return False
        slot.checked = now
        cpu = _cpu_seconds_of(slot.process.pid)
        if cpu is None:
            return False
        if slot.cpu is None or cpu > slot.cpu:
            slot.cpu, slot.progressed = cpu, now
        return now - slot.progressed > self.stall_seconds

    def cancel(self, key: str) -> bool:
        """Stop a task: a running one ends its worker (another takes its place), a queued one is
        withdrawn (its answer, if it had started after all, is its outcome)."""
        for i, slot in enumerate(self.slots):
            if slot.keys and slot.keys[0] == key:
                self._replace(i)
                return True
            if key in slot.keys:
                try:
                    slot.conn.send((key,))
                except OSError:
                    pass      # the worker is gone: the next poll() says so
                return True
        return False

    def shutdown(self, grace: float = 2.0) -> None:
        """Stop the workers: idle ones are asked to (they finish a compile begun in the background
        within `grace` seconds), then any still alive is killed."""
        for slot in self.slots:
            try:
                if not slot.keys:
                    slot.conn.send(None)
            except (OSError, BrokenPipeError):
                pass
        deadline = time.monotonic() + grace
        for slot in self.slots:
            slot.process.join(timeout=max(0.0, deadline - time.monotonic()))
            if slot.process.is_alive():
                slot.process.kill()
        for slot in self.slots:
            slot.process.join(timeout=1)
        if self.registry is not None:
            self.registry.close()


def make_executor(settings: Settings) -> WorkerPool:
    if settings.executor == "dask":
        if not settings.dask_scheduler:
            raise ValueError("GREYFIT_EXECUTOR=dask needs GREYFIT_DASK_SCHEDULER (e.g. tcp://host:8786)")
        from greyfit.service.jobs.dask_executor import DaskExecutor  # the dask extra: imported only when used
        return DaskExecutor(settings.dask_scheduler, settings.task_cpu_seconds, settings.task_wall_seconds,
                            connect_seconds=settings.dask_connect_seconds)
    return LocalWorkerPool(settings.workers, settings.task_cpu_seconds, settings.task_wall_seconds,
                           settings.worker_stall_seconds, WorkerRegistry(Path(settings.data_dir) / "workers"))
