"""What a worker runs: one request in, one `Outcome` out (never raises)."""
from __future__ import annotations

import traceback
from functools import lru_cache
from typing import Any, Callable

from pydantic import ValidationError

from greyfit.service.jobs.outcome import Outcome, TaskError
from greyfit.service.task_kinds import KINDS, TASK_KINDS
from greyfit.solvers.errors import FitError

__all__ = ["run_task", "TASK_KINDS"]


@lru_cache(maxsize=None)   # built once per worker process: a fit of milliseconds notices the imports
def _runners() -> dict[str, Callable[[dict | str, float], Any]]:
    return {name: _runner(name) for name in KINDS}


def _runner(name: str) -> Callable[[dict | str, float], Any]:
    kind = KINDS[name]
    schema, run = kind.request_schema(), kind.runner()

    def runner(request: dict | str, cpu_seconds: float):
        req = _parse(schema, request)
        if kind.caps_cpu:   # Ipopt stops by itself before the worker's hard CPU limit would kill it
            req.options.max_cpu_time = min(req.options.max_cpu_time, solve_budget(cpu_seconds))
        return run(req)

    return runner


def solve_budget(cpu_seconds: float) -> float:
    """The CPU seconds Ipopt may spend of a task's limit: what is left must hold the checks after
    the solve, so it is the larger of 10 % and 1 s (but Ipopt keeps at least half). With 90 % of a
    2-second limit, the checks of a 2 001-sample fit stopped by it needed 0.33 s of the 0.2 s left on
    a slow machine, and the worker was killed instead of answering.

    Parameters
    ----------
    cpu_seconds : float
        The task's CPU-time limit.

    Returns
    -------
    float
        Ipopt's `max_cpu_time` cap.
    """
    return max(0.5 * cpu_seconds, cpu_seconds - max(0.1 * cpu_seconds, 1.0))


def _parse(model, request: dict | str):
    return model.model_validate_json(request) if isinstance(request, str) else model.model_validate(request)


def run_task(kind: str, request: dict | str, cpu_seconds: float = 600.0) -> Outcome:
    """The task's outcome: succeeded with its result's JSON text, or failed with its error.

    The request may be the JSON text itself, and the result comes back as JSON text: the server
    stores and returns both without parsing them again.
    """
    try:
        runner = _runners()[kind]
        result = runner(request, cpu_seconds)
        return Outcome("succeeded", result_json=result.model_dump_json())
    except FitError as exc:
        return Outcome.failed(TaskError.of_fit_error(exc))
    except ValidationError as exc:
        return Outcome.failed(TaskError("ValidationError", str(exc), errors=[
            {"loc": list(e["loc"]), "msg": e["msg"]} for e in exc.errors()]))
    except ImportError as exc:   # an optional extra (matplotlib for reports) is not installed
        return Outcome.failed(TaskError("DependencyMissing", str(exc)))
    except Exception as exc:  # a bug or a CasADi failure: the task fails, the worker goes on
        return Outcome.failed(TaskError("InternalError", f"{type(exc).__name__}: {exc}",
                                        trace=traceback.format_exc(limit=5)))
