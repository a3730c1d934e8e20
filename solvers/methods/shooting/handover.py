"""Interpret while gcc compiles, go on compiled at the next solve: the first fit of a new model structure.

A structure's per-sample libraries are built in the background (`compiled(...,
interpret_meanwhile=True)`), and its first fit starts at once on the interpreted NLP. Whether the
libraries have arrived is looked at only where a solve begins fresh anyway: at the start of each
Ipopt solve (a multistart's next start, the hybrid solver's next phase, a profile point). Never
inside a solve: an Ipopt solve stopped when gcc finished and restarted from its iterate would lose
its barrier parameter and multipliers and get a new max_iter, so the answer would depend on when
gcc finished, i.e. on machine load.

The compiled kernels are built with -ffp-contract=off and give the interpreter's numbers bit for
bit (tests/solvers/test_handover.py checks it on whole fits), so a solve's result does not depend
on which of the two ran it: the same request gives the same estimates and iterations whether gcc
finished before the fit, during it, or never. Only the speed and `solver.compiled` differ.

So a first fit never waits for gcc longer than interpreting it would take (the foreground compile
it replaces waited 1 s on a quiet machine, a minute on a loaded one); a fit of several solves goes
on compiled from the first solve that begins after the build.
"""
from __future__ import annotations

from typing import Callable, Optional, Protocol, TypeVar


class _Solver(Protocol):
    @property
    def final(self) -> bool: ...   # on gcc's libraries (not the interpreter, nor the quick tier's tcc)


S = TypeVar("S", bound=_Solver)


def built_meanwhile(is_compiled: bool, remake: Optional[Callable[[], Optional[S]]]) -> Optional[S]:
    """The solver made again on gcc's compiled code, if the libraries built in the background exist now.

    Asked before a solve begins, never during one; it never waits for a build.

    Parameters
    ----------
    is_compiled : bool
        Whether the solver about to solve runs gcc's compiled code already (its stand-in until then is
        the interpreter, or the quick tier's tcc libraries: solvers/dynamics/quick.py).
    remake : callable or None
        Makes the solver again (`StructuredSolver.upgrade`); None where nothing is being built.

    Returns
    -------
    solver or None
        The remade solver when it is compiled; None to go on as before (compiled already, nothing
        to wait for, or the build has not ended or failed).
    """
    if is_compiled or remake is None:
        return None
    better = remake()
    return better if better is not None and better.final else None
