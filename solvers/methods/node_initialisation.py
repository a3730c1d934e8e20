"""Start values of multiple shooting's nodes, for each start of a multistart.

Measured states take the (gap-filled) data; every other state takes a simulation of the model
at that start's parameters, from the guessed initial state, so that the unmeasured nodes start
on a trajectory the model can join (not at 0, which opens every continuity gap at once).

Where that simulation fails or runs away (non-finite, or beyond DIVERGED), the nodes from there
on start at 0 (holding the last finite value, ~1e11, stopped a case that 0 lets converge), and
the fact is kept in `oem.node_notes` for the result's
warnings: a start far from a stable model is a start the solver has to repair, and the user
should know which one it was.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitWarning
from greyfit.solvers.data.experiments import fill_missing

DIVERGED = 1e12   # |state| taken as a run-away simulation


def node_states(oem, theta_phys: np.ndarray) -> list[np.ndarray]:
    """Per experiment, the guessed state at every sample (nx × N, physical units).

    Parameters
    ----------
    oem : OutputErrorModel
        The multiple-shooting output-error model; a divergence is noted in `oem.node_notes`.
    theta_phys : numpy.ndarray
        The start's physical parameter values, shape (n θ,).

    Returns
    -------
    list of numpy.ndarray
        One array per experiment, shape (nx, N): measured states from the gap-filled data, the others
        from the simulation (0 from where it fails or diverges), known initial states in the first column.
    """
    cm = oem.cm
    x0s = [oem.x0_guess(e) for e in range(len(oem.data))]
    failures = len(oem.simulation_failures)
    sims = oem.simulate(theta_phys, x0s)
    failed = oem.simulation_failures[failures:]
    del oem.simulation_failures[failures:]   # a start's trouble is not the result's failure
    out = []
    for e, d in enumerate(oem.data):
        states = np.array(sims[e][0], dtype=float)
        measured = {cm.states.index(s) for s in cm.direct_outputs.values()}
        sane = np.isfinite(states) & (np.abs(states) < DIVERGED)
        bad = [i for i in range(cm.nx) if i not in measured and not sane[i].all()]
        if bad:
            first = min(int(np.argmin(sane[i])) for i in bad)
            oem.node_notes.append((d.name, _note(oem, e, theta_phys, bad, d.t[first], failed)))
        for i in range(cm.nx):
            states[i] = np.where(sane[i] & (np.arange(d.n) < _first_bad(sane[i])), states[i], 0.0)
        for out_name, state in cm.direct_outputs.items():
            states[cm.states.index(state)] = fill_missing(d.y[cm.outputs.index(out_name)], d.t)
        for i, v in d.x0_known.items():
            states[i, 0] = v
        out.append(states)
    return out


def _first_bad(sane: np.ndarray) -> int:
    return sane.size if sane.all() else int(np.argmin(sane))


def _note(oem, e: int, theta_phys: np.ndarray, states: list[int], time: float,
          failed: list[str]) -> str:
    names = ", ".join(oem.cm.states[i] for i in states)
    params = ", ".join(f"{lab}={v:.4g}" for lab, v in zip(oem.layout.labels, theta_phys))
    why = f" ({failed[0]})" if failed else ""
    return (f"experiment '{oem.data[e].name}': the simulation at the start ({params}) diverged at "
            f"t = {time:.4g}{why}; the nodes of {names} start at 0 from there")


def node_warnings(oem) -> list[FitWarning]:
    """One `initial_simulation_diverged` warning per distinct note (informative, not a verdict).

    Parameters
    ----------
    oem : OutputErrorModel or None
        The output-error model whose `node_notes` were filled by `node_states` (None: no model).

    Returns
    -------
    list of FitWarning
        One warning per distinct (experiment, note), empty when there are none.
    """
    if oem is None:
        return []
    notes = list(dict.fromkeys(getattr(oem, "node_notes", [])))
    return [FitWarning(code="initial_simulation_diverged",
                       message=note + "; multiple shooting started from those nodes",
                       detail={"experiment": name}) for name, note in notes]
