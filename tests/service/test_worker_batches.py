"""Several small tasks per round trip: a worker takes a batch in one message, answers each task as it
ends, and a worker lost mid-batch costs only the task it was running (its start charged) while the
tasks queued behind it come back unstarted and uncharged."""
import json
import os
import signal
import time

from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from greyfit.service.jobs.executors import LocalWorkerPool
from greyfit.service.jobs.outcome import Outcome
from tests.service.conftest import make_settings, msd_request, slow_request, wait_for_job
from tests.systems import MSD_TRUTH


def short_request(seed: int) -> dict:
    body = msd_request(seed, n=41)
    body["method"] = "equation_error"
    return body


def poll_until(pool, keys, seconds=60):
    done, started = {}, []
    deadline = time.monotonic() + seconds
    while not keys <= done.keys() and time.monotonic() < deadline:
        done.update(pool.poll())
        started += pool.started()
        time.sleep(0.02)
    return done, started


def assert_msd_truth(outcome: Outcome, tol: float = 0.05) -> None:
    """c and k as simulated (tests.systems.MSD_TRUTH; m is fixed), within `tol` relative."""
    params = json.loads(outcome.result_json)["parameters"]
    for name in ("c", "k"):
        assert abs(params[name]["value"] / MSD_TRUTH[name] - 1) < tol, (name, params[name]["value"])


def test_a_batch_goes_to_a_worker_in_one_message_up_to_its_depth():
    pool = LocalWorkerPool(workers=1, cpu_seconds=60, wall_seconds=60)
    try:
        pool.depth = 4
        tasks = [(f"t{i}", "fit", msd_request(i)) for i in range(6)]
        left = pool.submit_batch(tasks)
        assert [key for key, _, _ in left] == ["t4", "t5"]          # no room for more than 4
        assert (pool.free(), pool.queue_room()) == (0, 0)
        done, started = poll_until(pool, {"t0", "t1", "t2", "t3"})
        assert sorted(started) == ["t0", "t1", "t2", "t3"]           # every start acknowledged
        for key in ("t0", "t1", "t2", "t3"):
            assert done[key].status == "succeeded"
            assert_msd_truth(done[key])
        assert pool.free() == 1
    finally:
        pool.shutdown()


def test_a_worker_killed_mid_batch_gives_back_only_what_it_had_not_finished():
    pool = LocalWorkerPool(workers=1, cpu_seconds=60, wall_seconds=60)
    try:
        pool.depth = 4
        slow = slow_request()
        slow["options"]["multistart"] = 30                          # tens of seconds
        pool.submit_batch([("a", "fit", short_request(0)), ("b", "fit", short_request(1)),
                           ("slow", "fit", slow), ("c", "fit", short_request(2))])
        done, started = {}, []
        deadline = time.monotonic() + 60
        while "slow" not in started and time.monotonic() < deadline:
            done.update(pool.poll())
            started += pool.started()
            time.sleep(0.02)
        assert started == ["a", "b", "slow"]
        time.sleep(0.2)
        os.kill(pool.slots[0].process.pid, signal.SIGKILL)
        more, _ = poll_until(pool, {"slow", "c"})   # a and b were reported before the kill
        done.update(more)
        assert done["a"].status == done["b"].status == "succeeded"   # finished: kept, not re-run
        assert done["slow"].status == "failed" and done["slow"].error.retry is True
        assert done["slow"].error.type == "WorkerLost"
        assert done["c"] == Outcome("not_started")                      # queued: handed back
        assert pool.free() == 1
    finally:
        pool.shutdown()


def test_a_job_of_short_tasks_survives_a_worker_killed_mid_batch(tmp_path):
    """Every task finishes once; a start is charged only where a worker acknowledged it."""
    n = 120
    with TestClient(create_app(make_settings(tmp_path, workers=2))) as c:
        job_id = c.post("/v1/jobs", json={"requests": [short_request(i) for i in range(n)]}).json()["id"]
        pool = c.app.state.dispatcher.executor
        deadline = time.monotonic() + 120
        while max(len(s.keys) for s in pool.slots) < 3 and time.monotonic() < deadline:
            time.sleep(0.002)
        assert max(len(s.keys) for s in pool.slots) >= 3, "no worker was given a batch"
        deep = max(pool.slots, key=lambda s: len(s.keys))
        os.kill(deep.process.pid, signal.SIGKILL)
        job = wait_for_job(c, job_id, timeout=180)
    assert job["progress"] == {"done": n, "total": n, "succeeded": n, "failed": 0}
    attempts = [t["attempts"] for t in job["tasks"]]
    assert set(attempts) <= {1, 2} and attempts.count(2) <= 1, attempts   # only the running task lost one
