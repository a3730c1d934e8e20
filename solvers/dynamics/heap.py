"""Keep freed heap memory in the process between fits (glibc), so a fit's arrays reuse pages.

glibc serves allocations above a threshold (dynamic, 128 KB to 32 MB) with fresh `mmap`s and gives
the top of the heap back to the system once more than twice that threshold is free. A fit allocates
and frees many arrays of 0.1–10 MB (sensitivities, Jacobian rows, the lack-of-fit screen's columns),
so each fit took its pages from the kernel again: 2 300 page faults and 4 ms of system time in a
50 ms fit of the seat model (8 states, 1 000 samples), 5 500 faults and 16 ms at 200 000 samples.
With allocations up to `MMAP_THRESHOLD` served from the heap and up to `TRIM_THRESHOLD` of free heap
kept, the next fit finds its pages mapped (10 faults per seat fit).

The settings are the process's (`mallopt`): they are set once, at the first fit, and
``GREYFIT_HEAP=system`` leaves glibc's defaults alone. The cost is memory a process keeps after its
fits: at most `TRIM_THRESHOLD` of free heap above what it uses. Elsewhere than glibc nothing is set.
"""
from __future__ import annotations

import ctypes
import os
import threading
import warnings

MMAP_THRESHOLD = 32 * 2 ** 20   # glibc's own ceiling for its dynamic threshold
TRIM_THRESHOLD = 64 * 2 ** 20
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3   # malloc.h

_lock = threading.Lock()
_done = False   # set once per process
_kept = False   # whether glibc took the thresholds


def keep_heap() -> bool:
    """Set glibc's thresholds once per process, unless ``GREYFIT_HEAP=system``.

    Returns
    -------
    bool
        Whether this process's allocator runs with the thresholds above.
    """
    global _done
    if _done:
        return _kept
    with _lock:
        if not _done:
            _set()
            _done = True
    return _kept


def _set() -> None:
    global _kept
    setting = os.environ.get("GREYFIT_HEAP", "kept").strip().lower()
    if setting == "system":
        return
    if setting != "kept":   # a typo would otherwise go unseen
        warnings.warn(f"GREYFIT_HEAP={setting!r} is not one of kept, system: greyfit uses 'kept'",
                      RuntimeWarning, stacklevel=4)
    try:   # glibc answers with its name and version; elsewhere there is no such name
        if not (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"):
            return
    except (AttributeError, ValueError, OSError):
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _kept = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
