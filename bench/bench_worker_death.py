"""Workers die with their server: `kill -9` of a real `greyfit serve` (SQLite, 2 workers) while
two long fits run, then how long until every child process of the dead server has ended (workers,
body parser, multiprocessing's resource tracker); the restarted server runs both tasks again.

    python bench/bench_worker_death.py [--rounds 5] [--bound 60]
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.servers import (  # noqa: E402
    alive,
    children_of,
    free_port,
    long_fit,
    start_server,
    stop_server,
    wait_gone,
    wait_running,
)


def one_round(data_dir: Path, bound: float) -> tuple[int, int, float, bool]:
    """(children at the kill, children alive after `bound` s, seconds until none, tasks re-run)."""
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(data_dir, port, workers=2)
    job = httpx.post(f"{base}/v1/jobs", json={"requests": [long_fit(), long_fit()]}, timeout=60).json()
    wait_running(base, job["id"], attempts=1)
    children = children_of(server.pid)
    os.kill(server.pid, signal.SIGKILL)
    killed = time.monotonic()
    server.wait()
    left = wait_gone(children, bound)
    seconds = time.monotonic() - killed
    for pid in alive(left):   # what the old code left: ended here, not by the next server's sweep
        os.kill(pid, signal.SIGKILL)
    restarted = start_server(data_dir, port, workers=2)
    try:
        rerun = all(t["attempts"] == 2 for t in wait_running(base, job["id"], attempts=2))
        httpx.delete(f"{base}/v1/jobs/{job['id']}")
    finally:
        stop_server(restarted)
    return len(children), len(left), seconds, rerun


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--bound", type=float, default=60.0, help="seconds to wait for the children to end")
    args = parser.parse_args()
    print("round  children  alive after bound  seconds until none  tasks run again")
    for r in range(args.rounds):
        with tempfile.TemporaryDirectory() as folder:
            n, left, seconds, rerun = one_round(Path(folder), args.bound)
        print(f"{r:5d}  {n:8d}  {left:17d}  {seconds if not left else float('nan'):18.2f}  {rerun}", flush=True)


if __name__ == "__main__":
    main()
