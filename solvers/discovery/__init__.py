"""Discovery: fit, trace the residual to a missing physical effect, add it, refit, report.

The steps in the order they run are in `loop`; screening in `screening`, `scoring_equations`,
`scoring_outputs`; the effect library in `effects` and `output_effects`; model rewrites in `augment`.
"""
from greyfit.solvers.discovery.loop import discover

__all__ = ["discover"]
