"""Reads bounded like writes: the job list carries no task bodies, tasks and results are paged, and
results are streamed from the store.

Defect: GET /v1/jobs?limit=200 over 200 jobs of 1 000 tasks answered every task of every job
(73.5 MB, server RSS +550 MB)."""
from fastapi.testclient import TestClient
from sqlalchemy import event

from greyfit.service.http.app import create_app
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


def test_a_page_of_tasks_is_read_from_the_store_not_cut_from_all_of_them(tmp_path):
    """Defect: the job route loaded every task of the job, then cut the page in Python; the results
    route loaded them all for the job's status. Reads: the page's task rows, counts for the rest."""
    with TestClient(create_app(make_settings(tmp_path, workers=1))) as c:
        store = c.app.state.store
        assert c.app.state.dispatcher._lock.acquire(timeout=30)   # the tasks stay queued meanwhile
        try:
            job_id = store.create_job("fit", [{"i": i} for i in range(60)], "sixty")
            whole = c.get(f"/v1/jobs/{job_id}").json()
            task_reads = []

            def remember(_conn, _cursor, statement, parameters, _context, _many):
                if "tasks.attempts, tasks.started_at, tasks.finished_at" in statement:   # rows of tasks
                    task_reads.append((statement, parameters))

            event.listen(store.engine, "before_cursor_execute", remember)
            try:
                page = c.get(f"/v1/jobs/{job_id}", params={"task_offset": 50, "task_limit": 4}).json()
                results = c.get(f"/v1/jobs/{job_id}/results", params={"offset": 58}).json()
            finally:
                event.remove(store.engine, "before_cursor_execute", remember)
        finally:
            c.app.state.dispatcher._lock.release()
        assert [t["index"] for t in page["tasks"]] == [50, 51, 52, 53]
        assert page["tasks"] == whole["tasks"][50:54]
        assert {k: v for k, v in page.items() if k != "tasks"} == {k: v for k, v in whole.items() if k != "tasks"}
        assert page["status"] == results["status"] == "queued" and page["progress"]["total"] == 60
        assert [r["index"] for r in results["results"]] == [58, 59]
        assert len(task_reads) == 1 and "LIMIT" in task_reads[0][0], task_reads   # one page, in SQL
