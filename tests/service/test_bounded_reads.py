"""Reads bounded like writes: the job list carries no task bodies, tasks and results are paged, and
results are streamed from the store.

Defect: GET /v1/jobs?limit=200 over 200 jobs of 1 000 tasks answered every task of every job
(73.5 MB, server RSS +550 MB)."""
from fastapi.testclient import TestClient

from greyfit.service.app import create_app
from tests.service.conftest import make_settings, msd_request, wait_for_job


def bad_request() -> dict:
    body = msd_request(1, n=41)
    body["model"]["equations"] = {"x": "v", "v": "-k*x - c*v + no_such_symbol"}
    return body


def test_the_job_list_has_each_jobs_progress_and_no_tasks(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=1))) as c:
        mixed = c.post("/v1/jobs", json={"requests": [msd_request(0, n=41), bad_request(), msd_request(2, n=41)],
                                         "label": "mixed"}).json()["id"]
        wait_for_job(c, mixed)
        cancelled = c.post("/v1/jobs", json={"requests": [msd_request(i, n=41) for i in range(30)]}).json()["id"]
        c.delete(f"/v1/jobs/{cancelled}")
        wait_for_job(c, cancelled)
        listed = c.get("/v1/jobs", params={"limit": 200}).json()
        assert listed["count"] == 2 and [j["id"] for j in listed["data"]] == [cancelled, mixed]
        for entry in listed["data"]:
            assert "tasks" not in entry
            full = c.get(f"/v1/jobs/{entry['id']}").json()
            assert entry == {k: v for k, v in full.items() if k != "tasks"}
        by_id = {j["id"]: j for j in listed["data"]}
        assert by_id[mixed]["progress"] == {"done": 3, "total": 3, "succeeded": 2, "failed": 1}
        assert by_id[mixed]["status"] == "succeeded" and by_id[mixed]["label"] == "mixed"
        assert by_id[cancelled]["status"] == "cancelled" and by_id[cancelled]["finished_at"] is not None
        assert c.get("/v1/jobs", params={"offset": 1, "limit": 1}).json()["data"][0]["id"] == mixed


def test_tasks_and_results_are_paged_and_streamed_in_order(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=2))) as c:
        requests = [msd_request(i, n=41) for i in range(45)]
        requests[7] = bad_request()
        job_id = c.post("/v1/jobs", json={"requests": requests}).json()["id"]
        wait_for_job(c, job_id, timeout=180)
        everything = c.get(f"/v1/jobs/{job_id}/results").json()
        assert [r["index"] for r in everything["results"]] == list(range(45))   # more than one page of 20
        assert everything["results"][7]["error"]["type"] == "ModelDefinitionError"
        assert all(abs(r["result"]["parameters"]["k"]["value"] - 5.0) < 0.25
                   for r in everything["results"] if r["index"] != 7)
        paged = c.get(f"/v1/jobs/{job_id}/results", params={"offset": 5, "limit": 25}).json()
        assert paged["results"] == everything["results"][5:30] and paged["status"] == everything["status"]
        assert c.get(f"/v1/jobs/{job_id}/results", params={"offset": 45}).json()["results"] == []
        job = c.get(f"/v1/jobs/{job_id}", params={"task_offset": 40, "task_limit": 3}).json()
        assert [t["index"] for t in job["tasks"]] == [40, 41, 42] and job["progress"]["done"] == 45
        assert c.get(f"/v1/jobs/{job_id}/results", params={"limit": 0}).status_code == 422
