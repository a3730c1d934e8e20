"""The job store on SQLite and PostgreSQL: claims once, leases, retries, graceful hand-back."""
import json
import threading
import time

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import (
    Column,
    Float,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    create_engine,
    event,
    inspect,
    select,
    text,
)

from greyfit.service.http.app import create_app
from greyfit.service.jobs.store import JobStore, make_engine, task_requests, tasks
from tests.service.conftest import make_settings, msd_request, wait_for_job


@pytest.fixture
def store(store_url):
    s = JobStore(make_engine(store_url))
    yield s
    s.engine.dispose()


def requests(n):
    return [{"i": i} for i in range(n)]


def joined(slices) -> str:
    """A result's slices as the route sends them: str (PostgreSQL) or UTF-8 bytes (SQLite's blob reads)."""
    return b"".join(s if isinstance(s, bytes) else s.encode() for s in slices).decode()


def results(store, job_id):
    """The job's outcomes as the results route streams them, parsed."""
    return [{"index": idx, "status": status, "result": json.loads(joined(result)) if result else None,
             "error": json.loads(error) if error else None}
            for idx, status, result, error in store.result_pages(job_id)]


def test_claim_finish_once_in_order(store):
    a = store.create_job("fit", requests(2), "a")
    b = store.create_job("fit", requests(1), "b")
    claimed = [store.claim("o1", 30, 3) for _ in range(3)]
    assert [(t.job_id, t.idx) for t in claimed] == [(a, 0), (a, 1), (b, 0)]
    assert store.claim("o1", 30, 3) is None
    assert store.finish(a, 0, "o1", "succeeded", '{"x": 1}', None)
    assert not store.finish(a, 0, "o1", "failed", None, {"type": "X"})       # once only
    assert not store.finish(a, 1, "someone-else", "succeeded", "{}", None)   # not theirs
    assert results(store, a)[0] == {"index": 0, "status": "succeeded", "result": {"x": 1}, "error": None}


def test_claim_many_takes_the_oldest_tasks_in_one_go_and_finish_many_writes_only_its_own(store):
    a = store.create_job("fit", requests(3), "a")
    b = store.create_job("fit", [{"b": 0}, '{"b": 1}'], "b")     # a dict or its JSON text
    first = store.claim_many("o1", 30, 3, 4)
    assert [(t.job_id, t.idx) for t in first] == [(a, 0), (a, 1), (a, 2), (b, 0)]
    assert [t.request for t in first] == ['{"i": 0}', '{"i": 1}', '{"i": 2}', '{"b": 0}']
    rest = store.claim_many("o2", 30, 3, 4)
    assert [(t.job_id, t.idx, t.request) for t in rest] == [(b, 1, '{"b": 1}')]
    assert store.claim_many("o1", 30, 3, 4) == []
    done = [(a, 0, "succeeded", '{"x": 0}', None), (a, 1, "failed", None, {"type": "DataError"}),
            (b, 1, "succeeded", "{}", None)]                  # the last one is o2's
    assert store.finish_many("o1", done) == 2
    assert [r["status"] for r in results(store, a)] == ["succeeded", "failed", "running"]
    assert results(store, a)[1]["error"] == {"type": "DataError"}
    assert store.get_job(b)["tasks"][1]["status"] == "running"


def test_the_sqlite_claim_reads_the_queue_index_and_sorts_nothing(tmp_path):
    """Defect: SQLite keeps no planner statistics unless ANALYZE runs, and without them the claim read
    ix_tasks_status and sorted every queued row ("USE TEMP B-TREE FOR ORDER BY": 10.7 ms a claim at
    10 000 queued, 0.04 ms through the queue index). The plan must be right with and without them."""
    store = JobStore(make_engine(f"sqlite:///{tmp_path / 'greyfit.db'}"))
    try:
        a = store.create_job("fit", requests(3), None)
        store.create_job("fit", requests(2), None)
        selects = []

        def remember(_conn, _cursor, statement, parameters, _context, _many):
            if statement.lstrip().upper().startswith("SELECT") and "ORDER BY" in statement:
                selects.append((statement, parameters))

        event.listen(store.engine, "before_cursor_execute", remember)
        try:
            claimed = store.claim_many("o", 30, 3, 2)      # the statement as the claim runs it
        finally:
            event.remove(store.engine, "before_cursor_execute", remember)
        assert [(t.job_id, t.idx) for t in claimed] == [(a, 0), (a, 1)]
        (statement, parameters), = [s for s in selects if "FROM tasks" in s[0]]
        for analyse in (False, True):
            with store.engine.connect() as conn:
                if analyse:
                    conn.exec_driver_sql("ANALYZE")
                plan = [row[-1] for row in conn.exec_driver_sql("EXPLAIN QUERY PLAN " + statement, parameters)]
            assert any("ix_tasks_queue" in step for step in plan), plan
            assert not any("TEMP B-TREE" in step for step in plan), plan
    finally:
        store.engine.dispose()


def test_sqlite_connections_write_ahead_and_sync_each_commit(tmp_path):
    """A job answered 202 survives a power loss: every pooled connection is in WAL mode with
    synchronous=FULL (2); NORMAL (1), as before, could lose the last commits then."""
    engine = make_engine(f"sqlite:///{tmp_path / 'greyfit.db'}")
    try:
        held = [engine.connect() for _ in range(3)]     # several connections of the pool at once
        try:
            for conn in held:
                assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
                assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 2
        finally:
            for conn in held:
                conn.close()
    finally:
        engine.dispose()


def test_a_store_made_with_requests_in_the_task_rows_is_migrated(store_url):
    """Before request texts had their own table, `tasks` held them: opening such a store moves them
    out once, and its queued, running and finished tasks carry on."""
    old = MetaData()
    Table("jobs", old, Column("id", String(36), primary_key=True), Column("label", String(200)),
          Column("kind", String(20), nullable=False), Column("cancelled", Integer, nullable=False),
          Column("created_at", Float, nullable=False), Column("total", Integer, nullable=False))
    old_tasks = Table("tasks", old, Column("job_id", String(36), primary_key=True),
                      Column("idx", Integer, primary_key=True), Column("status", String(12), nullable=False),
                      Column("request", Text, nullable=False), Column("result", Text), Column("error", Text),
                      Column("attempts", Integer, nullable=False), Column("lease_until", Float),
                      Column("owner", String(36)), Column("started_at", Float), Column("finished_at", Float))
    engine = create_engine(store_url)
    old.create_all(engine)
    with engine.begin() as conn:
        conn.execute(old.tables["jobs"].insert().values(id="j", label=None, kind="fit", cancelled=0,
                                                        created_at=1.0, total=3))
        for row in ({"idx": 0, "status": "succeeded", "result": '{"r": 0}', "attempts": 1},
                    {"idx": 1, "status": "running", "attempts": 1, "owner": "dead-server", "lease_until": 0.0},
                    {"idx": 2, "status": "queued", "attempts": 0}):
            conn.execute(old_tasks.insert().values(job_id="j", request=f'{{"i": {row["idx"]}}}', **row))
    engine.dispose()
    for _ in range(2):                                        # the second opening finds it done
        store = JobStore(make_engine(store_url))
        assert "request" not in {c["name"] for c in inspect(store.engine).get_columns("tasks")}
        with store.engine.connect() as conn:
            moved = conn.execute(select(task_requests.c.idx, task_requests.c.request)
                                 .order_by(task_requests.c.idx)).all()
        assert [tuple(r) for r in moved] == [(0, '{"i": 0}'), (1, '{"i": 1}'), (2, '{"i": 2}')]
        store.engine.dispose()
    store = JobStore(make_engine(store_url))
    try:
        assert store.requeue_expired() == 1                   # the dead server's task comes back
        claimed = store.claim_many("o", 30, 3, 5)
        assert [(t.idx, t.request) for t in claimed] == [(1, '{"i": 1}'), (2, '{"i": 2}')]
        assert results(store, "j")[0]["result"] == {"r": 0}
    finally:
        store.engine.dispose()


def test_concurrent_claims_take_every_task_exactly_once(store):
    job = store.create_job("fit", requests(40), None)
    taken: list[tuple[str, int]] = []
    lock = threading.Lock()

    def worker(owner):
        while (task := store.claim(owner, 30, 3)) is not None:
            store.mark_started(owner, [(task.job_id, task.idx, time.time())])
            store.mark_started(owner, [(task.job_id, task.idx, time.time())])   # charged once per claim
            with lock:
                taken.append((owner, task.idx))

    threads = [threading.Thread(target=worker, args=(f"owner{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert sorted(i for _, i in taken) == list(range(40))
    with store.engine.connect() as conn:
        rows = conn.execute(select(tasks.c.idx, tasks.c.owner, tasks.c.attempts)
                            .where(tasks.c.job_id == job)).all()
    assert all(r.attempts == 1 for r in rows)
    assert {r.owner for r in rows} == {o for o, _ in taken}


def test_lost_worker_is_retried_then_fails_with_the_count(store):
    job = store.create_job("fit", requests(1), None)
    lost = {"type": "WorkerLost", "field": None, "retry": True, "detail": "the worker process died (signal SIGKILL)"}
    for _ in (1, 2):
        assert claim_and_start(store, "o").idx == 0
        assert store.release(job, 0, "o", 3, lost) == "queued"
    assert claim_and_start(store, "o").idx == 0
    assert store.release(job, 0, "o", 3, lost) == "failed"
    record = store.get_job(job)["tasks"][0]
    assert record["status"] == "failed" and record["attempts"] == 3
    assert "lost 3 times" in record["error"] and "SIGKILL" in record["error"]


def claim_and_start(store, owner, lease=30.0):
    """A claim whose worker acknowledged the start (what the dispatcher writes after the ack)."""
    task = store.claim(owner, lease, 3)
    if task is not None:
        store.mark_started(owner, [(task.job_id, task.idx, time.time())])
    return task


def test_graceful_hand_back_does_not_count_an_attempt_but_a_dead_server_does(store):
    job = store.create_job("fit", requests(1), None)
    for _ in range(5):                                  # five graceful restarts mid-task
        assert claim_and_start(store, "o") is not None
        assert store.requeue_owned("o") == 1
    assert store.get_job(job)["tasks"][0]["attempts"] == 0
    for _ in range(3):                                  # three servers that died mid-task: the lease expires
        assert claim_and_start(store, "o", 0.01) is not None
        time.sleep(0.02)
        assert store.requeue_expired() == 1
    assert store.claim("o", 30, 3) is None              # started 3 times, lost 3 times: failed
    record = store.get_job(job)["tasks"][0]
    assert record["status"] == "failed" and "started 3 times" in record["error"]


def test_servers_that_die_between_claim_and_start_charge_no_attempt(store):
    """Defect: the claim charged the attempt, so three server deaths right after a claim failed a
    task 'lost 3 times' that never ran."""
    job = store.create_job("fit", requests(1), None)
    for _ in range(5):                                  # five servers died after their claim, before a start
        assert store.claim("o", 0.01, 3) is not None
        time.sleep(0.02)
        assert store.requeue_expired() == 1
    record = store.get_job(job)["tasks"][0]
    assert record["status"] == "queued" and record["attempts"] == 0 and record["started_at"] is None
    task = claim_and_start(store, "o")                  # the next server runs it
    assert task is not None and store.get_job(job)["tasks"][0]["attempts"] == 1
    assert store.finish(job, 0, "o", "succeeded", "{}", None)


def test_a_claim_given_back_unstarted_keeps_the_attempts_of_earlier_starts(store):
    job = store.create_job("fit", requests(1), None)
    assert claim_and_start(store, "o", 0.01) is not None   # started once, its server died
    time.sleep(0.02)
    assert store.requeue_expired() == 1
    assert store.claim("o", 30, 3) is not None              # claimed, not started: a graceful stop
    assert store.requeue_owned("o") == 1
    assert store.claim("o2", 30, 3) is not None             # claimed by a claim whose answer was lost
    assert store.renew("o2", 30, []) == 1
    assert store.get_job(job)["tasks"][0]["attempts"] == 1


def test_store_write_check(store):
    store.check_writable("probe-owner")
    store.check_writable("probe-owner")                 # idempotent


def test_a_job_runs_end_to_end_on_this_store(store_url, tmp_path):
    with TestClient(create_app(make_settings(tmp_path, database_url=store_url, workers=1))) as c:
        job_id = c.post("/v1/jobs", json={"requests": [msd_request(i, n=41) for i in range(3)]}).json()["id"]
        job = wait_for_job(c, job_id)
        assert job["progress"] == {"done": 3, "total": 3, "succeeded": 3, "failed": 0}
        assert c.get("/readyz").json()["status"] == "ready"


def test_postgres_claims_skip_a_row_another_replica_has_locked(postgres_url):
    """FOR UPDATE SKIP LOCKED: a claim passes over a locked row instead of waiting for its lock."""
    store = JobStore(make_engine(postgres_url))
    try:
        job = store.create_job("fit", requests(2), None)
        got = []
        with store.engine.connect() as other:
            tx = other.begin()
            other.execute(text("SELECT idx FROM tasks WHERE job_id = :j AND idx = 0 FOR UPDATE"), {"j": job})
            claimer = threading.Thread(target=lambda: got.append(store.claim("o", 30, 3)), daemon=True)
            claimer.start()
            claimer.join(timeout=10)
            blocked = claimer.is_alive()
            tx.rollback()
        claimer.join(timeout=10)
        assert not blocked, "the claim waited for another transaction's row lock"
        assert got[0].idx == 1
    finally:
        store.engine.dispose()


def test_postgres_stores_request_and_result_texts_with_lz4(postgres_url):
    store = JobStore(make_engine(postgres_url))
    try:
        with store.engine.connect() as conn:
            if int(conn.execute(text("SHOW server_version_num")).scalar()) < 140000:
                pytest.skip("PostgreSQL < 14 has no per-column compression")
        make_engine(postgres_url).dispose()   # a second server start finds it done
        body = msd_request(3, n=401)
        job = store.create_job("fit", [body], None)
        task = store.claim("o", 30, 1)
        assert json.loads(task.request) == body
        store.finish(job, 0, "o", "succeeded", task.request, None)   # a result of the same size
        with store.engine.connect() as conn:
            stored = conn.execute(text(
                "SELECT pg_column_compression(r.request), pg_column_size(r.request), length(r.request), "
                "pg_column_compression(t.result), pg_column_size(t.result) FROM task_requests r "
                "JOIN tasks t USING (job_id, idx) WHERE job_id = :j"), {"j": job}).one()
        assert stored[0] == "lz4" and stored[3] == "lz4" and max(stored[1], stored[4]) < stored[2], stored
        assert results(store, job)[0]["result"] == body
    finally:
        store.engine.dispose()


def test_a_large_result_is_read_a_slice_at_a_time(store, monkeypatch):
    """A result longer than RESULT_CHUNK comes out of result_pages as slices of at most that many
    characters (a query each), which join to the stored text; a short one is one piece."""
    from greyfit.service.jobs import store as store_module
    monkeypatch.setattr(store_module, "RESULT_CHUNK", 1000)
    job_id = store.create_job("fit", [{"n": 1}, {"n": 2}], None)
    big = json.dumps({"values": list(range(2000)), "name": "é" * 300})   # ~10 kB, not all ASCII
    for _ in range(2):
        task = store.claim("s1", 30, 3)
        store.finish(task.job_id, task.idx, "s1", "succeeded", big if task.idx == 0 else '{"ok": 1}', None)
    pages = list(store.result_pages(job_id))
    slices = list(pages[0][2])
    assert len(slices) > 1 and max(map(len, slices)) <= store_module.RESULT_CHUNK and joined(slices) == big
    assert joined(pages[1][2]) == '{"ok": 1}'
