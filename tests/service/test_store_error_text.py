"""A job store error tells a caller without the API key which component failed, not the database's
own text: that names the SQLite file's path, or the PostgreSQL host and port ('connection to server
at "127.0.0.1", port 5432'). The same rule as /readyz; a caller with the key gets the whole text.

Defect: every /v1/* route answered the database's text to anyone (problems.store_error_detail)."""
import uuid

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine
from sqlalchemy.engine import make_url

from greyfit.service.http.app import create_app
from tests.service.conftest import make_settings, msd_request

KEY = "s3cret-key"


def _break_store(app, store_url: str, tmp_path) -> tuple[list[str], list[tuple[str, str]]]:
    """Make the store fail as it does in service; (what must not be shown, the requests that meet it)."""
    store = app.state.store
    post = ("POST", "/v1/jobs")
    if store_url.startswith("sqlite"):   # the file deleted or replaced under the server: StoreUnavailable
        (tmp_path / "greyfit.db").rename(tmp_path / "moved.db")
        return [str(tmp_path)], [post]
    # PostgreSQL answering, but without the database: psycopg's OperationalError names host and port
    url = make_url(store_url)
    store.engine = create_engine(url.set(database=f"missing_{uuid.uuid4().hex[:8]}"))
    return [url.host or "127.0.0.1", f"port {url.port or 5432}"], [
        post, ("GET", "/v1/jobs"), ("GET", f"/v1/jobs/{uuid.uuid4()}"), ("GET", f"/v1/jobs/{uuid.uuid4()}/results")]


@pytest.mark.parametrize("keyed", [False, True], ids=["no API key", "API key"])
def test_a_store_error_shows_no_path_host_or_port_without_the_api_key(store_url, tmp_path, keyed):
    settings = make_settings(tmp_path, database_url=store_url, workers=1, api_key=KEY if keyed else None)
    app = create_app(settings)
    with TestClient(app, raise_server_exceptions=False) as c:
        engine = app.state.store.engine
        secrets, requests = _break_store(app, store_url, tmp_path)
        try:
            auth = {"Authorization": f"Bearer {KEY}"} if keyed else {}
            for method, path in requests:
                body = {"requests": [msd_request(0, n=41)]} if method == "POST" else None
                resp = c.request(method, path, json=body, headers=auth)
                assert resp.status_code == 503 and int(resp.headers["retry-after"]) >= 1, (path, resp.text)
                detail = resp.json()["detail"]
                assert "job store" in detail, detail
                shown = [s for s in secrets if s in resp.text]
                if keyed:                  # the operator, with the key, reads what the database said
                    assert shown == secrets, (path, detail)
                else:
                    assert shown == [], (path, detail)
        finally:
            app.state.store.engine = engine   # the shutdown hands its tasks back through the store
            if (tmp_path / "moved.db").exists():
                (tmp_path / "moved.db").rename(tmp_path / "greyfit.db")
