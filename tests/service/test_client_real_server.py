"""greyfit.client.Client against a real `greyfit serve` process: fit, discover, simulate, a job, a report."""
import numpy as np
import pytest

from greyfit.client import Client, GreyfitError
from greyfit.schemas import FitResult
from greyfit.schemas.simulate import SimulateResult
from tests.service.conftest import msd_request
from tests.service.test_discover_api import duffing_body
from tests.service.test_real_server import free_port, start_server, stop_server


@pytest.mark.slow
def test_client_round_trips_against_a_real_server(tmp_path):
    port = free_port()
    server = start_server(tmp_path, port)
    try:
        client = Client(f"http://127.0.0.1:{port}")
        body = msd_request(4)
        fit = client.fit(body)
        assert isinstance(fit, FitResult) and fit.success
        assert abs(fit.parameters["c"].value - 0.8) < 4 * fit.parameters["c"].stderr

        found = client.discover(duffing_body())
        assert found.steps[0].effect == "cubic_stiffness"
        page = client.report(found, duffing_body())     # before/after overlay with the added term
        assert 'id="fig-discovery_overlay"' in page and 'id="fig-discovery_metrics"' in page

        sim = client.simulate({"model": body["model"], "fit_result": fit.model_dump(mode="json"),
                               "experiments": body["experiments"]})
        assert isinstance(sim, SimulateResult)
        assert abs(sim.validation.rmse["x"] - fit.metrics.rmse["x"]) < 1e-9 * fit.metrics.rmse["x"]

        job = client.submit_job([msd_request(5), msd_request(6)], label="client")
        assert job.status in ("queued", "running", "succeeded")
        done = client.wait(job.id, timeout=120)
        assert done.status == "succeeded" and done.progress.succeeded == 2
        results = client.results(job.id).results
        estimates = [FitResult.model_validate(r.result).parameters["k"].value for r in results]
        assert np.allclose(estimates, 5.0, rtol=0.01)
        page = client.job_report(job.id, index=1)
        assert page.startswith("<!DOCTYPE html>") and 'id="fig-compare_estimation"' in page

        bad = msd_request(7)
        bad["model"]["equations"]["v"] = "(u - c*v - kk*x)/m"
        with pytest.raises(GreyfitError) as info:
            client.fit(bad)
        assert info.value.status == 422 and "equations.v" in str(info.value)
    finally:
        stop_server(server)
