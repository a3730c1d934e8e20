"""Job store on SQLAlchemy Core: SQLite by default, PostgreSQL for several replicas.

A task is claimed by a conditional UPDATE (status = 'queued'; on PostgreSQL the candidate row is
selected `FOR UPDATE SKIP LOCKED`, so concurrent replicas pass each other instead of colliding),
so two dispatchers never run the same task; a running task holds a lease that its dispatcher
renews, and tasks whose lease has expired (their server died) are re-queued — a job accepted is
never lost. `attempts` counts the starts a worker acknowledged (`mark_started`), not the claims: a
server that dies between a claim and a start costs the task nothing; a graceful shutdown hands its
tasks back without counting one.

Request texts live in their own table: a task row is written on every claim, lease renewal and
outcome, and a database rewrites the whole row (SQLite does, PostgreSQL copies it), request
included — megabytes for a large request. Stores made before that are migrated when opened.
"""
from __future__ import annotations

import json
import os
import sqlite3
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, cast

from sqlalchemy import (
    Column,
    Float,
    Index,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    bindparam,
    case,
    create_engine,
    event,
    func,
    inspect,
    literal_column,
    select,
    text,
    tuple_,
    update,
)
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.exc import DBAPIError, IntegrityError, InterfaceError, InternalError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout

from greyfit.schemas.jobs import JobStatus

metadata = MetaData()

jobs = Table(
    "jobs", metadata,
    Column("id", String(36), primary_key=True),
    Column("label", String(200)),
    Column("kind", String(20), nullable=False),
    Column("cancelled", Integer, nullable=False, default=0),
    Column("created_at", Float, nullable=False),
    Column("total", Integer, nullable=False),
    # the client (named API key) that created the job, the only one that sees it; '' for the single
    # GREYFIT_API_KEY and for a server without keys (and for every job made before clients existed)
    Column("client", String(64), nullable=False, default="", server_default=""),
)
# a client's list of its own jobs, newest first, without reading the others'
CLIENT_INDEX = Index("ix_jobs_client", jobs.c.client, jobs.c.created_at)

tasks = Table(
    "tasks", metadata,
    Column("job_id", String(36), primary_key=True),
    Column("idx", Integer, primary_key=True),
    Column("status", String(12), nullable=False, index=True),
    Column("result", Text),
    Column("error", Text),
    Column("attempts", Integer, nullable=False, default=0),
    Column("lease_until", Float),
    Column("owner", String(36)),
    Column("started_at", Float),
    Column("finished_at", Float),
    Column("queued_at", Float),   # the job's creation time, copied: the claim reads the queue in this order
)
# The queue in claim order, queued rows only: a claim reads the first rows of this index instead of
# sorting every queued row (0.4 ms at 1 000 queued, 313 ms at 300 000 with the sort; bench_claims.py)
QUEUE_INDEX = Index("ix_tasks_queue", tasks.c.queued_at, tasks.c.job_id, tasks.c.idx,
                    postgresql_where=tasks.c.status == "queued", sqlite_where=tasks.c.status == "queued")

# written once when the job is created, read when the task is claimed (and by a job's report page)
task_requests = Table(
    "task_requests", metadata,
    Column("job_id", String(36), primary_key=True),
    Column("idx", Integer, primary_key=True),
    Column("request", Text, nullable=False),
)

# Idempotency-Key of a job's creation (the IETF httpapi draft's semantics): the same key and body
# give the job created the first time; written in the job's own transaction, so a job exists with
# its key or not at all
idempotency_keys = Table(
    "idempotency_keys", metadata,
    Column("key", String(200), primary_key=True),
    Column("fingerprint", String(64), nullable=False),
    Column("job_id", String(36), nullable=False),
    Column("created_at", Float, nullable=False),
)

# the named API keys (service/http/clients.py): a key is stored as the SHA-256 of its text (keys are 256
# random bits: no slow hash needed); revoked keys keep their row, so a name is never given twice
api_keys = Table(
    "api_keys", metadata,
    Column("name", String(64), primary_key=True),
    Column("digest", String(64), nullable=False, unique=True),
    Column("created_at", Float, nullable=False),
    Column("revoked_at", Float),
)

# one row per server: readiness writes it to prove that the store accepts writes
store_probes = Table(
    "store_probes", metadata,
    Column("owner", String(36), primary_key=True),
    Column("at", Float, nullable=False),
)

# the statements of every claim and outcome, built once (building them costs more than running them)
_CLAIM_CANDIDATES = (select(tasks.c.job_id, tasks.c.idx, tasks.c.attempts, jobs.c.kind)
                     .join(jobs, jobs.c.id == tasks.c.job_id)
                     .where(tasks.c.status == "queued")
                     .order_by(tasks.c.queued_at, tasks.c.job_id, tasks.c.idx).limit(bindparam("b_limit")))
# PostgreSQL: a row another replica is claiming is passed over, not waited for
_CLAIM_CANDIDATES_SKIP_LOCKED = _CLAIM_CANDIDATES.with_for_update(skip_locked=True, of=tasks)
# SQLite: the same select naming its index. SQLite keeps no statistics unless ANALYZE runs, and
# without them its planner read ix_tasks_status and sorted every queued row in a temporary B-tree
# (10.7 ms a claim at 10 000 queued; 0.04 ms through the queue index). INDEXED BY holds whatever the
# statistics say; the status is written out, not bound: SQLite matches a partial index's WHERE
# against the statement's text (with `status = ?` INDEXED BY fails to prepare: "no query solution").
_CLAIM_CANDIDATES_SQLITE = text(
    f"SELECT tasks.job_id, tasks.idx, tasks.attempts, jobs.kind FROM tasks INDEXED BY {QUEUE_INDEX.name} "
    "JOIN jobs ON jobs.id = tasks.job_id WHERE tasks.status = 'queued' "
    "ORDER BY tasks.queued_at, tasks.job_id, tasks.idx LIMIT :b_limit").columns(
    tasks.c.job_id, tasks.c.idx, tasks.c.attempts, jobs.c.kind)
_REQUEST_TEXTS = select(task_requests.c.idx, task_requests.c.request).where(
    task_requests.c.job_id == bindparam("b_job"), task_requests.c.idx.in_(bindparam("b_idxs", expanding=True)))
_START = (update(tasks)
          .where(tasks.c.job_id == bindparam("b_job"), tasks.c.idx.in_(bindparam("b_idxs", expanding=True)),
                 tasks.c.status == "queued")
          .values(status="running", owner=bindparam("b_owner"), lease_until=bindparam("b_lease"),
                  started_at=None))
# a worker acknowledged the start: the attempt is charged now, once per claim (started_at IS NULL)
_STARTED = (update(tasks)
            .where(tasks.c.job_id == bindparam("b_job"), tasks.c.idx == bindparam("b_idx"),
                   tasks.c.status == "running", tasks.c.owner == bindparam("b_owner"), tasks.c.started_at.is_(None))
            .values(started_at=bindparam("b_at"), attempts=tasks.c.attempts + 1))
# a task handed back: the attempt of its claim is given back if it had been charged (started)
_UNCHARGED = tasks.c.attempts - case((tasks.c.started_at.is_(None), 0), else_=1)
_JOB = select(jobs).where(jobs.c.id == bindparam("b_id"))
_JOB_TASKS = (select(tasks.c.idx, tasks.c.status, tasks.c.attempts, tasks.c.started_at, tasks.c.finished_at,
                     tasks.c.error)
              .where(tasks.c.job_id == bindparam("b_id")).order_by(tasks.c.idx))
# a result is read whole only up to RESULT_CHUNK characters; a longer one a slice a query, so that
# streaming it holds one slice in memory: four downloads of a 31.6 MB result held 519 MB when it was
# read whole. PostgreSQL: length and substr (in characters; the server reads the TOAST slices).
# SQLite: its incremental blob I/O (bytes), since its substr and length load the whole value into the
# web process (SQLite runs in it) to count characters
RESULT_CHUNK = 1 << 20
_RESULTS_SQLITE = (select(tasks.c.idx, tasks.c.status, literal_column("tasks.rowid"), tasks.c.error,
                          tasks.c.result.is_not(None))
                   .where(tasks.c.job_id == bindparam("b_id")).order_by(tasks.c.idx))
_RESULT_LENGTH = func.length(tasks.c.result)
_RESULTS = (select(tasks.c.idx, tasks.c.status,
                   case((_RESULT_LENGTH <= bindparam("b_chunk"), tasks.c.result), else_=None), tasks.c.error,
                   _RESULT_LENGTH)
            .where(tasks.c.job_id == bindparam("b_id")).order_by(tasks.c.idx))
_RESULT_SLICE = (select(func.substr(tasks.c.result, bindparam("b_from"), bindparam("b_chunk")))
                 .where(tasks.c.job_id == bindparam("b_id"), tasks.c.idx == bindparam("b_idx")))
_FINISH = (update(tasks)
           .where(tasks.c.job_id == bindparam("b_job"), tasks.c.idx == bindparam("b_idx"),
                  tasks.c.status == "running", tasks.c.owner == bindparam("b_owner"))
           .values(status=bindparam("b_status"), finished_at=bindparam("b_at"), result=bindparam("b_result"),
                   error=bindparam("b_error"), lease_until=None))


class _Raced(Exception):
    """A claim found a task taken by another server between its select and its update."""


class IdempotencyKeyReused(Exception):
    """An Idempotency-Key sent again with another body: answered 422."""


class StoreUnavailable(Exception):
    """The job store cannot take writes (deleted, read-only, full or unreachable): answered 503.

    `public` says which component failed without the database's text (paths, hosts, ports)."""

    def __init__(self, detail: str, public: str = "the job store does not take writes"):
        super().__init__(detail)
        self.public = public


# what a store that fails raises: StoreUnavailable, and the database driver's errors as SQLAlchemy
# wraps them (read-only is InternalError on PostgreSQL, OperationalError on SQLite)
STORE_ERRORS = (StoreUnavailable, OperationalError, InternalError, InterfaceError, PoolTimeout)


class DataDirNotWritable(RuntimeError):
    """The data directory (SQLite store, compiled-model cache) cannot be written: the server must
    not start. The message is one line that says which folder, as whom, and what to do."""


def check_data_dir(data_dir: Path, database_file: Optional[Path] = None) -> None:
    """Raise DataDirNotWritable unless a file can be created in `data_dir` (made if missing) and
    `database_file`, if it exists, opened for writing.

    It tries: os.access answers from the permission bits, which root passes on any folder, also
    one on a read-only file system."""
    who = f"uid {os.geteuid()}" if hasattr(os, "geteuid") else "this user"
    fix = ("make it writable for that user (a host folder mounted on it: chown it to that uid) "
           "or point GREYFIT_DATA_DIR at a folder it can write")
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
        probe = data_dir / f".greyfit-write-check-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        os.close(fd)
        probe.unlink()
        if database_file is not None and database_file.exists():
            with open(database_file, "ab"):
                pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        # the probe's own name says nothing: name the folder, or the database file that refused
        place = f" on {exc.filename}" if exc.filename and ".greyfit-write-check-" not in str(exc.filename) else ""
        raise DataDirNotWritable(f"the data directory {data_dir.resolve()} is not writable by {who} "
                                 f"({reason}{place}): {fix}") from None


@dataclass
class TaskRow:
    job_id: str
    idx: int
    kind: str
    request: str   # the request's JSON text, handed to the worker unparsed


def make_engine(url: str) -> Engine:
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _pragmas(dbapi_conn, _record):  # WAL: readers do not block the dispatcher's writes
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            # FULL: a job answered 202 survives a power loss (NORMAL may lose the last commits then)
            cur.execute("PRAGMA synchronous=FULL")
            cur.close()
            _refuse_read_only(dbapi_conn)

        event.listen(engine, "handle_error", _drop_read_only_connection)
    else:
        engine = create_engine(url, pool_pre_ping=True)
    metadata.create_all(engine)
    _move_requests_out_of_tasks(engine)
    _add_queue_order(engine)
    _add_job_clients(engine)
    _compress_texts_with_lz4(engine)
    return engine


# SQLite opens a file it cannot write (write-protected, immutable, a read-only mount) read-only
# instead of failing, and a pooled connection stays so for life: every later write fails although
# the file is writable again. A connection proves it can write when it is made, and one that
# meets a read-only error is dropped from the pool.
_WRITE_CHECK = "_greyfit_write_check"


def _refuse_read_only(dbapi_conn) -> None:
    """Fail the connection unless it can take a write: a write statement that changes nothing
    still needs a writable database (`attempt to write a readonly database` otherwise)."""
    cur = dbapi_conn.cursor()
    try:
        cur.execute(f"CREATE TABLE IF NOT EXISTS {_WRITE_CHECK} (x INTEGER)")
        cur.execute(f"DELETE FROM {_WRITE_CHECK} WHERE 0")
        dbapi_conn.commit()
    finally:
        cur.close()


def _drop_read_only_connection(context) -> None:
    """A read-only error invalidates the connection (and the pool), like a lost connection."""
    if "readonly database" in str(context.original_exception):
        context.is_disconnect = True


LZ4_COLUMNS = (("task_requests", "request"), ("tasks", "result"), ("tasks", "error"))


def _compress_texts_with_lz4(engine: Engine) -> None:
    """PostgreSQL >= 14 stores the request and result texts compressed with lz4 instead of pglz.

    Texts over ~2 kB are compressed on write: storing a job of 100 fits of 401 samples took 320 ms with
    pglz and 190-215 ms with lz4 (median of 5, this machine), on the cores the workers share. Values
    written before keep their compression. Checked first, so a restart (or a replica) does not take the
    table lock again; a server built without lz4 keeps pglz."""
    if engine.dialect.name != "postgresql":
        return
    with engine.connect() as conn:
        if int(conn.execute(text("SHOW server_version_num")).scalar_one()) < 140000:
            return
        current: dict[str, str] = dict(conn.execute(text(
            "SELECT c.relname || '.' || a.attname, a.attcompression FROM pg_attribute a "
            "JOIN pg_class c ON c.oid = a.attrelid WHERE c.relname IN ('tasks', 'task_requests') "
            "AND c.relnamespace = to_regnamespace(current_schema())::oid")).all())
    todo = [(table, column) for table, column in LZ4_COLUMNS if current.get(f"{table}.{column}") != "l"]
    if not todo:
        return
    try:
        with engine.begin() as conn:
            for table, column in todo:
                conn.execute(text(f"ALTER TABLE {table} ALTER COLUMN {column} SET COMPRESSION lz4"))
    except DBAPIError:   # "compression method lz4 not supported": built without lz4
        return


def _move_requests_out_of_tasks(engine: Engine) -> None:
    """A store made when `tasks` held the request texts: move them to `task_requests`, once.

    One transaction: a server stopped half-way leaves the store as it was. On PostgreSQL the table
    is locked first, so replicas starting together migrate it once (the others find it done)."""
    if "request" not in {c["name"] for c in inspect(engine).get_columns("tasks")}:
        return
    with engine.begin() as conn:
        if engine.dialect.name == "postgresql":
            conn.execute(text("LOCK TABLE tasks IN ACCESS EXCLUSIVE MODE"))
            if "request" not in {c["name"] for c in inspect(conn).get_columns("tasks")}:
                return
        conn.execute(text("INSERT INTO task_requests (job_id, idx, request) SELECT job_id, idx, request FROM tasks"))
        conn.execute(text("ALTER TABLE tasks DROP COLUMN request"))


def _add_queue_order(engine: Engine) -> None:
    """A store made before `tasks.queued_at`: add it (from the jobs' creation times) and its index, once."""
    _add_column_once(engine, "tasks", "queued_at", QUEUE_INDEX, (
        "ALTER TABLE tasks ADD COLUMN queued_at FLOAT",
        "UPDATE tasks SET queued_at = (SELECT created_at FROM jobs WHERE jobs.id = tasks.job_id)"))


def _add_job_clients(engine: Engine) -> None:
    """A store made before clients: add `jobs.client` ('' for every job: the single key's, or
    anyone's on a server without keys) and its index, once."""
    _add_column_once(engine, "jobs", "client", CLIENT_INDEX,
                     ("ALTER TABLE jobs ADD COLUMN client VARCHAR(64) NOT NULL DEFAULT ''",))


def _add_column_once(engine: Engine, table: str, column: str, index: Index, statements: tuple[str, ...]) -> None:
    """Run `statements` (which add `table.column`) and create `index`, in one transaction, unless the
    column exists. On PostgreSQL the table is locked first, so replicas starting together migrate it
    once (the others find it done)."""
    if column in {c["name"] for c in inspect(engine).get_columns(table)}:
        return
    with engine.begin() as conn:
        if engine.dialect.name == "postgresql":
            conn.execute(text(f"LOCK TABLE {table} IN ACCESS EXCLUSIVE MODE"))
            if column in {c["name"] for c in inspect(conn).get_columns(table)}:
                return
        for statement in statements:
            conn.execute(text(statement))
        index.create(conn)


def _chunks(items: list, size: int) -> list[list]:
    return [items[i:i + size] for i in range(0, len(items), size)]


def _sqlite_file(engine: Engine) -> Optional[str]:
    url = make_url(str(engine.url))
    if url.get_backend_name() != "sqlite" or not url.database or url.database == ":memory:":
        return None
    return os.path.abspath(url.database)


class JobStore:
    def __init__(self, engine: Engine):
        self.engine = engine
        self.sqlite_path = _sqlite_file(engine)
        # the file we opened: a file deleted or replaced under a running server takes jobs to nowhere
        self._sqlite_id = self._file_identity()
        self._claim_candidates = {"postgresql": _CLAIM_CANDIDATES_SKIP_LOCKED,
                                  "sqlite": _CLAIM_CANDIDATES_SQLITE}.get(engine.dialect.name, _CLAIM_CANDIDATES)

    def _file_identity(self) -> Optional[tuple[int, int]]:
        if self.sqlite_path is None:
            return None
        try:
            st = os.stat(self.sqlite_path)
        except FileNotFoundError:
            return None
        return st.st_dev, st.st_ino

    def check_file(self) -> None:
        """Raise StoreUnavailable if the SQLite file was deleted or replaced since the server started."""
        if self.sqlite_path is not None and self._file_identity() != self._sqlite_id:
            raise StoreUnavailable(f"the SQLite job store {self.sqlite_path} was deleted or replaced while the "
                                   "server ran; jobs written now would be lost: restart the server",
                                   "the SQLite job store file was deleted or replaced while the server ran; "
                                   "restart the server")

    def check_writable(self, owner: str) -> None:
        """Prove the store takes a write (readiness); raise StoreUnavailable saying why not."""
        self.check_file()
        try:
            with self.engine.begin() as conn:
                conn.execute(store_probes.delete().where(store_probes.c.owner == owner))
                conn.execute(store_probes.insert().values(owner=owner, at=time.time()))
        except Exception as exc:   # what the database says is the useful detail
            raise StoreUnavailable(f"the job store does not take writes: {type(exc).__name__}: "
                                   f"{str(exc).splitlines()[0][:300]}",
                                   f"the job store does not take writes ({type(exc).__name__})") from exc

    def create_job(self, kind: str, requests: list[dict | str], label: Optional[str],
                   idempotency: Optional[tuple[str, str]] = None, client: str = "") -> str:
        """A job of one task per request (a dict, or its JSON text, stored as it is), `client`'s.

        `idempotency`: (key, fingerprint of kind, label and requests). A key already stored with the
        same fingerprint returns its job, no new one; with another, IdempotencyKeyReused."""
        self.check_file()
        if idempotency is not None:
            existing = self._job_of_key(*idempotency)
            if existing is not None:
                return existing
        try:
            return self._insert_job(kind, requests, label, idempotency, client)
        except IntegrityError:
            if idempotency is None:
                raise
            existing = self._job_of_key(*idempotency)   # a concurrent request with the key won the race
            if existing is None:
                raise
            return existing

    def _job_of_key(self, key: str, fingerprint: str) -> Optional[str]:
        with self.engine.connect() as conn:
            row = conn.execute(select(idempotency_keys.c.fingerprint, idempotency_keys.c.job_id)
                               .where(idempotency_keys.c.key == key)).first()
        if row is None:
            return None
        if row.fingerprint != fingerprint:
            raise IdempotencyKeyReused(key)
        return row.job_id

    def _insert_job(self, kind: str, requests: list[dict | str], label: Optional[str],
                    idempotency: Optional[tuple[str, str]], client: str) -> str:
        job_id = str(uuid.uuid4())
        now = time.time()
        with self.engine.begin() as conn:
            if idempotency is not None:
                conn.execute(idempotency_keys.insert().values(key=idempotency[0], fingerprint=idempotency[1],
                                                              job_id=job_id, created_at=now))
            conn.execute(jobs.insert().values(id=job_id, label=label, kind=kind, cancelled=0,
                                              created_at=now, total=len(requests), client=client))
            conn.execute(tasks.insert(), [
                {"job_id": job_id, "idx": i, "status": "queued", "attempts": 0, "queued_at": now}
                for i in range(len(requests))])
            conn.execute(task_requests.insert(), [
                {"job_id": job_id, "idx": i, "request": r if isinstance(r, str) else json.dumps(r)}
                for i, r in enumerate(requests)])
        return job_id

    def get_job(self, job_id: str, task_offset: int = 0, task_limit: Optional[int] = None,
                client: Optional[str] = None) -> Optional[dict[str, Any]]:
        """A job with its task counts by status and times (`counts`, `started_at`, `finished_at`, as
        `list_jobs`) and its tasks from `task_offset`, `task_limit` of them at most (None: all; 0: none),
        read a page at a time from the database; None if there is no such job (of `client`, if given)."""
        query = _JOB if client is None else _JOB.where(jobs.c.client == client)
        with self.engine.connect() as conn:
            job = conn.execute(query, {"b_id": job_id}).mappings().first()
            if job is None:
                return None
            summary = _summaries(conn, [job_id])[job_id]
            query = _JOB_TASKS if task_offset == 0 and task_limit is None else \
                _JOB_TASKS.where(tasks.c.idx >= task_offset).limit(task_limit)   # idx: 0 .. total-1
            rows = [] if task_limit == 0 else conn.execute(query, {"b_id": job_id}).all()
        return {"job": dict(job), **summary, "tasks": [r._asdict() for r in rows]}

    def list_jobs(self, offset: int, limit: int, client: Optional[str] = None) -> tuple[list[dict], int]:
        """A page of jobs (`client`'s only, if given), newest first, each with its task counts by status
        (`counts`), not its tasks: the page of 200 jobs of 1 000 tasks each was 73.5 MB with the tasks."""
        mine = (jobs.c.client == client,) if client is not None else ()
        with self.engine.connect() as conn:
            count = conn.execute(select(func.count()).select_from(jobs).where(*mine)).scalar_one()
            page = conn.execute(select(jobs).where(*mine).order_by(jobs.c.created_at.desc(), jobs.c.id)
                                .offset(offset).limit(limit)).mappings().all()
            summary = _summaries(conn, [j["id"] for j in page])
        return [{"job": dict(j), **summary[j["id"]]} for j in page], count

    def result_pages(self, job_id: str, offset: int = 0, limit: Optional[int] = None, page: int = 20):
        """(idx, status, result JSON as an iterator of its slices or None, error JSON) of each task
        from `offset`, `page` rows a query: an answer streamed from this holds one page of small
        results in memory, and one slice of a large one, not every result of the job."""
        last, left = offset - 1, limit
        sqlite = self.engine.dialect.name == "sqlite"
        while left is None or left > 0:
            size = page if left is None else min(page, left)
            with self.engine.connect() as conn:
                rows = conn.execute((_RESULTS_SQLITE if sqlite else _RESULTS).where(tasks.c.idx > last).limit(size),
                                    {"b_id": job_id, "b_chunk": RESULT_CHUNK}).all()
            for idx, status, small, error, length in rows:
                if sqlite:   # (rowid, whether there is a result)
                    slices = self._blob_slices(small) if length else None
                else:
                    slices = None if not length else iter([small]) if small is not None else \
                        self._result_slices(job_id, idx, length)
                yield idx, status, slices, error
            if len(rows) < size:
                return
            last = rows[-1][0]
            left = None if left is None else left - len(rows)

    def _blob_slices(self, rowid: int):
        """A result on SQLite, RESULT_CHUNK bytes a read of its blob (a connection taken for each read:
        a slow client holds none between them)."""
        chunk, at = RESULT_CHUNK, 0
        while True:
            with self.engine.connect() as conn:
                sqlite = cast(sqlite3.Connection, conn.connection.driver_connection)   # (an SQLite engine's)
                with sqlite.blobopen("tasks", "result", rowid, readonly=True) as blob:
                    blob.seek(at)
                    data = blob.read(chunk)
            if data:
                yield data
            if len(data) < chunk:
                return
            at += len(data)

    def _result_slices(self, job_id: str, idx: int, length: int):
        """A long result, RESULT_CHUNK characters a query (a stored result never changes: no transaction)."""
        chunk = RESULT_CHUNK
        for start in range(1, length + 1, chunk):
            with self.engine.connect() as conn:
                yield conn.execute(_RESULT_SLICE, {"b_id": job_id, "b_idx": idx, "b_from": start,
                                                   "b_chunk": chunk}).scalar_one()

    def cancel(self, job_id: str) -> list[int]:
        """Cancel queued tasks now and return the running ones (the dispatcher stops them)."""
        now = time.time()
        with self.engine.begin() as conn:
            conn.execute(update(jobs).where(jobs.c.id == job_id).values(cancelled=1))
            conn.execute(update(tasks).where(tasks.c.job_id == job_id, tasks.c.status == "queued")
                         .values(status="cancelled", finished_at=now))
            running = conn.execute(select(tasks.c.idx).where(
                tasks.c.job_id == job_id, tasks.c.status == "running")).scalars().all()
        return list(running)

    def claim(self, owner: str, lease_seconds: float, max_attempts: int) -> Optional[TaskRow]:
        """Take the oldest queued task, or None; safe against concurrent dispatchers."""
        claimed = self.claim_many(owner, lease_seconds, max_attempts, 1)
        return claimed[0] if claimed else None

    def claim_many(self, owner: str, lease_seconds: float, max_attempts: int, limit: int) -> list[TaskRow]:
        """Take up to `limit` of the oldest queued tasks in one transaction.

        A claim charges no attempt: `mark_started` does, when a worker acknowledges the start."""
        for _ in range(5):
            try:
                with self.engine.begin() as conn:
                    claimed = self._claim_in(conn, owner, lease_seconds, max_attempts, limit)
            except _Raced:
                continue
            if claimed is not None:
                return claimed
            # every candidate had used its attempts: look again
        return []

    def _claim_in(self, conn, owner: str, lease_seconds: float, max_attempts: int,
                  limit: int) -> Optional[list[TaskRow]]:
        # the texts are read for the claimed tasks only: sorting the candidates with them would read
        # every queued request
        rows = conn.execute(self._claim_candidates, {"b_limit": limit}).all()
        if not rows:
            return []
        now = time.time()
        by_job: dict[str, list] = {}
        for row in rows:
            if row.attempts >= max_attempts:
                self._fail_queued(conn, row.job_id, row.idx, now, (
                    f"the task was started {row.attempts} times and each time its worker or server was lost "
                    "(crash, kill or hang); not retried again"))
            else:
                by_job.setdefault(row.job_id, []).append(row)
        claimed = []
        for job_id, group in by_job.items():   # one statement per job, not per task
            texts = dict(conn.execute(_REQUEST_TEXTS, {"b_job": job_id, "b_idxs": [r.idx for r in group]}).all())
            for row in [r for r in group if r.idx not in texts]:
                self._fail_queued(conn, job_id, row.idx, now, "the task's request is missing from the job store")
            group = [r for r in group if r.idx in texts]
            if not group:
                continue
            res = conn.execute(_START, {"b_job": job_id, "b_idxs": [r.idx for r in group], "b_owner": owner,
                                        "b_lease": now + lease_seconds})
            if res.rowcount != len(group):   # another server took one meanwhile: roll back, look again
                raise _Raced()
            claimed += [TaskRow(job_id, r.idx, r.kind, texts[r.idx]) for r in group]
        return claimed or None

    @staticmethod
    def _fail_queued(conn, job_id: str, idx: int, now: float, detail: str) -> None:
        conn.execute(update(tasks).where(tasks.c.job_id == job_id, tasks.c.idx == idx, tasks.c.status == "queued")
                     .values(status="failed", finished_at=now, error=json.dumps({"type": "WorkerLost",
                                                                                 "detail": detail})))

    def renew(self, owner: str, lease_seconds: float, held: list[tuple[str, int]]) -> int:
        """Extend the leases of the tasks `owner` holds; give back the ones it owns but does not hold.

        A claim whose COMMIT's answer was lost (the connection dropped after the database committed)
        leaves tasks owned by this server that its dispatcher never learned of: renewing every row
        it owns would keep them running, unrun, for ever. They go back to the queue without an
        attempt counted (they never started: no start was acknowledged). Returns how many were given back."""
        now = time.time()
        with self.engine.begin() as conn:
            owned = conn.execute(select(tasks.c.job_id, tasks.c.idx)
                                 .where(tasks.c.owner == owner, tasks.c.status == "running")).all()
            keep = set(held)
            unknown = [(r.job_id, r.idx) for r in owned if (r.job_id, r.idx) not in keep]
            known = [(r.job_id, r.idx) for r in owned if (r.job_id, r.idx) in keep]
            for chunk in _chunks(known, 500):
                conn.execute(update(tasks).where(tuple_(tasks.c.job_id, tasks.c.idx).in_(chunk),
                                                 tasks.c.owner == owner, tasks.c.status == "running")
                             .values(lease_until=now + lease_seconds))
            for chunk in _chunks(unknown, 500):
                conn.execute(update(tasks).where(tuple_(tasks.c.job_id, tasks.c.idx).in_(chunk),
                                                 tasks.c.owner == owner, tasks.c.status == "running")
                             .values(status="queued", owner=None, lease_until=None,
                                     attempts=_UNCHARGED, started_at=None))
        return len(unknown)

    def mark_started(self, owner: str, started: list[tuple[str, int, float]], conn=None) -> None:
        """Charge an attempt to each (job_id, idx, at) whose worker acknowledged the start, once per claim."""
        if not started:
            return
        params = [{"b_job": j, "b_idx": i, "b_owner": owner, "b_at": at} for j, i, at in started]
        if conn is not None:
            conn.execute(_STARTED, params)
            return
        with self.engine.begin() as own:
            own.execute(_STARTED, params)

    def requeue_expired(self) -> int:
        """Tasks whose server stopped renewing their lease go back to the queue (a started one
        keeps its attempt; one only claimed had none charged)."""
        with self.engine.begin() as conn:
            res = conn.execute(update(tasks).where(tasks.c.status == "running",
                                                   tasks.c.lease_until < time.time())
                               .values(status="queued", owner=None, lease_until=None, started_at=None))
        return res.rowcount

    def requeue_owned(self, owner: str) -> int:
        """A graceful shutdown hands its running tasks back; the interrupted start does not count."""
        with self.engine.begin() as conn:
            res = conn.execute(update(tasks).where(tasks.c.status == "running", tasks.c.owner == owner)
                               .values(status="queued", owner=None, lease_until=None,
                                       attempts=_UNCHARGED, started_at=None))
        return res.rowcount

    def release(self, job_id: str, idx: int, owner: str, max_attempts: int, error: dict) -> str:
        """A task whose worker was lost goes back to the queue, or fails after max_attempts starts.

        Returns the task's new status ('queued' or 'failed'), or '' if the task is no longer ours.
        """
        with self.engine.begin() as conn:
            attempts = conn.execute(select(tasks.c.attempts).where(
                tasks.c.job_id == job_id, tasks.c.idx == idx, tasks.c.status == "running",
                tasks.c.owner == owner)).scalar_one_or_none()
            if attempts is None:
                return ""
            mine = (tasks.c.job_id == job_id, tasks.c.idx == idx, tasks.c.status == "running", tasks.c.owner == owner)
            if attempts < max_attempts:
                conn.execute(update(tasks).where(*mine).values(status="queued", owner=None, lease_until=None,
                                                              started_at=None, error=json.dumps(error)))
                return "queued"
            final = {**error, "detail": f"the task's worker was lost {attempts} times; not retried again "
                                        f"(last: {error.get('detail')})"}
            conn.execute(update(tasks).where(*mine).values(status="failed", finished_at=time.time(),
                                                          lease_until=None, error=json.dumps(final)))
            return "failed"

    def finish(self, job_id: str, idx: int, owner: str, status: str, result_json: Optional[str],
               error: Optional[dict]) -> bool:
        """Record a task's outcome once; False if the task is no longer ours (e.g. re-queued)."""
        return self.finish_many(owner, [(job_id, idx, status, result_json, error)]) == 1

    def finish_many(self, owner: str, outcomes: list[tuple[str, int, str, Optional[str], Optional[dict]]],
                    started: Optional[list[tuple[str, int, float]]] = None) -> int:
        """`finish` for several (job_id, idx, status, result_json, error) in one statement; how many
        were still ours. `started`: starts to charge first (`mark_started`), in the same transaction."""
        now = time.time()
        with self.engine.begin() as conn:
            self.mark_started(owner, started or [], conn)
            if not outcomes:
                return 0
            res = conn.execute(_FINISH, [
                {"b_job": job_id, "b_idx": idx, "b_owner": owner, "b_status": status, "b_at": now,
                 "b_result": result_json, "b_error": json.dumps(error) if error is not None else None}
                for job_id, idx, status, result_json, error in outcomes])
        return res.rowcount

    def task_counts(self) -> dict[str, int]:
        """Unfinished tasks of every job, by status (queued, running): for /metrics and the queue's limit."""
        with self.engine.connect() as conn:
            rows = conn.execute(select(tasks.c.status, func.count()).where(tasks.c.status.in_(("queued", "running")))
                                .group_by(tasks.c.status)).all()
        return {status: n for status, n in rows}

    def queued_of(self, client: str) -> int:
        """Queued tasks of the jobs one client created (the per-client limit of the queue)."""
        with self.engine.connect() as conn:
            return conn.execute(select(func.count()).select_from(tasks.join(jobs, tasks.c.job_id == jobs.c.id))
                                .where(tasks.c.status == "queued", jobs.c.client == client)).scalar_one()

    def queue_depth(self) -> int:
        with self.engine.connect() as conn:
            return conn.execute(select(func.count()).select_from(tasks)
                                .where(tasks.c.status == "queued")).scalar_one()

    def is_cancelled(self, job_id: str) -> bool:
        with self.engine.connect() as conn:
            return bool(conn.execute(select(jobs.c.cancelled).where(jobs.c.id == job_id)).scalar_one_or_none())


def _summaries(conn, ids: list[str]) -> dict[str, dict]:
    """Per job id: its tasks' counts by status, first start and last finish, from one grouped query."""
    summary: dict[str, dict] = {i: {"counts": {}, "started_at": None, "finished_at": None} for i in ids}
    if not ids:
        return summary
    rows = conn.execute(select(tasks.c.job_id, tasks.c.status, func.count(), func.min(tasks.c.started_at),
                               func.max(tasks.c.finished_at))
                        .where(tasks.c.job_id.in_(ids)).group_by(tasks.c.job_id, tasks.c.status)).all()
    for job_id, status, n, started, finished in rows:
        entry = summary[job_id]
        entry["counts"][status] = n
        entry["started_at"] = min(filter(None, (entry["started_at"], started)), default=None)
        entry["finished_at"] = max(filter(None, (entry["finished_at"], finished)), default=None)
    return summary


def status_of_counts(cancelled: bool, counts: dict[str, int]) -> JobStatus:
    """queued | running | succeeded | failed | cancelled, from the number of tasks in each status.

    A job whose tasks have all ended is `succeeded` if at least one task succeeded (failed tasks
    carry their errors in the results), `failed` if none did, `cancelled` if it was cancelled.
    """
    live = counts.get("queued", 0) + counts.get("running", 0)
    total = sum(counts.values())
    if cancelled and live == 0:
        return "cancelled"
    if counts.get("queued", 0) == total:
        return "queued"
    if live:
        return "running"
    return "succeeded" if counts.get("succeeded", 0) else "failed"
