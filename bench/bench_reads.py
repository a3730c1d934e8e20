"""Memory of the reads: the job list over 200 jobs of 1 000 tasks, and four concurrent downloads
of a 31 MB answer (100 results of 310 KB; and one result of 31 MB, read from the store a slice at
a time), against a real `greyfit serve` on loopback (SQLite).

The store is filled directly (200 000 finished task rows with small results and one error each,
and a job of 100 results of 310 KB), then the server is started on it. For each read: the answer's
size and the web process's resident memory before and at its peak (VmHWM, read from /proc), reset
between reads where the kernel allows it (/proc/PID/clear_refs 5).

    python bench/bench_reads.py [--jobs 200] [--tasks 1000]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sqlalchemy import text  # noqa: E402

from greyfit.service.jobs.store import JobStore, make_engine  # noqa: E402
from tests.servers import free_port, start_server, stop_server  # noqa: E402


def fill(data_dir: Path, n_jobs: int, n_tasks: int) -> tuple[str, str]:
    store = JobStore(make_engine(f"sqlite:///{data_dir / 'greyfit.db'}"))
    error = json.dumps({"type": "DataError", "field": "experiments[0]", "detail": "x" * 200})
    for _ in range(n_jobs):
        store.create_job("fit", [{"i": i} for i in range(n_tasks)], "bench")
    big = store.create_job("fit", [{"i": i} for i in range(100)], "big")
    single = store.create_job("fit", [{"i": 0}], "single")
    result = json.dumps({"values": [0.123456789] * 24_000})          # ~310 KB each, 31 MB in all
    with store.engine.begin() as conn:
        conn.execute(text("UPDATE tasks SET status='failed', error=:e, attempts=1, started_at=1, finished_at=2 "
                          "WHERE job_id NOT IN (:big, :single)"), {"e": error, "big": big, "single": single})
        conn.execute(text("UPDATE tasks SET status='succeeded', result=:r, attempts=1, started_at=1, finished_at=2 "
                          "WHERE job_id = :big"), {"r": result, "big": big})
        conn.execute(text("UPDATE tasks SET status='succeeded', result=:r, attempts=1, started_at=1, finished_at=2 "
                          "WHERE job_id = :single"), {"r": json.dumps({"values": [0.123456789] * 2_400_000}),
                                                      "single": single})
    store.engine.dispose()
    return big, single


def kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def reset_peak(pid: int) -> None:
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    except OSError:
        pass


def measure(pid: int, what: str, read) -> None:
    reset_peak(pid)
    before = kb(pid, "VmRSS")
    started = time.perf_counter()
    size = read()
    print(f"{what:48s} answer {size / 1e6:8.2f} MB  RSS {before / 1024:6.0f} MB -> peak "
          f"{kb(pid, 'VmHWM') / 1024:6.0f} MB  ({time.perf_counter() - started:.2f} s)")


def four_downloads(url: str) -> int:
    """Four clients read `url` at once, each streaming the answer (never holding it whole); bytes in all."""
    sizes: list[int] = []

    def download() -> None:
        with httpx.stream("GET", url, timeout=300) as resp:
            sizes.append(sum(len(chunk) for chunk in resp.iter_bytes()))

    threads = [threading.Thread(target=download) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return sum(sizes)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--jobs", type=int, default=200)
    ap.add_argument("--tasks", type=int, default=1000)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        big, single = fill(data, args.jobs, args.tasks)
        port = free_port()
        server = start_server(data, port, workers=1)
        base = f"http://127.0.0.1:{port}"
        try:
            pid = server.pid
            measure(pid, f"GET /v1/jobs?limit=200 ({args.jobs} x {args.tasks} tasks)",
                    lambda: len(httpx.get(f"{base}/v1/jobs", params={"limit": 200}, timeout=300).content))
            for job, what in ((big, "100 results"), (single, "one result")):
                measure(pid, f"4 concurrent GET /v1/jobs/{{id}}/results ({what})",
                        lambda job=job: four_downloads(f"{base}/v1/jobs/{job}/results"))
        finally:
            stop_server(server)


if __name__ == "__main__":
    main()
