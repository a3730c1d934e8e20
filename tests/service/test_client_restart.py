"""greyfit.Client (httpx) against a `greyfit serve` that is killed and started again mid-batch:
every fit returns, with the truth's numbers, and no job is stored twice; then the async client on
the restarted server.

The server is killed with SIGKILL (its whole process group: web process and workers), as a crash
or an OOM kill would, while synchronous fits are in flight and jobs are being created; a new server
starts on the same port and data directory. The client meets refused connections (nothing listens),
connections closed without an answer (the fits in flight) and, for a job whose creation was stored
but not answered, the same Idempotency-Key again.
"""
import asyncio
import os
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from pydantic import ValidationError

from greyfit.client import AsyncClient, Client, InvalidRequest, ServiceUnreachable
from tests.servers import free_port, msd_request, slow_request, start_server, stop_server

TRUTH = {"c": 0.8, "k": 5.0}   # tests.systems.simulate_msd


def _fit_and_time(client: Client, body: dict) -> tuple:
    result = client.fit(body)
    return result, time.monotonic()


def _submit_jobs(client: Client, labels: list[str], every: float, out: dict) -> None:
    for label in labels:
        out[label] = client.submit_job([msd_request(len(out) + 40)], label=label).id
        time.sleep(every)


@pytest.mark.slow
def test_a_batch_survives_a_server_restart(tmp_path):
    port = free_port()
    data = tmp_path / "data"
    server = start_server(data, port, workers=1)
    client = Client(f"http://127.0.0.1:{port}", timeout=120, max_retries=40, max_retry_wait=120)
    labels, created = [f"restart {i}" for i in range(8)], {}
    try:
        with ThreadPoolExecutor(5) as pool:
            fits = [pool.submit(_fit_and_time, client, slow_request()) for _ in range(4)]
            submitter = threading.Thread(target=_submit_jobs, args=(client, labels, 0.3, created))
            submitter.start()
            while not any(f.done() for f in fits):   # the batch is under way: one answer is in
                time.sleep(0.02)
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
            restarted = time.monotonic()
            server = start_server(data, port, workers=1)
            answers = [f.result() for f in fits]
            submitter.join()
        for result, _ in answers:
            assert result.success
            for name, truth in TRUTH.items():
                assert abs(result.parameters[name].value - truth) < 5 * result.parameters[name].stderr
        assert sum(done > restarted for _, done in answers) >= 1   # in flight at the kill, sent again
        assert sorted(created) == sorted(labels)
        for job_id in created.values():
            assert client.wait(job_id, timeout=120).status == "succeeded"
        stored = [j for j in client.list_jobs(limit=100).data if j.label in created]
        assert sorted(j.label for j in stored) == sorted(labels)             # each job once
        assert {j.label: j.id for j in stored} == created
        _the_async_client_fits_and_creates_a_job_once(f"http://127.0.0.1:{port}")
    finally:
        client.close()
        stop_server(server)


def test_a_server_that_is_not_there_is_said_so_after_the_retries():
    port = free_port()   # nothing listens
    client = Client(f"http://127.0.0.1:{port}", max_retries=2, max_retry_wait=5)
    with pytest.raises(ServiceUnreachable) as info:
        client.job("x")
    assert f"127.0.0.1:{port}/v1/jobs/x" in str(info.value) and "2 retries" in str(info.value)
    assert [what for what, _ in client.last_retries] == ["ConnectError", "ConnectError"]
    assert all(0.1 <= wait <= 0.5 for _, wait in client.last_retries)   # 0.25 s, then 0.5 s, jittered


def test_an_invalid_dict_is_refused_with_the_services_words():
    """Before anything is sent (no server here): the loc/msg the service's 422 and the CLI give."""
    from greyfit.schemas import FitRequest
    from greyfit.service.http.error_text import error_lines
    from greyfit.service.http.json_parsing import validate_strict
    body = msd_request(1)
    body["metod"] = "multiple_shooting"
    body["experiments"][0]["time"][3] = "0.3"
    with pytest.raises(InvalidRequest) as info:
        Client("http://127.0.0.1:9").fit(body)
    err = info.value
    assert err.status == 422
    assert {e["loc"] for e in err.errors} == {"metod", "experiments[0].time[3]"}
    assert "did you mean 'method'?" in str(err) and "pydantic" not in str(err)
    with pytest.raises(ValidationError) as cli:   # the CLI's text is the same lines
        validate_strict(FitRequest, body)
    assert error_lines(cli.value).splitlines() == [f"{e['loc']}: {e['msg']}" for e in err.errors]


def _the_async_client_fits_and_creates_a_job_once(base: str) -> None:
    async def run():
        async with AsyncClient(base, timeout=120) as client:
            fits = await asyncio.gather(*(client.fit(msd_request(50 + i)) for i in range(2)))
            first = await client.submit_job([msd_request(52)], label="async", idempotency_key="k-async")
            again = await client.submit_job([msd_request(52)], label="async", idempotency_key="k-async")
            done = await client.wait(first.id, timeout=120)
            return fits, first, again, done, await client.results(first.id)

    fits, first, again, done, outcomes = asyncio.run(run())
    for fit in fits:
        assert fit.success and abs(fit.parameters["k"].value - TRUTH["k"]) < 5 * fit.parameters["k"].stderr
    assert again.id == first.id and done.status == "succeeded"
    assert abs(outcomes.results[0].result.parameters["c"].value - TRUTH["c"]) < 0.05
