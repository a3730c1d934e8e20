"""Claim time against the length of the queue, on PostgreSQL and on SQLite.

A dispatcher claims the oldest queued tasks many times a second; the claim must not slow down as the
queue grows. It reads the first rows of a partial index on the queued rows in claim order
(`tasks.queued_at, job_id, idx`), where it used to sort every queued row.

For each queue length (1 000, 10 000, 100 000, 300 000 tasks queued, in jobs of 1 000), the median
and p95 of 100 claims of one task (each claimed task is put back, so the queue stays the same
length); the claim's own select alone; on SQLite the same select without `INDEXED BY` (what the
claim ran before: SQLite has no statistics unless ANALYZE runs, and its planner then took the status
index and sorted every queued row); and the old query, which sorted the candidates by the jobs'
creation time through the join. PostgreSQL's tables are analysed after filling (autovacuum would),
SQLite's are not (nothing analyses the default store).

    python bench/bench_claims.py [--sizes 1000,10000,100000,300000] [--claims 100]
                                 [--stores postgresql,sqlite]

PostgreSQL: GREYFIT_TEST_DATABASE_URL (default postgresql+psycopg://postgres@127.0.0.1:5432/test);
a schema of its own is made and dropped. SQLite: a temporary file.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sqlalchemy import bindparam, create_engine, select, text, update  # noqa: E402
from sqlalchemy.engine import make_url  # noqa: E402

from greyfit.service.jobs import store as store_module  # noqa: E402
from greyfit.service.jobs.store import JobStore, jobs, make_engine, task_requests, tasks  # noqa: E402

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
    """A candidate select alone, in a transaction of its own as the claim runs it."""
    out = []
    for _ in range(claims):
        with engine.begin() as conn:
            t0 = time.perf_counter()
            conn.execute(query, {"b_limit": 1}).all()
            out.append(time.perf_counter() - t0)
    return out


def _cell(ms: np.ndarray) -> str:
    return f"{np.median(ms):8.3f} / {np.percentile(ms, 95):8.3f}"


def run(url: str, label: str, sizes: list[int], claims: int) -> None:
    store = JobStore(make_engine(url))
    postgres = store.engine.dialect.name == "postgresql"
    old = OLD_QUERY.with_for_update(skip_locked=True, of=tasks) if postgres else OLD_QUERY
    selects = {"its select": store._claim_candidates, "old sorted select": old}
    if not postgres:   # what the claim ran before it named its index
        selects = {"its select": store._claim_candidates, "without INDEXED BY": store_module._CLAIM_CANDIDATES,
                   "old sorted select": old}
    print(f"\n{label}: ms per claim of one task (median / p95 of {claims}), load average {os.getloadavg()[0]:.2f}")
    print(f"{'queued':>8} {'whole claim':>19} " + " ".join(f"{name:>19}" for name in selects))
    have = 0
    for size in sizes:
        fill(store.engine, size, have)
        have = size
        whole = np.array(time_claims(store, claims)) * 1e3
        cells = [_cell(np.array(time_select(store.engine, query, claims)) * 1e3) for query in selects.values()]
        print(f"{size:>8} {_cell(whole)} " + " ".join(cells) + f"   (load {os.getloadavg()[0]:.2f})", flush=True)
    store.engine.dispose()


def run_postgres(sizes: list[int], claims: int) -> None:
    base = os.environ.get("GREYFIT_TEST_DATABASE_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
    schema = f"bench_{uuid.uuid4().hex[:8]}"
    admin = create_engine(base)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    try:
        url = make_url(base).update_query_dict({"options": f"-csearch_path={schema}"})
        run(url.render_as_string(hide_password=False), "PostgreSQL", sizes, claims)
    finally:
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="1000,10000,100000,300000")
    parser.add_argument("--claims", type=int, default=100)
    parser.add_argument("--stores", default="postgresql,sqlite", help="postgresql, sqlite or both")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    stores = {s.strip() for s in args.stores.split(",")}
    print(f"load average {os.getloadavg()[0]:.2f} ({os.cpu_count()} cores)")
    if "postgresql" in stores:
        run_postgres(sizes, args.claims)
    if "sqlite" in stores:
        with tempfile.TemporaryDirectory() as tmp:
            run(f"sqlite:///{tmp}/bench.db", "SQLite", sizes, args.claims)


if __name__ == "__main__":
    main()
