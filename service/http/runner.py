"""Turn a worker outcome into a response or the matching error."""
from __future__ import annotations

from fastapi import HTTPException, Response

from greyfit.service.jobs.outcome import Outcome, fit_error_of
from greyfit.solvers.errors import FitError


class WorkerTaskFailed(Exception):
    """A worker's task ended in an unexpected exception: answered as a 500 like any other bug."""


def outcome_or_raise(outcome: Outcome, retry_after: int = 2) -> Response:
    """The worker's result JSON as the response (not parsed again), or the matching error.

    An error of the solvers' `FitError` tree is raised again as the nearest class of the tree (the
    app answers 422 for all of them). A lost worker is a 503 with `Retry-After` (`retry_after`
    seconds), as every 503 is documented."""
    if outcome.status == "succeeded" and outcome.result_json is not None:
        return Response(outcome.result_json, media_type="application/json")
    err = outcome.error
    if err is None:   # (a synchronous fit is never withdrawn nor handed back: the dispatcher fails it)
        raise WorkerTaskFailed(f"the task ended without a result ({outcome.status})")
    fit_error = fit_error_of(err)
    if fit_error is not None:
        raise fit_error
    if err.type == "WorkerLost":
        raise HTTPException(503, f"{err.detail}; retry", headers={"Retry-After": str(retry_after)})
    if err.type == "Timeout":
        raise HTTPException(504, err.detail)
    if err.type == "DependencyMissing":   # an optional extra of this server is not installed
        raise HTTPException(501, err.detail)
    if err.type == "ValidationError":
        raise FitError(err.detail)
    # a bug in the task (the dispatcher logged its trace): the answer every bug gets, with a request id
    raise WorkerTaskFailed(f"{err.type}: {err.detail}")
