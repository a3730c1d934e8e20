"""gcc builds handed from a process that is about to exit to a detached one that finishes them.

A fit of a new model structure runs on the interpreter (or tcc's code) while gcc builds its
libraries in the background (`compiled.library`): the next fit of that structure, in any process,
finds them in the disk cache. A command-line process has printed its answer before those builds end
(a discovery's refits start dozens; measured: the answer at 9.8 s, the builds' end at 131 s). Waiting
for them looked like a hang; killing them wasted them. `hand_over` stops them here
(`compiled.abandon_builds`: compilers killed, temporary folders removed) and starts one detached
process (its own session, niced, no terminal) that builds them into the same cache, one at a time
through the machine's compile slots, and exits.

Run as ``python -m greyfit.solvers.dynamics.detached FILE``, FILE a JSON list of
``{"function": casadi serialised Function, "library": path, "work": expected work}``; the file is
deleted once read.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

# below the user's next command: these builds only spare a later process a compile
NICENESS = 10


def hand_over(timeout: float = 1.0) -> tuple[int, int] | None:
    """Stop this process's background builds and start a detached process that finishes them.

    Parameters
    ----------
    timeout : float, optional
        Longest wait, in seconds, for this process's builds to stop.

    Returns
    -------
    (int, int) or None
        The detached process's id and the number of builds it was given; None when no build was
        running or the process could not be started (the builds are then abandoned: a later fit
        starts them again).
    """
    from greyfit.solvers.dynamics import compiled
    builds = compiled.abandon_builds(timeout)
    if not builds:
        return None
    jobs = [{"function": fn.serialize(), "library": str(path), "work": work} for fn, path, work in builds]
    folder = compiled.cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=folder, prefix=".handover-", suffix=".json",
                                         delete=False) as handle:
            json.dump(jobs, handle)
        proc = subprocess.Popen([sys.executable, "-m", __name__, handle.name], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                                close_fds=True)
    except OSError:
        return None
    return proc.pid, len(jobs)


def build_all(jobs: list[dict]) -> int:
    """Build each library (the largest expected work first) into the disk cache.

    Parameters
    ----------
    jobs : list of dict
        As `hand_over` writes them.

    Returns
    -------
    int
        How many libraries are on disk afterwards.
    """
    import casadi as ca

    from greyfit.solvers.dynamics import compiled
    done = 0
    for job in sorted(jobs, key=lambda j: -float(j["work"])):
        library = Path(job["library"])
        if not library.exists():
            fn = ca.Function.deserialize(job["function"])
            compiled._build(fn, library, queue=True, work=float(job["work"]))
        done += library.exists()
    return done


def main(argv: list[str]) -> int:
    """Build the compile jobs a command handed over (their file named on the command line), then exit.

    Parameters
    ----------
    argv : list of str
        The command line: the program and the jobs file.

    Returns
    -------
    int
        The exit code (0 when every build ended).
    """
    path = Path(argv[1])
    try:
        jobs = json.loads(path.read_text())
    finally:
        path.unlink(missing_ok=True)
    os.nice(NICENESS)
    return 0 if build_all(jobs) == len(jobs) else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
