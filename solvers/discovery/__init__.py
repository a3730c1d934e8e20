"""Discovery: fit, trace the residual to a missing physical effect, add it, refit, report.

The steps in the order they run are in `loop`; discrimination by refit and parsimony in
`discriminate`; refits in `confirm`. The screen, its scorers, the candidates, the model rewrites and
the effect library with its families are one layer below, in `solvers/screening/`: the fit's
lack-of-fit check runs the same screen, and a plain fit imports nothing of this package.

`discover` loads the loop on first use, so importing this package costs nothing until it runs.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from greyfit.solvers.discovery.loop import discover

__all__ = ["discover"]


def __getattr__(name: str) -> Any:
    if name != "discover":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from greyfit.solvers.discovery.loop import discover
    globals()[name] = discover
    return discover
