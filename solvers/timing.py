"""Where a call's wall time goes: a stopwatch of named stages, and the one a fit reports.

A fit's stages (`FIT_STAGES`) are timed by `stage` blocks in `solvers.fit`; a block inside another
counts for the inner stage only, so the stages add up to the whole call (the rest is "other").
The fit's stopwatch is found through a context variable rather than passed down: the stages are
marked in a handful of places, and a fit run inside another call (the discovery loop's refits)
gets its own watch, not its caller's.
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Iterator

# the stopwatch's clock (a name of this module's, so a test can drive it alone)
_now = time.perf_counter

# in the order a fit passes through them
FIT_STAGES = ("prepare", "checks_before", "solve", "diagnostics", "checks_after", "validation")


class Stopwatch:
    """Wall time per named stage; a stage entered inside another pauses the outer one."""

    def __init__(self, stages: tuple[str, ...] = ()):
        self.started = _now()
        self.stages: dict[str, float] = {s: 0.0 for s in stages}
        self._open: list[list] = []   # [name, time it last resumed], innermost last

    def elapsed(self) -> float:
        """Wall time since the stopwatch was made.

        Returns
        -------
        float
            Seconds.
        """
        return _now() - self.started

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Add the wall time of the block to stage `name` (a new name starts a new entry).

        Parameters
        ----------
        name : str
            The stage.

        Yields
        ------
        None
            The block runs timed; its time is added even when it raises.
        """
        now = _now()
        if self._open:
            outer = self._open[-1]
            self.stages[outer[0]] = self.stages.get(outer[0], 0.0) + now - outer[1]
        self._open.append([name, now])
        try:
            yield
        finally:
            now = _now()
            _, resumed = self._open.pop()
            self.stages[name] = self.stages.get(name, 0.0) + now - resumed
            if self._open:
                self._open[-1][1] = now

    def report(self) -> dict[str, float]:
        """Seconds per stage, and the rest of the elapsed time as "other".

        Returns
        -------
        dict of str to float
            Stage name to seconds (rounded to 0.1 ms), plus "other".
        """
        out = {k: round(v, 4) for k, v in self.stages.items()}
        out["other"] = round(max(self.elapsed() - sum(self.stages.values()), 0.0), 4)
        return out


_WATCH: ContextVar[Stopwatch | None] = ContextVar("greyfit_fit_stopwatch", default=None)


@contextmanager
def timed_fit() -> Iterator[Stopwatch]:
    """A new fit stopwatch for the block: `stage` blocks inside it (in this thread) report to it.

    Yields
    ------
    Stopwatch
        The fit's stopwatch (`FIT_STAGES`).
    """
    watch = Stopwatch(FIT_STAGES)
    token = _WATCH.set(watch)
    try:
        yield watch
    finally:
        _WATCH.reset(token)


@contextmanager
def stage(name: str) -> Iterator[None]:
    """Time the block as stage `name` of the current fit's stopwatch; outside `timed_fit`, nothing.

    Parameters
    ----------
    name : str
        One of `FIT_STAGES`.

    Yields
    ------
    None
        The block.
    """
    watch = _WATCH.get()
    if watch is None:
        yield
        return
    with watch.stage(name):
        yield
