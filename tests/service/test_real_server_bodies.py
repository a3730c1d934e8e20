"""Against a real `greyfit serve`: a burst of large bodies does not stall the probes.

Parsing a 30 MB JSON body takes about a second of CPU with the interpreter lock held, so it cannot
run in the web process (not even in a thread: the lock stalls the event loop just the same).
/healthz is probed in open loop (one probe every 25 ms) while three 20 MB bodies arrive at once.

What is asserted is not timing (issue 22: no test asserts a wall-clock bound): every probe is
answered 200, probes are answered while the bodies are still being parsed, and every body gets its
right answer. How long the probes wait (p95 ~30 ms on a quiet machine with parser processes, about
four parses when parsing in the web process) is measured by `bench/bench_load.py --bodies`.
"""
import copy
import json
import threading
import time

import httpx
import pytest

from tests.servers import (  # noqa: F401  (re-exported for the tests that import them from here)
    free_port,
    large_fit_request,
    msd_request,
    probe_healthz,
    start_server,
    stop_server,
    wait_until_finished,
)

BODY_MEGABYTES = 20


def split_in_two(request: dict) -> dict:
    """The same data as two experiments of half the length (within the server's sample limit)."""
    exp = request["experiments"][0]
    half = len(exp["time"]) // 2
    parts = [{k: ({s: v[sl] for s, v in val.items()} if isinstance(val, dict) else val[sl]) if k in
              ("time", "inputs", "outputs") else val for k, val in exp.items()}
             for sl in (slice(0, half), slice(half, 2 * half))]
    return {**request, "experiments": parts}


@pytest.mark.slow
def test_healthz_answers_during_a_burst_of_large_bodies(tmp_path):
    fit = large_fit_request(BODY_MEGABYTES)
    n = len(fit["experiments"][0]["time"])
    accepted = split_in_two(fit)
    accepted["experiments"][1]["name"] = "second"
    accepted["experiments"][1]["outputs"]["x"].pop()     # valid JSON and schema; the worker says DataError
    bad = copy.deepcopy(fit)
    bad["experiments"][0]["outputs"]["x"][-1] = "not a number"   # found only at the very end of the parse
    bodies = {"/v1/fits": fit, "/v1/jobs": {"requests": [bad]}, "/v1/jobs ": {"requests": [accepted]}}
    bodies = {path: json.dumps(body).encode() for path, body in bodies.items()}   # ~20 MB each
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(tmp_path, port, workers=1, GREYFIT_MAX_SAMPLES_PER_EXPERIMENT=str(n - 1))
    try:
        answers: dict[str, httpx.Response] = {}
        answered_at: dict[str, float] = {}
        stop = threading.Event()
        probes: list[tuple[float, int]] = []
        prober = threading.Thread(target=lambda: probe_healthz(base, stop, answers=probes))
        prober.start()

        def post(path: str, content: bytes) -> None:
            try:
                answers[path] = httpx.post(base + path.strip(), content=content, timeout=120,
                                           headers={"content-type": "application/json"})
            except httpx.HTTPError as exc:
                answers[path] = exc
            answered_at[path] = time.perf_counter()

        posts = [threading.Thread(target=post, args=item) for item in bodies.items()]
        time.sleep(0.2)
        sent = time.perf_counter()
        for t in posts:
            t.start()
        for t in posts:
            t.join()
        stop.set()
        prober.join()

        # /healthz answered throughout: every probe 200, and some answered while the bodies were parsed
        assert probes and all(status == 200 for _, status in probes), sorted({s for _, s in probes})
        assert any(sent < at < min(answered_at.values()) for at, _ in probes), \
            "no /healthz answer came while the large bodies were being parsed"
        statuses = {path: getattr(a, "status_code", repr(a)) for path, a in answers.items()}
        assert statuses == {"/v1/fits": 422, "/v1/jobs": 422, "/v1/jobs ": 202}, \
            {p: getattr(a, "text", "")[:300] for p, a in answers.items()}
        # field naming intact: this server's sample limit, and pydantic's error at its place
        assert [e["loc"] for e in answers["/v1/fits"].json()["errors"]] == ["experiments[0].time"]
        assert [e["loc"] for e in answers["/v1/jobs"].json()["errors"]] == \
            [f"requests[0].experiments[0].outputs.x[{n - 1}]"]

        job = wait_until_finished(base, answers["/v1/jobs "].json()["id"], timeout=60)
        assert job["status"] == "failed"
        assert job["tasks"][0]["error"]["type"] == "DataError"
        assert job["tasks"][0]["error"]["field"] == "experiments[1].outputs.x"
        assert httpx.post(f"{base}/v1/fits", json=msd_request(0), timeout=60).status_code == 200
    finally:
        stop_server(server)
