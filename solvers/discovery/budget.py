"""Time of a discovery request: where it goes (wall time per phase) and when it is spent (the budget,
in CPU seconds of this process: the search ends after the same work on a quiet and on a loaded
machine, where a wall-clock budget ended it earlier the busier the machine was);
and the bounds of one refit (`RefitLimits`): iterations relative to the leader's refit, which decide,
and CPU seconds, a safety net.

A refit starts next to its answer (one Gauss-Newton step from the fit it extends), so a candidate
that is right converges in a few iterations: the audited cases took 4-14, 58 at most with the
exact-Hessian polish of a sharp tanh. A contender refitted beside a leader gets at most
`CONTENDER_ITER_FACTOR` times the leader's iterations (at least `CONTENDER_MIN_ITER`): one that does
not converge within them is not decided (reported as such, never as an answer), and since the bound
counts iterations, not seconds, the same data give the same answer on a quiet and on a loaded
machine. CPU seconds bound every refit only as a safety net against a pathological solve (a
diverging iterate whose linear algebra explodes): at most `REFIT_CPU_FACTOR` times the base fit's
CPU time (at least `REFIT_CPU_FLOOR_S`), a contender also `CONTENDER_CPU_FACTOR` times the leader's;
a refit cut there is `cpu_limit`, no verdict.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from greyfit.solvers.timing import Stopwatch

PHASES = ("base_fit", "screening", "refits", "validation")


class Clock:
    """The discovery request's stopwatch (wall time per phase, `PHASES`) and its CPU budget."""

    def __init__(self, budget_s: float):
        self.watch = Stopwatch(PHASES)
        self.cpu_started = time.process_time()
        self.budget_s = budget_s
        self.exhausted = False

    def elapsed(self) -> float:
        """Wall time since the clock was made.

        Returns
        -------
        float
            Seconds.
        """
        return self.watch.elapsed()

    def cpu(self) -> float:
        """CPU time of this process since the clock was made (what the budget counts).

        Returns
        -------
        float
            Seconds.
        """
        return time.process_time() - self.cpu_started

    def left(self) -> float:
        """What is left of the budget, in CPU seconds.

        Returns
        -------
        float
            Seconds; negative once the budget is spent.
        """
        return self.budget_s - self.cpu()

    def allows(self) -> bool:
        """May another screen or refit start? Records that the budget ended the search if not.

        Returns
        -------
        bool
            True while budget is left; False (and `exhausted` set) once it is spent.
        """
        if self.left() <= 0:
            self.exhausted = True
            return False
        return True

    def phase(self, name: str):
        """Context manager that adds the wall time of its block to phase `name` (a phase inside
        another counts for the inner one only).

        Parameters
        ----------
        name : str
            One of `PHASES` (another name starts a new entry).

        Returns
        -------
        contextlib.AbstractContextManager
            The timed block's context (`Stopwatch.stage`).
        """
        return self.watch.stage(name)

    def report(self) -> dict[str, float]:
        """Seconds per phase, and the rest as "other" (`Stopwatch.report`).

        Returns
        -------
        dict of str to float
            Phase name to seconds (rounded to 0.1 ms), plus "other": elapsed time outside the phases.
        """
        return self.watch.report()


CONTENDER_ITER_FACTOR = 3      # a contender's iterations: at most this many times the leader's ...
CONTENDER_MIN_ITER = 20        # ... and never fewer than this
CONTENDER_CPU_FACTOR = 10.0    # a contender's CPU seconds: at most this many times the leader's ...
CONTENDER_MIN_CPU_S = 5.0      # ... and never fewer than this
REFIT_CPU_FACTOR = 20.0        # any refit's CPU seconds: at most this many times the base fit's ...
REFIT_CPU_FLOOR_S = 10.0       # ... and never fewer than this


@dataclass
class RefitLimits:
    """Bounds of the refits of one contender: Ipopt iterations (decide) and CPU seconds (safety net)."""

    max_iter: int
    max_cpu_time: float
    reason: str   # how the bounds were set, for a rejection's detail


@dataclass
class RefitCost:
    """What one refit took: Ipopt iterations (polish included), CPU seconds, and whether it converged."""

    iterations: int
    cpu_s: float
    converged: bool


def refit_cpu_cap(base_cpu_s: float) -> float:
    """The CPU seconds any refit may take: the safety net relative to the base fit.

    Parameters
    ----------
    base_cpu_s : float
        CPU seconds of the declared model's fit (0 when not measured).

    Returns
    -------
    float
        max(`REFIT_CPU_FLOOR_S`, `REFIT_CPU_FACTOR` × base_cpu_s).
    """
    return max(REFIT_CPU_FLOOR_S, REFIT_CPU_FACTOR * base_cpu_s)


def contender_limits(leader: list[RefitCost], max_iter: int) -> RefitLimits | None:
    """The bounds of the contenders refitted beside a leader, from what the leader's refits took.

    Parameters
    ----------
    leader : list of RefitCost
        The leader's refits (one, or one per variant).
    max_iter : int
        The refits' own iteration cap (`confirm.REFIT_MAX_ITER`): the bound never exceeds it.

    Returns
    -------
    RefitLimits or None
        At most `CONTENDER_ITER_FACTOR` × the most iterations a converged refit of the leader took (at
        least `CONTENDER_MIN_ITER`, at most `max_iter`) and `CONTENDER_CPU_FACTOR` × its CPU seconds (at
        least `CONTENDER_MIN_CPU_S`); None when no refit of the leader converged (no reference: the
        contenders get the refits' own caps).
    """
    done = [c for c in leader if c.converged]
    if not done:
        return None
    iterations = max(c.iterations for c in done)
    cpu = sum(c.cpu_s for c in done)
    n = int(min(max(CONTENDER_ITER_FACTOR * iterations, CONTENDER_MIN_ITER), max_iter))
    return RefitLimits(max_iter=n, max_cpu_time=max(CONTENDER_MIN_CPU_S, CONTENDER_CPU_FACTOR * cpu),
                       reason=f"a contender gets at most {CONTENDER_ITER_FACTOR}x the iterations of the leader's "
                              f"refit ({iterations}), at least {CONTENDER_MIN_ITER}, and {CONTENDER_CPU_FACTOR:g}x its "
                              f"CPU time ({cpu:.2g} s), at least {CONTENDER_MIN_CPU_S:g} s")
