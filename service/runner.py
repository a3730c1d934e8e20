"""Turn a worker outcome into a response or the matching error."""
from __future__ import annotations

from fastapi import HTTPException, Response

from greyfit.solvers.errors import DataError, FitError, ModelDefinitionError

_ERRORS = {"DataError": DataError, "ModelDefinitionError": ModelDefinitionError}


class WorkerTaskFailed(Exception):
    """A worker's task ended in an unexpected exception: answered as a 500 like any other bug."""


def outcome_or_raise(outcome: dict, retry_after: int = 2) -> Response:
    """The worker's result JSON as the response (not parsed again), or the matching error.

    A lost worker is a 503 with `Retry-After` (`retry_after` seconds), as every 503 is documented."""
    if outcome["status"] == "succeeded":
        return Response(outcome["result_json"], media_type="application/json")
    err = outcome["error"]
    cls = _ERRORS.get(err["type"])
    if cls is not None:
        raise cls(err["detail"], err.get("field"))
    if err["type"] in ("Timeout", "WorkerLost"):
        if err["type"] == "WorkerLost":
            raise HTTPException(503, f"{err['detail']}; retry", headers={"Retry-After": str(retry_after)})
        raise HTTPException(504, err["detail"])
    if err["type"] == "DependencyMissing":   # an optional extra of this server is not installed
        raise HTTPException(501, err["detail"])
    if err["type"] == "ValidationError":
        raise FitError(err["detail"])
    # a bug in the task (the dispatcher logged its trace): the answer every bug gets, with a request id
    raise WorkerTaskFailed(f"{err['type']}: {err['detail']}")
