"""greyfit: fit the physical parameters of ODE models to measured data (CasADi + Ipopt).

The public face of the library::

    import greyfit
    result = greyfit.fit(greyfit.FitRequest.model_validate(request_dict))
    print(result.params["k"].value)

`fit`, `discover`, `simulate` and `frequency_fit` take the same requests as the HTTP service's
routes and return the same results; `Client` (and `AsyncClient`) call a running service. The numerics load on first
use, so `from greyfit import Client` does not import CasADi.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from greyfit.client import AsyncClient, Client
    from greyfit.schemas.design import DesignRequest, DesignResult
    from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
    from greyfit.schemas.fit import FitOptions, FitRequest, FitResult
    from greyfit.schemas.frequency import FrequencyFitRequest
    from greyfit.schemas.simulate import SimulateRequest, SimulateResult
    from greyfit.solvers.design import design_experiment as design
    from greyfit.solvers.discovery.loop import discover
    from greyfit.solvers.fit import fit_model as fit
    from greyfit.solvers.frequency.fit import fit_frequency_response as frequency_fit
    from greyfit.solvers.simulation.simulate import simulate_request as simulate

# name -> (module, attribute): resolved on first access (PEP 562), so importing greyfit is cheap
_LAZY = {
    "fit": ("greyfit.solvers.fit", "fit_model"),
    "discover": ("greyfit.solvers.discovery.loop", "discover"),
    "simulate": ("greyfit.solvers.simulation.simulate", "simulate_request"),
    "frequency_fit": ("greyfit.solvers.frequency.fit", "fit_frequency_response"),
    "design": ("greyfit.solvers.design", "design_experiment"),
    "DesignRequest": ("greyfit.schemas.design", "DesignRequest"),
    "DesignResult": ("greyfit.schemas.design", "DesignResult"),
    "Client": ("greyfit.client", "Client"),
    "AsyncClient": ("greyfit.client", "AsyncClient"),
    "FitRequest": ("greyfit.schemas.fit", "FitRequest"),
    "FitResult": ("greyfit.schemas.fit", "FitResult"),
    "FitOptions": ("greyfit.schemas.fit", "FitOptions"),
    "DiscoverRequest": ("greyfit.schemas.discovery", "DiscoverRequest"),
    "DiscoveryResult": ("greyfit.schemas.discovery", "DiscoveryResult"),
    "SimulateRequest": ("greyfit.schemas.simulate", "SimulateRequest"),
    "SimulateResult": ("greyfit.schemas.simulate", "SimulateResult"),
    "FrequencyFitRequest": ("greyfit.schemas.frequency", "FrequencyFitRequest"),
}

__all__ = ["__version__", "fit", "discover", "simulate", "frequency_fit", "Client", "AsyncClient", "FitRequest",
           "FitResult", "FitOptions", "DiscoverRequest", "DiscoveryResult", "SimulateRequest", "SimulateResult",
           "FrequencyFitRequest", "design", "DesignRequest", "DesignResult"]


def _version() -> str:
    # importlib.metadata costs ~20 ms to import: a fresh process's first fit does not pay it
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("greyfit")
    except PackageNotFoundError:   # running from a source tree that was never installed
        return "0+unknown"


def __getattr__(name: str) -> Any:
    if name == "__version__":
        globals()[name] = value = _version()
        return value
    if name not in _LAZY:
        raise AttributeError(f"module 'greyfit' has no attribute {name!r}")
    import importlib
    module, attribute = _LAZY[name]
    value = getattr(importlib.import_module(module), attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
