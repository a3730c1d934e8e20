"""Discovery: fit, trace the residual to a missing physical effect, add it, refit, report.

The steps in the order they run are in `loop`; screening in `screening`, `scoring_equations`,
`scoring_outputs`; the effect library in `effects`, read from the registry of families in `families/`
(one module per family: add one there and one line in `families/__init__.py`, and its name in
schemas/discovery.py's `Effect`); discrimination by refit and parsimony in `discriminate`; refits in
`confirm`; model rewrites in `augment`.

`discover` loads the loop on first use: every fit's lack-of-fit check runs the screen, and a fresh
process's first fit need not import the refits and rewrites (12 ms) to do it.
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
