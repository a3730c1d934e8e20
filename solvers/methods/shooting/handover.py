"""Interpret while gcc compiles, then go on compiled: the first fit of a new model structure.

A structure's per-sample libraries are built in the background (`compiled(...,
interpret_meanwhile=True)`), and its first fit starts at once on the interpreted NLP. That NLP carries
an Ipopt iteration callback (`stop_callback`) that ends the solve at the first iteration after the
builds have ended; `solve` then asks the solver's factory for the compiled NLP and continues from
the point reached. So a first fit never waits for gcc longer than interpreting it would take (the
foreground compile it replaces waited 1 s on a quiet machine, a minute on a loaded one), and a long
one still runs mostly compiled.

The callback is armed only while a build runs in this process: a compile that failed (or a
`GREYFIT_COMPILE=never` process) leaves the interpreted solve alone.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable, Optional

import casadi as ca
import numpy as np

from greyfit.solvers.dynamics import compiled
from greyfit.solvers.nlp.solver import NlpOutcome

STOPPED = "User_Requested_Stop"


class StopWhenCompiled(ca.Callback):
    """Ipopt's iteration callback: 1 (stop) once no background build runs while one did at the start.

    It takes none of Ipopt's iterates (empty inputs): nothing is copied per iteration.
    """

    def __init__(self) -> None:
        ca.Callback.__init__(self)
        self.armed = False
        self.fired = False
        self.construct("greyfit_stop_when_compiled", {})

    def get_n_in(self) -> int:
        """Number of inputs: one per output of an `nlpsol` (CasADi's callback interface).

        Returns
        -------
        int
            ``casadi.nlpsol_n_out()``.
        """
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        """Number of outputs: the one stop flag.

        Returns
        -------
        int
            1.
        """
        return 1

    def get_name_in(self, i: int) -> str:
        """Name of input `i`: the `nlpsol` output it receives.

        Parameters
        ----------
        i : int
            Index of the input.

        Returns
        -------
        str
            ``casadi.nlpsol_out(i)`` (x, f, g, lam_x, ...).
        """
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        """Name of output `i`.

        Parameters
        ----------
        i : int
            Index of the output (0, the only one).

        Returns
        -------
        str
            "ret", the name Ipopt's iteration callback reads.
        """
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        """Shape of input `i`: empty, so that no iterate is copied per iteration.

        Parameters
        ----------
        i : int
            Index of the input.

        Returns
        -------
        casadi.Sparsity
            A 0×0 sparsity.
        """
        return ca.Sparsity(0, 0)

    def eval(self, arg):
        """One Ipopt iteration: stop when the background builds have ended since the solve began.

        Parameters
        ----------
        arg : list
            The (empty) inputs.

        Returns
        -------
        list of int
            [1] to stop the solve (once: the callback disarms itself and records `fired`), else [0].
        """
        if self.armed and not compiled.building_any():
            self.armed, self.fired = False, True
            return [1]
        return [0]


def stop_callback(is_compiled: bool) -> Optional[StopWhenCompiled]:
    """The iteration callback for an NLP built now, or None where no switch can come.

    Parameters
    ----------
    is_compiled : bool
        Whether the NLP's per-sample Functions are compiled C already.

    Returns
    -------
    StopWhenCompiled or None
        A callback for the ``iteration_callback`` option of an interpreted NLP while libraries are
        being built in this process; None otherwise (compiled, or nothing to wait for).
    """
    if is_compiled or not compiled.building_any():
        return None
    return StopWhenCompiled()


def solve(run: Callable[[np.ndarray], NlpOutcome], stop: Optional[StopWhenCompiled],
          upgrade: Callable[[], Optional[Callable[[np.ndarray], NlpOutcome]]], w0: np.ndarray) -> NlpOutcome:
    """One solve from `w0` that moves to the compiled NLP when its libraries arrive mid-solve.

    Parameters
    ----------
    run : callable
        Solves the interpreted NLP from a start (`run_ipopt` over it).
    stop : StopWhenCompiled or None
        That NLP's iteration callback (None: `run` alone).
    upgrade : callable
        Returns the compiled NLP's `run`, or None when it is still interpreted (a build failed).
    w0 : numpy.ndarray
        Start of the decision vector.

    Returns
    -------
    NlpOutcome
        The outcome of the last solve, with the iterations and wall time of both; the same optimum
        as one solve (Ipopt restarts from the interpreted solve's last iterate).
    """
    if stop is None:
        return run(w0)
    stop.armed, stop.fired = compiled.building_any(), False
    first = run(w0)
    if not (stop.fired and first.status == STOPPED):
        return first
    better = upgrade()
    rest = (better or run)(first.w)
    return replace(rest, iterations=first.iterations + rest.iterations,
                   wall_time_s=first.wall_time_s + rest.wall_time_s)

