"""Worker processes that die with their server, and a sweep of those a dead server left behind.

A fit worker is busy in CasADi and Ipopt for seconds to minutes without reading its pipe, so it
does not notice that its server is gone (before: both workers of a server killed with `kill -9`
were still computing 150 s later, beside the restarted server's workers running the same tasks).

- On Linux a worker asks the kernel for SIGKILL when its parent dies (`prctl(PR_SET_PDEATHSIG)`),
  which needs neither the interpreter lock nor a thread of its own. The kernel sends it when the
  *thread* that started the worker ends, so every worker is started from one thread that lives as
  long as the server (`start_process`), never from the dispatcher's, which ends before the workers
  are stopped gracefully.
- Elsewhere a thread of the worker polls its parent's pid (an orphan is adopted by another process).
- `WorkerRegistry` writes each worker's pid and start time into the data folder; a server starting
  on that folder kills the workers of registered servers that are no longer alive (a worker that
  escaped both, e.g. one started while its server was being killed).
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import ctypes
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Optional

log = logging.getLogger("greyfit.service")

PR_SET_PDEATHSIG = 1   # <linux/prctl.h>

# one thread, alive as long as the process, starts every worker (the parent-death signal is tied to it)
_STARTER = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="greyfit-worker-starter")


def start_process(process: Any) -> None:
    """`process.start()` from the lasting starter thread (see the module's docstring)."""
    _STARTER.submit(process.start).result()


def die_with_parent(parent_pid: int) -> None:
    """In a worker: end this process when `parent_pid` (its server) ends, even by SIGKILL."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0:
                if os.getppid() != parent_pid:   # the server died before the request took effect
                    os._exit(0)
                return
        except (OSError, AttributeError):
            pass
    threading.Thread(target=_watch_parent, args=(parent_pid,), name="greyfit-parent-watch", daemon=True).start()


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(1.0)
    os._exit(0)


def start_time(pid: int) -> Optional[int]:
    """A process's start time in clock ticks since boot (/proc/<pid>/stat field 22), or None if it
    is gone (or there is no /proc): with the pid it names one process, whatever reuses the pid later."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return None if fields[0] == b"Z" else int(fields[19])   # a zombie has ended already


class WorkerRegistry:
    """The workers of this server, one file per server in `folder`: `<pid>-<start time>` lines."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        me = os.getpid()
        self.path = self.folder / f"{me}-{start_time(me) or 0}.pids"
        self._lock = threading.Lock()

    def record(self, pid: int) -> None:
        """Add a worker. A full or read-only disk costs only the sweep of this worker, never its start."""
        try:
            with self._lock, open(self.path, "a") as f:
                f.write(f"{pid}-{start_time(pid) or 0}\n")
        except OSError as exc:
            log.warning("could not register worker %d in %s (%s)", pid, self.folder, exc.strerror)

    def close(self) -> None:
        """A server stopping gracefully has stopped its workers: nothing to sweep."""
        with contextlib.suppress(OSError):
            self.path.unlink(missing_ok=True)

    def sweep(self) -> int:
        """Kill the registered workers of servers no longer alive; how many were killed."""
        killed = 0
        for file in self.folder.glob("*.pids"):
            if file == self.path or _alive(file.stem):
                continue
            try:
                entries = file.read_text().split()
            except OSError:
                continue
            for entry in entries:
                if _alive(entry):
                    try:
                        os.kill(int(entry.partition("-")[0]), signal.SIGKILL)
                        killed += 1
                    except (OSError, ValueError):
                        pass
            with contextlib.suppress(OSError):
                file.unlink(missing_ok=True)
        if killed:
            log.warning("killed %d worker process(es) left running by a server that had died", killed)
        return killed


def _alive(entry: str) -> bool:
    """Whether `<pid>-<start time>` names a running process (the same one, not a reused pid)."""
    pid, _, started = entry.partition("-")
    try:
        return start_time(int(pid)) == int(started)
    except ValueError:
        return False
