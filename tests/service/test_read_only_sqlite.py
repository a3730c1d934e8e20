"""A SQLite file that was briefly not writable must not leave read-only connections in the pool.

SQLite opens a write-protected file read-only instead of failing; a pooled connection made then
stayed read-only for life: every POST answered 503 until a restart, while /readyz said 200. The
fault is real: the file is made immutable (`chattr +i`, which binds root too) for a moment."""
import shutil
import subprocess
import time

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import text

from greyfit.service.app import create_app
from tests.service.conftest import make_settings, msd_request, wait_for_job


def chattr(flag: str, path) -> bool:
    if shutil.which("chattr") is None:
        return False
    return subprocess.run(["chattr", flag, str(path)], capture_output=True).returncode == 0


def test_a_briefly_immutable_sqlite_file_leaves_no_read_only_connection(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=1))) as c:
        db = tmp_path / "greyfit.db"
        if not chattr("+i", db):
            pytest.skip("chattr +i is not available on this file system")
        try:
            c.app.state.store.engine.dispose()       # the pool's next connections are opened now
            for _ in range(3):
                c.get("/v1/jobs")                       # the web process and the dispatcher both connect
                assert c.get("/readyz").status_code == 503
            time.sleep(0.3)
        finally:
            chattr("-i", db)
        assert c.get("/readyz").status_code == 200
        engine = c.app.state.store.engine
        held = [engine.connect() for _ in range(4)]     # the pool's connections at once, each must write
        try:
            for conn in held:
                conn.execute(text("DELETE FROM store_probes WHERE 0"))
                conn.commit()
        finally:
            for conn in held:
                conn.close()
        ids = []
        for i in range(6):                              # each a write on whichever pooled connection
            resp = c.post("/v1/jobs", json={"requests": [msd_request(i, n=41)]})
            assert resp.status_code == 202, resp.text
            ids.append(resp.json()["id"])
        assert all(wait_for_job(c, i)["status"] == "succeeded" for i in ids)
        assert c.get("/readyz").status_code == 200
