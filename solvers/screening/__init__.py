"""Screening: score the library's candidate effects against a fit's residual, one linearised step each.

Below both the fit's checks and discovery: the lack-of-fit check (`solvers/checks/lack_of_fit.py`)
runs the screen on every output-error fit, and discovery runs it to choose what to refit, so a plain
fit loads this wing and never discovery's refits and rewrites.

The screen is in `screening`; its scorers in `scoring` (the vectorised statistics),
`scoring_equations` and `scoring_outputs`; the candidates in `candidate`, built on the canonical form
of the equations in `canonical` and written into a model by `augment`; the effect library in
`effects`, read from the registry of families in `families/` (one module per family: add one there
and one line in `families/__init__.py`, and its name in schemas/discovery.py's `Effect`).
"""
