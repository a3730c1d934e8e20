"""Wall time of a discovery request: where it goes (per phase) and when it is spent (the budget)."""
from __future__ import annotations

import time
from contextlib import contextmanager

PHASES = ("base_fit", "screening", "refits", "validation")


class Clock:
    def __init__(self, budget_s: float):
        self.started = time.perf_counter()
        self.budget_s = budget_s
        self.phases = {p: 0.0 for p in PHASES}
        self.exhausted = False

    def elapsed(self) -> float:
        """Wall time since the clock was made.

        Returns
        -------
        float
            Seconds.
        """
        return time.perf_counter() - self.started

    def left(self) -> float:
        """What is left of the budget.

        Returns
        -------
        float
            Seconds; negative once the budget is spent.
        """
        return self.budget_s - self.elapsed()

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

    @contextmanager
    def phase(self, name: str):
        """Context manager that adds the wall time of its block to phase `name`.

        Parameters
        ----------
        name : str
            One of `PHASES` (another name starts a new entry).

        Yields
        ------
        None
            The block runs timed; its time is added even when it raises.
        """
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.phases[name] = self.phases.get(name, 0.0) + time.perf_counter() - t0

    def report(self) -> dict[str, float]:
        """Seconds per phase, and the rest as "other".

        Returns
        -------
        dict of str to float
            Phase name to seconds (rounded to 0.1 ms), plus "other": elapsed time outside the phases.
        """
        total = self.elapsed()
        out = {k: round(v, 4) for k, v in self.phases.items()}
        out["other"] = round(max(total - sum(self.phases.values()), 0.0), 4)
        return out
