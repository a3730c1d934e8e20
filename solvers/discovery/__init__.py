"""Discovery: fit, trace the residual to a missing physical effect, add it, refit, report.

The steps in the order they run are in `loop`; screening in `screening`, `scoring_equations`,
`scoring_outputs`; the effect library in `effects`, read from the registry of families in `families/`
(one module per family: add one there and one line in `families/__init__.py`, and its name in
schemas/discovery.py's `Effect`); discrimination by refit and parsimony in `discriminate`; refits in
`confirm`; model rewrites in `augment`.
"""
from greyfit.solvers.discovery.loop import discover

__all__ = ["discover"]
