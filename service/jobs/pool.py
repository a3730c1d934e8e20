"""What the dispatcher asks of an executor: the `WorkerPool` Protocol and its optional abilities.

Every executor (local worker processes, a Dask cluster) answers `WorkerPool`. A pool whose workers
hold tasks queued behind the one they run, take several in one message and can say whether a task
would start at once is also a `QueueingPool`, which `queueing()` returns (None for a pool without
those abilities, e.g. Dask, whose scheduler queues): the dispatcher asks once, by a typed method,
instead of probing attributes.
"""
from __future__ import annotations

from typing import Any, Optional, Protocol, Union

from greyfit.service.jobs.outcome import Outcome

TaskRequest = Union[dict[str, Any], str]   # a task's request: its JSON text, or the parsed body
Submission = tuple[str, str, TaskRequest]  # (key, kind, request)

__all__ = ["QueueingPool", "Submission", "TaskRequest", "WorkerPool"]


class WorkerPool(Protocol):
    """Where tasks run: started by key, their outcomes polled."""

    replaced: int   # workers replaced (lost, stalled or ended for a cancel): /metrics

    def unready(self) -> Optional[str]:
        """Why nothing can run tasks now (readiness), or None."""

    def capacity(self) -> int:
        """Tasks run at once."""

    def free(self) -> int:
        """Workers without a task."""

    def queue_room(self) -> int:
        """Places left behind the tasks of busy workers (0 where the pool queues nothing)."""

    def submit(self, key: str, kind: str, request: TaskRequest) -> None:
        """Start a task (or queue it behind a running one, where there is room)."""

    def poll(self) -> list[tuple[str, Outcome]]:
        """The outcomes that arrived since the last call, by key."""

    def started(self) -> list[str]:
        """The keys whose worker acknowledged the start since the last call."""

    def cancel(self, key: str) -> bool:
        """Stop a task; False if the pool does not hold it."""

    def wait(self, timeout: float) -> None:
        """Block until an outcome may have arrived, `wake()` is called, or the timeout passes."""

    def wake(self) -> None:
        """End a `wait()` early."""

    def shutdown(self) -> None:
        """Stop the workers."""

    def queueing(self) -> Optional[QueueingPool]:
        """This pool as a `QueueingPool`, or None if it lacks those abilities."""


class QueueingPool(WorkerPool, Protocol):
    """A pool whose workers each hold up to `depth` tasks (the one they run and those behind it)."""

    depth: int                       # tasks a worker holds in all; the dispatcher sets it
    task_seconds: Optional[float]    # a task's usual length, when the dispatcher knows it

    def submit_batch(self, tasks: list[Submission]) -> list[Submission]:
        """Hand out several tasks, one message per worker; returns those nothing had room for."""

    def can_start_now(self) -> bool:
        """Whether `submit` would start a task at once; quick enough for a caller's thread."""
