"""What a worker runs: one request in, one JSON-ready outcome out (never raises)."""
from __future__ import annotations

import traceback
from functools import lru_cache
from typing import Any, Callable

from pydantic import ValidationError

TASK_KINDS = ("fit", "discover", "simulate", "report", "frequency_fit")


@lru_cache(maxsize=None)   # built once per worker process: a fit of milliseconds notices the imports
def _runners() -> dict[str, Callable[[dict, float], Any]]:
    from greyfit.schemas import FitRequest
    from greyfit.solvers.fit import fit_model

    def fit(request: dict | str, cpu_seconds: float):
        req = _parse(FitRequest, request)
        # Ipopt stops by itself before the worker's hard CPU limit would kill it
        req.options.max_cpu_time = min(req.options.max_cpu_time, 0.9 * cpu_seconds)
        return fit_model(req)

    def frequency_fit(request: dict | str, cpu_seconds: float):
        from greyfit.schemas.frequency import FrequencyFitRequest
        from greyfit.solvers.frequency import fit_frequency_response
        req = _parse(FrequencyFitRequest, request)
        req.options.max_cpu_time = min(req.options.max_cpu_time, 0.9 * cpu_seconds)
        return fit_frequency_response(req)

    runners = {"fit": fit, "frequency_fit": frequency_fit}
    try:
        from greyfit.schemas.discovery import DiscoverRequest
        from greyfit.solvers.discovery import discover

        def disc(request: dict | str, cpu_seconds: float):
            req = _parse(DiscoverRequest, request)
            req.options.max_cpu_time = min(req.options.max_cpu_time, 0.9 * cpu_seconds)
            return discover(req)

        runners["discover"] = disc
    except ImportError:  # pragma: no cover - discovery is part of the package
        pass
    runners.update(_workflow_runners())
    return runners


def _workflow_runners() -> dict[str, Callable[[dict, float], Any]]:
    """Simulation and report pages also run in workers (CPU-bound: never in the web process)."""
    from greyfit.schemas.report import ReportRequest
    from greyfit.schemas.simulate import SimulateRequest

    def simulate(request: dict | str, cpu_seconds: float):
        from greyfit.solvers.simulation.simulate import simulate_request
        return simulate_request(_parse(SimulateRequest, request))

    def report(request: dict | str, cpu_seconds: float):
        from greyfit.service.report import report_public
        from greyfit.solvers.errors import DataError
        parsed = _parse(ReportRequest, request)
        try:
            return report_public(parsed)
        except (ValueError, OverflowError, TypeError, KeyError, IndexError, ArithmeticError) as exc:
            # a result that was not made by greyfit (odd keys, values near the float limits) cannot
            # be drawn: that is the caller's input, not a server fault
            raise DataError(f"this result cannot be drawn ({type(exc).__name__}: {exc}); send a result "
                            "as greyfit returned it", "result") from exc

    return {"simulate": simulate, "report": report}


def _parse(model, request: dict | str):
    return model.model_validate_json(request) if isinstance(request, str) else model.model_validate(request)


def run_task(kind: str, request: dict | str, cpu_seconds: float = 600.0) -> dict:
    """{'status': 'succeeded', 'result_json': '...'} or {'status': 'failed', 'error': {type, field, detail}}.

    The request may be the JSON text itself, and the result comes back as JSON text: the server
    stores and returns both without parsing them again.
    """
    from greyfit.solvers.errors import FitError
    try:
        runner = _runners()[kind]
        result = runner(request, cpu_seconds)
        return {"status": "succeeded", "result_json": result.model_dump_json()}
    except FitError as exc:
        return {"status": "failed", "error": {"type": type(exc).__name__, "field": exc.field,
                                              "detail": exc.message}}
    except ValidationError as exc:
        return {"status": "failed", "error": {"type": "ValidationError", "field": None,
                                              "detail": str(exc), "errors": [
                                                  {"loc": list(e["loc"]), "msg": e["msg"]} for e in exc.errors()]}}
    except ImportError as exc:   # an optional extra (matplotlib for reports) is not installed
        return {"status": "failed", "error": {"type": "DependencyMissing", "field": None,
                                              "detail": str(exc)}}
    except Exception as exc:  # a bug or a CasADi failure: the task fails, the worker goes on
        return {"status": "failed", "error": {"type": "InternalError", "field": None,
                                              "detail": f"{type(exc).__name__}: {exc}",
                                              "trace": traceback.format_exc(limit=5)}}
