"""greyfit: fit the physical parameters of ODE models to measured data (CasADi + Ipopt).

A model built in Python and fitted to a record (here the step response of a first-order lag with
gain 2 and time constant 0.5 s; `Experiment.from_csv`, `from_parquet`, `from_mat` and
`from_dataframe` read measured ones by the model's names)::

    >>> import numpy as np
    >>> import greyfit
    >>> model = greyfit.Model(states=["x"], inputs=["u"], equations={"x": "(K*u - x)/tau"},
    ...                       parameters=[greyfit.Parameter("K", 1.0, lower=0),
    ...                                   greyfit.Parameter("tau", 2.0, lower=0.01, unit="s")])
    >>> t = np.linspace(0.0, 3.0, 61)
    >>> record = greyfit.Experiment(time=t, inputs={"u": np.ones_like(t)},
    ...                             outputs={"x": 2.0 * (1.0 - np.exp(-t / 0.5))}, initial_state={"x": 0.0})
    >>> result = greyfit.fit(model=model, experiments=[record])
    >>> print(f"K = {result.parameters['K'].value:.3f}, tau = {result.parameters['tau'].value:.3f} s")
    K = 2.000, tau = 0.500 s
    >>> later = result.simulate(greyfit.Experiment(time=t, inputs={"u": 0.5 * np.ones_like(t)},
    ...                                            initial_state={"x": 0.0}))
    >>> print(f"{later.experiments[0].outputs['x'][-1]:.3f}")
    0.998

`fit` also takes a `FitRequest` or its dict; `discover`, `simulate`, `frequency_fit` and `design` take the
same requests as the HTTP service's routes and return the same results; `Client` (and `AsyncClient`)
call a running service. The numerics load on first use, so `from greyfit import Client` does not
import CasADi.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from greyfit.building import Experiment, Model, Parameter
    from greyfit.client import AsyncClient, Client
    from greyfit.fitting import FitResult, fit
    from greyfit.schemas.design import DesignRequest, DesignResult
    from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
    from greyfit.schemas.fit import FitOptions, FitRequest
    from greyfit.schemas.frequency import FrequencyFitRequest
    from greyfit.schemas.simulate import SimulateRequest, SimulateResult
    from greyfit.solvers.design import design_experiment as design
    from greyfit.solvers.discovery.loop import discover
    from greyfit.solvers.frequency.fit import fit_frequency_response as frequency_fit
    from greyfit.solvers.simulation.simulate import simulate_request as simulate

# name -> (module, attribute): resolved on first access (PEP 562), so importing greyfit is cheap
_LAZY = {
    "fit": ("greyfit.fitting", "fit"),
    "discover": ("greyfit.solvers.discovery.loop", "discover"),
    "simulate": ("greyfit.solvers.simulation.simulate", "simulate_request"),
    "frequency_fit": ("greyfit.solvers.frequency.fit", "fit_frequency_response"),
    "design": ("greyfit.solvers.design", "design_experiment"),
    "DesignRequest": ("greyfit.schemas.design", "DesignRequest"),
    "DesignResult": ("greyfit.schemas.design", "DesignResult"),
    "Client": ("greyfit.client", "Client"),
    "AsyncClient": ("greyfit.client", "AsyncClient"),
    "FitRequest": ("greyfit.schemas.fit", "FitRequest"),
    "FitResult": ("greyfit.fitting", "FitResult"),
    "Model": ("greyfit.building", "Model"),
    "Parameter": ("greyfit.building", "Parameter"),
    "Experiment": ("greyfit.building", "Experiment"),
    "FitOptions": ("greyfit.schemas.fit", "FitOptions"),
    "DiscoverRequest": ("greyfit.schemas.discovery", "DiscoverRequest"),
    "DiscoveryResult": ("greyfit.schemas.discovery", "DiscoveryResult"),
    "SimulateRequest": ("greyfit.schemas.simulate", "SimulateRequest"),
    "SimulateResult": ("greyfit.schemas.simulate", "SimulateResult"),
    "FrequencyFitRequest": ("greyfit.schemas.frequency", "FrequencyFitRequest"),
}

__all__ = ["__version__", "fit", "discover", "simulate", "frequency_fit", "Client", "AsyncClient", "FitRequest",
           "FitResult", "FitOptions", "DiscoverRequest", "DiscoveryResult", "SimulateRequest", "SimulateResult",
           "FrequencyFitRequest", "design", "DesignRequest", "DesignResult", "Model", "Parameter",
           "Experiment"]


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
