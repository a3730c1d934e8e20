"""Claim time against the length of the queue, on PostgreSQL (and SQLite beside it).

A dispatcher claims the oldest queued tasks many times a second; the claim must not slow down as the
queue grows. It reads the first rows of a partial index on the queued rows in claim order
(`tasks.queued_at, job_id, idx`), where it used to sort every queued row.

For each queue length (1 000, 10 000, 100 000, 300 000 tasks queued, in jobs of 1 000), the median
and p95 of 200 claims of one task (each claimed task is put back, so the queue stays the same
length), and beside it the same claim with the old query, which sorted the candidates by the jobs'
creation time through the join.

    python bench/bench_claims.py [--sizes 1000,10000,100000,300000] [--claims 200] [--sqlite]

PostgreSQL: GREYFIT_TEST_DATABASE_URL (default postgresql+psycopg://postgres@127.0.0.1:5432/test);
a schema of its own is made and dropped.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import uuid
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sqlalchemy import bindparam, create_engine, select, text, update  # noqa: E402
from sqlalchemy.engine import make_url  # noqa: E402

from greyfit.service import store as store_module  # noqa: E402
from greyfit.service.store import JobStore, jobs, make_engine, task_requests, tasks  # noqa: E402

OLD_QUERY = (select(tasks.c.job_id, tasks.c.idx, tasks.c.attempts, jobs.c.kind)
             .join(jobs, jobs.c.id == tasks.c.job_id).where(tasks.c.status == "queued")
             .order_by(jobs.c.created_at, tasks.c.idx).limit(bindparam("b_limit")))


def fill(engine, total: int, have: int, job_size: int = 1000) -> None:
    """Add jobs of `job_size` queued tasks until `total` are queued (rows written in bulk)."""
    with engine.begin() as conn:
        for start in range(have, total, job_size):
            job_id, now = str(uuid.uuid4()), time.time() + start * 1e-6
            n = min(job_size, total - start)
            conn.execute(jobs.insert().values(id=job_id, label=None, kind="fit", cancelled=0, created_at=now, total=n))
            conn.execute(tasks.insert(), [{"job_id": job_id, "idx": i, "status": "queued", "attempts": 0,
                                           "queued_at": now} for i in range(n)])
            conn.execute(task_requests.insert(), [{"job_id": job_id, "idx": i, "request": "{}"} for i in range(n)])
        if engine.dialect.name == "postgresql":
            conn.execute(text("ANALYZE tasks"))
            conn.execute(text("ANALYZE jobs"))


def time_claims(store: JobStore, claims: int) -> list[float]:
    out = []
    for _ in range(claims):
        t0 = time.perf_counter()
        claimed = store.claim_many("bench", 30.0, 1000, 1)
        out.append(time.perf_counter() - t0)
        with store.engine.begin() as conn:   # put it back: the queue keeps its length
            for row in claimed:
                conn.execute(update(tasks).where(tasks.c.job_id == row.job_id, tasks.c.idx == row.idx)
                             .values(status="queued", owner=None, lease_until=None, attempts=0))
    return out


def time_select(engine, query, claims: int) -> list[float]:
    """The candidate select alone (FOR UPDATE SKIP LOCKED on PostgreSQL, as the claim runs it)."""
    out = []
    if engine.dialect.name == "postgresql":
        query = query.with_for_update(skip_locked=True, of=tasks)
    for _ in range(claims):
        with engine.begin() as conn:
            t0 = time.perf_counter()
            conn.execute(query, {"b_limit": 1}).all()
            out.append(time.perf_counter() - t0)
    return out


def run(url: str, label: str, sizes: list[int], claims: int) -> None:
    store = JobStore(make_engine(url))
    have = 0
    print(f"\n{label}: ms per claim of one task (median / p95 of {claims})")
    print(f"{'queued':>8} {'whole claim':>18} {'its select':>18} {'old sorted select':>20}")
    for size in sizes:
        fill(store.engine, size, have)
        have = size
        whole = np.array(time_claims(store, claims)) * 1e3
        new = np.array(time_select(store.engine, store_module._CLAIM_CANDIDATES, claims)) * 1e3
        old = np.array(time_select(store.engine, OLD_QUERY, claims)) * 1e3
        print(f"{size:>8} {np.median(whole):8.3f} / {np.percentile(whole, 95):7.3f} "
              f"{np.median(new):8.3f} / {np.percentile(new, 95):7.3f} "
              f"{np.median(old):9.3f} / {np.percentile(old, 95):8.3f}")
    store.engine.dispose()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="1000,10000,100000,300000")
    parser.add_argument("--claims", type=int, default=200)
    parser.add_argument("--sqlite", action="store_true", help="also on SQLite (a temporary file)")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    print(f"load average {os.getloadavg()[0]:.2f} (2 cores)")
    base = os.environ.get("GREYFIT_TEST_DATABASE_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
    schema = f"bench_{uuid.uuid4().hex[:8]}"
    admin = create_engine(base)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    try:
        url = make_url(base).update_query_dict({"options": f"-csearch_path={schema}"})
        run(url.render_as_string(hide_password=False), "PostgreSQL", sizes, args.claims)
    finally:
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()
    if args.sqlite:
        import tempfile
        with tempfile.TemporaryDirectory() as tmp:
            run(f"sqlite:///{tmp}/bench.db", "SQLite", sizes, args.claims)


if __name__ == "__main__":
    main()
