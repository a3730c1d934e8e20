"""Scale-out: the same job API on a Dask distributed LocalCluster (loopback)."""
import pytest
from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from tests.service.conftest import make_settings, msd_request, wait_for_job

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as c:
        yield c


@pytest.mark.slow
def test_jobs_and_sync_fits_run_on_the_dask_cluster(tmp_path, cluster):
    settings = make_settings(tmp_path, executor="dask", dask_scheduler=cluster.scheduler_address)
    with TestClient(create_app(settings)) as c:
        assert c.get("/readyz").json() == {"status": "ready", "executor": "dask"}
        requests = [msd_request(i) for i in range(6)]
        requests[2]["model"]["equations"]["v"] = "(u - c*v - kk*x)/m"
        job = wait_for_job(c, c.post("/v1/jobs", json={"requests": requests}).json()["id"])
        assert job["status"] == "succeeded"
        results = c.get(f"/v1/jobs/{job['id']}/results").json()["results"]
        assert [r["status"] for r in results] == ["succeeded"] * 2 + ["failed"] + ["succeeded"] * 3
        assert results[2]["error"]["type"] == "ModelDefinitionError"
        for r in results[:2] + results[3:]:
            assert abs(r["result"]["parameters"]["k"]["value"] / 5.0 - 1) < 0.02
        resp = c.post("/v1/fits", json=msd_request(9))
        assert resp.status_code == 200 and resp.json()["success"]
    # the fits ran on the cluster's workers, not in this process
    info = distributed.Client(cluster.scheduler_address, set_as_default=False)
    try:
        logs = info.run(lambda: __import__("sys").modules.get("greyfit.solvers.fit") is not None)
        assert any(logs.values()), "no Dask worker imported the fit engine"
    finally:
        info.close()


@pytest.mark.slow
def test_readiness_says_when_the_dask_cluster_has_no_workers(tmp_path):
    """Defect: /readyz said 200 with no Dask worker, while every task waited for one."""
    import time

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as small:
        settings = make_settings(tmp_path, executor="dask", dask_scheduler=small.scheduler_address)
        with TestClient(create_app(settings)) as c:
            assert c.get("/readyz").status_code == 200
            small.scale(0)
            deadline, resp = time.monotonic() + 30, None
            while time.monotonic() < deadline:
                resp = c.get("/readyz")
                if resp.status_code == 503:
                    break
                time.sleep(0.2)
            assert resp.status_code == 503 and "no workers" in resp.json()["detail"]
            assert resp.headers["retry-after"]
            fit = c.post("/v1/fits", json=msd_request(0, n=41))   # at once, not after the wall-time limit
            assert fit.status_code == 503 and "no workers" in fit.json()["detail"] and fit.headers["retry-after"]
            small.scale(1)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and c.get("/readyz").status_code != 200:
                time.sleep(0.2)
            assert c.get("/readyz").status_code == 200
            job = wait_for_job(c, c.post("/v1/jobs", json={"requests": [msd_request(0, n=41)]}).json()["id"])
            assert job["status"] == "succeeded"
