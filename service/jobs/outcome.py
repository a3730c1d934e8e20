"""What crosses the process boundary: a task's outcome and its error, as dataclasses.

A worker (a local process or a Dask worker) sends an `Outcome` back through a pipe or the cluster;
both pickle it, so it holds plain values only. The job store keeps the error as JSON (`as_dict`),
in the shape it always had: {type, field, detail}, plus `retry`, `errors` or `trace` where set.

An error raised on purpose by the solvers (the `FitError` tree) travels with the names of its
classes up to `FitError` (`lineage`): the server answers with the nearest class of the tree it
knows, so a subclass added later is still the request's fault (422), not a bug (500).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Optional

from greyfit.solvers import errors as fit_errors

Status = Literal["succeeded", "failed", "cancelled", "not_started", "withdrawn"]

__all__ = ["Outcome", "Status", "TaskError", "fit_error_of"]


@dataclass(frozen=True)
class TaskError:
    """Why a task failed.

    `type` names the error (a `FitError` subclass, `ValidationError`, `Timeout`, `WorkerLost`,
    `DependencyMissing`, `Cancelled` or `InternalError`); `lineage` is set for a `FitError` only."""

    type: str
    detail: str
    field: Optional[str] = None
    retry: bool = False                          # its worker was lost: the task runs again
    errors: Optional[list[dict[str, Any]]] = None   # a request's validation errors, by location
    trace: Optional[str] = None                  # an internal error's traceback, for the log
    lineage: tuple[str, ...] = ()                # a FitError's class names, from its own up to FitError

    @classmethod
    def of_fit_error(cls, exc: fit_errors.FitError) -> TaskError:
        """The error of a task that raised one of the solvers' errors on purpose."""
        names = tuple(c.__name__ for c in type(exc).__mro__ if issubclass(c, fit_errors.FitError))
        return cls(type(exc).__name__, exc.message, exc.field, lineage=names)

    def as_dict(self) -> dict[str, Any]:
        """The error as the job store and the batch output keep it (no lineage: the type says it)."""
        out: dict[str, Any] = {"type": self.type, "field": self.field, "detail": self.detail}
        if self.retry:
            out["retry"] = True
        if self.errors is not None:
            out["errors"] = self.errors
        if self.trace is not None:
            out["trace"] = self.trace
        return out


@dataclass(frozen=True)
class Outcome:
    """A task's end: succeeded with its result's JSON text, or failed, cancelled, not started (its
    worker was replaced before it began) or withdrawn (taken back from a worker's queue)."""

    status: Status
    result_json: Optional[str] = None
    error: Optional[TaskError] = None
    seconds: Optional[float] = None   # the worker's own count of the task's wall time

    @classmethod
    def failed(cls, error: TaskError, seconds: Optional[float] = None) -> Outcome:
        return cls("failed", error=error, seconds=seconds)

    @property
    def is_retry(self) -> bool:
        """A failure outside the task (its worker was lost): the task runs again."""
        return self.status == "failed" and self.error is not None and self.error.retry

    def error_dict(self) -> Optional[dict[str, Any]]:
        return None if self.error is None else self.error.as_dict()

    def as_dict(self) -> dict[str, Any]:
        """The outcome as plain JSON-ready values, with only the fields that are set."""
        out: dict[str, Any] = {"status": self.status}
        if self.result_json is not None:
            out["result_json"] = self.result_json
        if self.error is not None:
            out["error"] = self.error.as_dict()
        if self.seconds is not None:
            out["seconds"] = self.seconds
        return out


def lost(detail: str) -> Outcome:
    """A task whose worker was lost (killed, crashed, or the cluster's): it runs again."""
    return Outcome.failed(TaskError("WorkerLost", detail, retry=True))


def timed_out(detail: str) -> Outcome:
    """A task that hit its CPU- or wall-time limit: not retried, it would hit it again."""
    return Outcome.failed(TaskError("Timeout", detail))


def fit_error_of(error: TaskError) -> Optional[fit_errors.FitError]:
    """The solvers' error a worker raised, rebuilt as the nearest class of the tree this process
    knows (its own, or a base of a subclass defined only where it was raised); None for any other."""
    for name in error.lineage:
        cls = getattr(fit_errors, name, None)
        if isinstance(cls, type) and issubclass(cls, fit_errors.FitError):
            exc = cls.__new__(cls)
            # through the base's constructor: a subclass's own may take other arguments (DataFileError)
            fit_errors.FitError.__init__(exc, error.detail, error.field)
            return exc
    return None
