"""A SQLite file that was briefly not writable must not leave read-only connections in the pool.

SQLite opens a file it cannot write read-only instead of failing, and a pooled connection made then
stayed read-only for life: every POST answered 503 until a restart, while /readyz said 200 (its
probe ran on a healthy connection).

The window is made two ways: the file made immutable (`chattr +i`, which binds root too; skipped
where the file system or the container does not allow it), and new connections opened read-only
(`mode=ro`), which is what SQLite does by itself with such a file and runs anywhere. While the
window lasts the dispatcher waits between its rounds, so the pool is the test's alone: it is filled
with connections made in the window, and after it every one of them would be handed to a writer.
"""
import contextlib
import shutil
import sqlite3
import subprocess

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, text
from sqlalchemy.exc import OperationalError

from greyfit.service.http.app import create_app
from tests.service.conftest import make_settings, msd_request, wait_for_job


def chattr(flag: str, path) -> bool:
    if shutil.which("chattr") is None:
        return False
    return subprocess.run(["chattr", flag, str(path)], capture_output=True).returncode == 0


@contextlib.contextmanager
def immutable(_engine, db):
    if not chattr("+i", db):
        pytest.skip("chattr +i is not available here (file system, or no CAP_LINUX_IMMUTABLE)")
    try:
        yield
    finally:
        chattr("-i", db)


@contextlib.contextmanager
def opened_read_only(engine, db):
    def connect(_dialect, _record, _cargs, _cparams):
        return sqlite3.connect(f"file:{db}?mode=ro", uri=True, check_same_thread=False, timeout=30)

    event.listen(engine, "do_connect", connect)
    try:
        yield
    finally:
        event.remove(engine, "do_connect", connect)


@pytest.mark.parametrize("window", [immutable, opened_read_only], ids=["chattr+i", "mode=ro"])
def test_a_connection_opened_while_the_file_was_not_writable_never_serves_a_writer(tmp_path, window):
    with TestClient(create_app(make_settings(tmp_path, workers=1)), raise_server_exceptions=False) as c:
        engine = c.app.state.store.engine
        dispatcher = c.app.state.dispatcher
        size = engine.pool.size()
        job = {"requests": [msd_request(0, n=41)]}
        assert dispatcher._lock.acquire(timeout=30)     # between two rounds: it holds no connection
        ids = []
        try:
            with window(engine, tmp_path / "greyfit.db"):
                engine.dispose()                        # every connection from here on is made in the window
                made = []
                for _ in range(size):                   # at once, so the pool keeps each of them
                    with contextlib.suppress(OperationalError):   # refused: it cannot write
                        made.append(engine.connect())
                for conn in made:
                    conn.close()
                assert c.get("/readyz").status_code == 503
                assert c.post("/v1/jobs", json=job).status_code == 503
            # the window is over: readiness and every writer, on whichever pooled connection
            for i in range(2 * size):
                ready = c.get("/readyz")
                assert ready.status_code == 200, ready.text
                resp = c.post("/v1/jobs", json={"requests": [msd_request(i, n=41)]})
                assert resp.status_code == 202, resp.text
                ids.append(resp.json()["id"])
            held = [engine.connect() for _ in range(size)]   # the pool's connections at once: each writes
            try:
                for conn in held:
                    conn.execute(text("DELETE FROM store_probes WHERE 0"))
                    conn.commit()
            finally:
                for conn in held:
                    conn.close()
        finally:
            dispatcher._lock.release()
        assert all(wait_for_job(c, i)["status"] == "succeeded" for i in ids)   # the dispatcher's writes too
        assert c.get("/readyz").status_code == 200
