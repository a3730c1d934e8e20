"""A loaded machine for determinism tests: CPU-burning processes beside the code under test.

Determinism is tested, not timing: the same request run quietly and under this load must give
the same answer bit for bit (timing goes to bench/).
"""
from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def burning_cpu(processes: int = 2) -> Iterator[None]:
    """`processes` busy-looping Python processes for the duration of the block, killed after it."""
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(processes)]
    try:
        yield
    finally:
        for p in burners:
            p.kill()
            p.wait()
