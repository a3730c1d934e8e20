"""The process boundary: a worker's error comes back as the answer its class in the FitError tree
gets, including a subclass the server's mapping has never heard of."""
import pickle

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from greyfit.service.http.problems import install_handlers
from greyfit.service.http.runner import outcome_or_raise
from greyfit.service.jobs import tasks
from greyfit.service.jobs.outcome import Outcome
from greyfit.solvers.errors import DataError, FitError


class NotIdentifiable(FitError):
    """A FitError subclass defined after the service's code: no table names it."""


class StepTooCoarse(DataError):
    """A DataError subclass with a constructor of its own (as DataFileError has)."""

    def __init__(self, step: float):
        super().__init__(f"the sampling step {step:g} s is coarser than the fastest mode", "experiments[0].time")


def worker_outcome(monkeypatch, exc: Exception) -> Outcome:
    """What a worker whose task raised `exc` sends back, through the pickling its pipe does."""
    def raising(request, cpu_seconds):
        raise exc

    monkeypatch.setattr(tasks, "_runners", lambda: {"fit": raising})
    return pickle.loads(pickle.dumps(tasks.run_task("fit", {}, 10.0)))


def answer(outcome: Outcome):
    app = FastAPI()
    install_handlers(app)

    @app.get("/fit")
    def fit():
        return outcome_or_raise(outcome)

    with TestClient(app, raise_server_exceptions=False) as c:
        return c.get("/fit")


def test_a_new_fit_error_subclass_from_a_worker_is_a_422_with_its_message(monkeypatch):
    outcome = worker_outcome(monkeypatch, NotIdentifiable("k and m enter only as k/m", "parameters"))
    assert outcome.status == "failed" and outcome.error.type == "NotIdentifiable"
    assert outcome.error.as_dict() == {"type": "NotIdentifiable", "field": "parameters",
                                       "detail": "k and m enter only as k/m"}
    resp = answer(outcome)
    assert resp.status_code == 422
    body = resp.json()
    assert body["type"].endswith("/fit-error") and body["detail"] == "parameters: k and m enter only as k/m"
    assert body["errors"] == [{"loc": "parameters", "msg": "k and m enter only as k/m"}]


def test_a_new_data_error_subclass_is_answered_as_invalid_data(monkeypatch):
    outcome = worker_outcome(monkeypatch, StepTooCoarse(0.5))
    resp = answer(outcome)
    assert resp.status_code == 422
    body = resp.json()
    assert body["type"].endswith("/data-error") and body["title"] == "Invalid data"
    assert body["errors"] == [{"loc": "experiments[0].time",
                               "msg": "the sampling step 0.5 s is coarser than the fastest mode"}]


@pytest.mark.parametrize("exc, status", [(KeyError("x"), 500), (ImportError("no matplotlib"), 501)])
def test_other_worker_errors_keep_their_answers(monkeypatch, exc, status):
    assert answer(worker_outcome(monkeypatch, exc)).status_code == status
