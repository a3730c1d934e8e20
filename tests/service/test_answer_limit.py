"""An answer past GREYFIT_MAX_ANSWER_BYTES is refused with the way to page it, and the hint works."""
import re
import time

from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from tests.service.conftest import assert_problem, make_settings, msd_request

LIMIT = 2048


def test_a_job_status_past_the_answer_limit_names_the_paging_that_fits(tmp_path):
    settings = make_settings(tmp_path, workers=1, max_answer_bytes=LIMIT)
    with TestClient(create_app(settings)) as c:
        n = 40
        requests = [msd_request(i, n=21) for i in range(n)]
        for r in requests:   # each fails at once in its worker (an unknown symbol), with an error to report
            r["model"]["equations"]["v"] = "(u - c*v - kk*x)/m"
        job_id = c.post("/v1/jobs", json={"requests": requests}).json()["id"]
        assert wait_for_job_paged(c, job_id, task_limit=1) == "failed"

        resp = c.get(f"/v1/jobs/{job_id}")
        assert_problem(resp, 422, "task_offset", "task_limit", "GREYFIT_MAX_ANSWER_BYTES", f"/v1/jobs/{job_id}/results")
        assert [e["loc"] for e in resp.json()["errors"]] == ["task_limit"]
        fits = int(re.search(r"task_limit=(\d+)", resp.json()["detail"]).group(1))
        assert 1 <= fits < n

        # following the hint pages the whole job, each page within the limit
        seen = []
        for offset in range(0, n, fits):
            page = c.get(f"/v1/jobs/{job_id}", params={"task_offset": offset, "task_limit": fits})
            assert page.status_code == 200, page.text
            assert len(page.content) <= LIMIT
            seen += [t["index"] for t in page.json()["tasks"]]
        assert seen == list(range(n))

        # results are streamed a page at a time: not limited
        results = c.get(f"/v1/jobs/{job_id}/results")
        assert results.status_code == 200 and len(results.content) > LIMIT
        assert [r["error"]["type"] for r in results.json()["results"]] == ["ModelDefinitionError"] * n


def wait_for_job_paged(c, job_id: str, task_limit: int, timeout: float = 180) -> str:
    """The job's status once it ended, read from a page of its tasks (the whole status is refused)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = c.get(f"/v1/jobs/{job_id}", params={"task_limit": task_limit}).json()["status"]
        if status in ("succeeded", "failed", "cancelled"):
            return status
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not finish in {timeout} s")
