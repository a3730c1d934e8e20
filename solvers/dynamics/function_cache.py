"""Functions derived per record length (`map`, `mapaccum`), kept per model across requests."""
from __future__ import annotations

from collections import OrderedDict

import casadi as ca


class FunctionCache:
    """A handful per model (one per record length seen), oldest dropped: building a `map` of a few
    thousand samples costs about a millisecond, as much as evaluating it."""

    def __init__(self, size: int = 64):
        self.size = size
        self.items: OrderedDict[tuple, ca.Function] = OrderedDict()

    def get(self, key: tuple, build) -> ca.Function:
        """The Function stored under `key`, built by `build()` on a miss; the oldest beyond `size` dropped.

        Parameters
        ----------
        key : tuple
            Identifies the derived Function (e.g. its kind and record length).
        build : callable
            No-argument callable returning the Function; called only on a miss.

        Returns
        -------
        casadi.Function
            The cached or newly built Function, now the most recently used.
        """
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        fn = self.items[key] = build()
        while len(self.items) > self.size:
            self.items.popitem(last=False)
        return fn
