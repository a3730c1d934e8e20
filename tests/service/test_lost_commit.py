"""A claim whose COMMIT the database carried out but whose answer never reached the server.

A TCP proxy between greyfit and PostgreSQL drops the answer to the COMMIT of a claim (and the
connection with it): the database has the tasks marked running for this server, while its
dispatcher never learned of them. Before, renewing every lease it owned kept them running, unrun,
for ever (a job stayed at 19/20 for minutes). Now the dispatcher renews only what it holds and
gives the rest back, and the job finishes."""
import socket
import threading

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.engine import make_url

from greyfit.service.http.app import create_app
from tests.service.conftest import make_settings, msd_request, wait_for_job


class CommitAnswerDropper:
    """Forwards 127.0.0.1:<port> to the database; once armed, the answer to the next COMMIT sent after
    a claim's UPDATE (tasks found and marked running) on the same connection is dropped and that
    connection closed."""

    # the statement that arms the drop: a claim's UPDATE (tasks found and marked running)
    trigger: tuple[bytes, ...] = (b"UPDATE tasks SET status", b"started_at")

    def __init__(self, host: str, port: int):
        self.target = (host, port)
        self.armed = threading.Event()
        self.dropped = 0
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.target)
            state = {"claim": False, "commit": False}
            threading.Thread(target=self._pump, args=(client, server, state, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(server, client, state, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, state: dict, upstream: bool) -> None:
        try:
            while data := src.recv(65536):
                if upstream and self.armed.is_set():
                    state["claim"] = state["claim"] or all(part in data for part in self.trigger)
                    state["commit"] = state["claim"] and b"COMMIT" in data
                if not upstream and state["commit"]:   # the database committed; its answer is lost
                    self.armed.clear()
                    self.dropped += 1
                    break
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def close(self) -> None:
        self.listener.close()


@pytest.fixture
def dropper(postgres_url):
    url = make_url(postgres_url)
    proxy = CommitAnswerDropper(url.host or "127.0.0.1", url.port or 5432)
    yield proxy, url.set(host="127.0.0.1", port=proxy.port).render_as_string(hide_password=False)
    proxy.close()


def test_a_claim_whose_commit_answer_is_lost_is_given_back_and_run(dropper, tmp_path):
    proxy, url = dropper
    settings = make_settings(tmp_path, database_url=url, workers=1, lease_seconds=2.0)
    with TestClient(create_app(settings)) as client:
        proxy.armed.set()
        job = client.post("/v1/jobs", json={"requests": [msd_request(s) for s in range(3)]}).json()
        done = wait_for_job(client, job["id"], timeout=60)
    assert proxy.dropped == 1                          # the lost answer did happen
    assert done["status"] == "succeeded", done
    assert [t["status"] for t in done["tasks"]] == ["succeeded"] * 3
    assert all(t["attempts"] == 1 for t in done["tasks"])   # the lost claim was not counted as a start


class CreateAnswerDropper(CommitAnswerDropper):
    """Drops the answer to the COMMIT of a job's creation (after `INSERT INTO jobs`) instead."""

    trigger = (b"INSERT INTO jobs",)


def test_a_job_created_whose_answer_was_lost_is_the_same_job_on_retry_with_its_key(postgres_url, tmp_path):
    """The POST that lost its answer says 503 retry; the retry with the same Idempotency-Key and body
    returns the job the database did create, and only that one exists."""
    url = make_url(postgres_url)
    proxy = CreateAnswerDropper(url.host or "127.0.0.1", url.port or 5432)
    try:
        settings = make_settings(tmp_path, database_url=url.set(host="127.0.0.1", port=proxy.port)
                                 .render_as_string(hide_password=False), workers=1)
        body = {"requests": [msd_request(s) for s in range(2)], "label": "once"}
        headers = {"Idempotency-Key": "create-7f3a"}
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            proxy.armed.set()
            first = client.post("/v1/jobs", json=body, headers=headers)
            assert proxy.dropped == 1 and first.status_code == 503, first.text
            again = client.post("/v1/jobs", json=body, headers=headers)
            assert again.status_code == 202, again.text
            done = wait_for_job(client, again.json()["id"], timeout=60)
            assert done["status"] == "succeeded"
            listed = client.get("/v1/jobs").json()
            assert listed["count"] == 1 and listed["data"][0]["id"] == done["id"]
            other = client.post("/v1/jobs", json={**body, "label": "other"}, headers=headers)
            assert other.status_code == 422 and "Idempotency-Key" in other.text
    finally:
        proxy.close()


def test_the_same_key_and_body_give_one_job(client):
    body = {"requests": [msd_request(0)]}
    a = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k-1"}).json()
    b = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k-1"}).json()
    c = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k-2"}).json()
    assert a["id"] == b["id"] != c["id"]
    bad = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "has space"})
    assert bad.status_code == 400 and "Idempotency-Key" in bad.text


def test_a_key_sent_again_with_the_label_none_is_another_body(client):
    """Defect: the fingerprint joined the kind and the label as text, so no label and the label
    "None" were the same body: the second POST got 202 with the first job instead of 422."""
    body = {"requests": [msd_request(0)]}
    first = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "label-none"})
    assert first.status_code == 202 and first.json()["label"] is None
    other = client.post("/v1/jobs", json={**body, "label": "None"}, headers={"Idempotency-Key": "label-none"})
    assert other.status_code == 422 and "Idempotency-Key" in other.text, other.text
    again = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "label-none"})
    assert again.status_code == 202 and again.json()["id"] == first.json()["id"]
