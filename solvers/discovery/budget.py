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
        return time.perf_counter() - self.started

    def left(self) -> float:
        return self.budget_s - self.elapsed()

    def allows(self) -> bool:
        """May another screen or refit start? Records that the budget ended the search if not."""
        if self.left() <= 0:
            self.exhausted = True
            return False
        return True

    @contextmanager
    def phase(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.phases[name] = self.phases.get(name, 0.0) + time.perf_counter() - t0

    def report(self) -> dict[str, float]:
        total = self.elapsed()
        out = {k: round(v, 4) for k, v in self.phases.items()}
        out["other"] = round(max(total - sum(self.phases.values()), 0.0), 4)
        return out
