"""Turn a worker outcome into a response or the matching error."""
from __future__ import annotations

from fastapi import HTTPException

from solvers.errors import DataError, FitError, ModelDefinitionError

_ERRORS = {"DataError": DataError, "ModelDefinitionError": ModelDefinitionError}


def outcome_or_raise(outcome: dict) -> dict:
    if outcome["status"] == "succeeded":
        return outcome["result"]
    err = outcome["error"]
    cls = _ERRORS.get(err["type"])
    if cls is not None:
        raise cls(err["detail"], err.get("field"))
    if err["type"] in ("Timeout", "WorkerLost"):
        raise HTTPException(503 if err["type"] == "WorkerLost" else 504, err["detail"])
    if err["type"] == "ValidationError":
        raise FitError(err["detail"])
    raise HTTPException(500, f"{err['type']}: {err['detail']}")
