"""Example request bodies and answers for the OpenAPI description: real requests that work as sent.

FastAPI would generate an example from the schema alone (a state named "X1upTr6t…"), which "Try it
out" cannot send. These come from the repository's examples (copies shipped in
service/http/static/examples; tests/service/test_offline_docs.py keeps them equal), so each UI offers a
request that validates and converges. Each task kind names its example on its entry in
service/task_kinds.py; the builders are here. The answers' examples are real too: the result of the
example fit (service/http/static/examples/msd_result.json, kept equal to a fresh fit by
tests/service/test_openapi_descriptions.py), a job of it, the probes' answers and a 422.
"""
from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from greyfit.service.task_kinds import KINDS, Example

EXAMPLES_DIR = Path(__file__).resolve().parent / "static" / "examples"


@lru_cache(maxsize=None)
def example_request(filename: str) -> dict:
    """A request shipped in service/http/static/examples (a copy of examples/<filename> or its source)."""
    return json.loads((EXAMPLES_DIR / filename).read_text(encoding="utf-8"))


def msd_fit() -> dict:
    """The mass-spring-damper fit of examples/msd_request.json."""
    return example_request("msd_request.json")


def msd_simulation() -> dict:
    """The same model and record, simulated with the values the data were made with."""
    msd = msd_fit()
    return {"model": msd["model"], "parameters": {"c": 0.8, "k": 5.0}, "experiments": msd["experiments"],
            "options": msd.get("options", {})}


def msd_design() -> dict:
    """A D-optimal input for the mass-spring-damper's c and k, beside the one step that was run."""
    msd = msd_fit()
    time = [round(0.1 * i, 10) for i in range(101)]
    return {"model": msd["model"], "parameters": {"c": 0.8, "k": 5.0},
            "inputs": {"u": {"lower": -1.0, "upper": 1.0}}, "outputs": {"x": 0.01},
            "duration": 10.0, "sample_time": 0.1, "hold": 0.5,
            "initial_state": {"x": 0.0, "v": 0.0},
            "baseline": {"name": "step", "time": time, "inputs": {"u": [1.0] * len(time)}},
            "options": {"starts": 1, "max_iterations": 50}}


def msd_job() -> dict:
    """The mass-spring-damper fit as a batch job of one request."""
    return {"requests": [msd_fit()], "label": "demo"}


def msd_discover() -> dict:
    """The mass-spring-damper fit with a search for one missing effect."""
    return {**msd_fit(), "discovery": {"max_terms": 1}}


def frequency_pi_loop() -> dict:
    """The PI-loop frequency-response fit of examples/frequency_pi_loop_request.json."""
    return example_request("frequency_pi_loop_request.json")


def examples() -> dict[str, Example]:
    """Path of a POST operation -> its example body: the task kinds' (service/task_kinds.py)."""
    out = {}
    for kind in KINDS.values():
        for path, example in ((kind.sync_path, kind.example), (kind.jobs_path, kind.job_example)):
            if path is not None and example is not None:
                out[path] = example
    return out


def add_examples(spec: dict) -> None:
    """Give each request body with an example its example (media-type `examples`, shown by both UIs)."""
    components = spec.setdefault("components", {}).setdefault("examples", {})
    for path, example in examples().items():
        body = spec["paths"].get(path, {}).get("post", {}).get("requestBody")
        if body is None:
            continue
        components[example.name] = {"summary": example.summary, "value": example.build()}
        ref = {"$ref": f"#/components/examples/{example.name}"}
        body["content"]["application/json"]["examples"] = {example.name: ref}


JOB_ID = "5f0c2a4e-8d1b-4c6f-9a57-0e3b7d21c9aa"
WHEN = ("2026-12-07T15:50:37.592000Z", "2026-12-07T15:50:37.640000Z", "2026-12-07T15:50:38.012000Z")


def msd_result() -> dict:
    """The FitResult of the example fit (`greyfit fit examples/msd_request.json`)."""
    return example_request("msd_result.json")


def msd_job_record(finished: bool = True) -> dict:
    """The example job (one fit) as GET /v1/jobs/{id} answers it, finished or just created."""
    done = 1 if finished else 0
    task = {"index": 0, "status": "succeeded" if finished else "queued", "attempts": done,
            "started_at": WHEN[1] if finished else None, "finished_at": WHEN[2] if finished else None,
            "error": None}
    return {"id": JOB_ID, "kind": "fit", "label": "demo", "status": task["status"],
            "progress": {"done": done, "total": 1, "succeeded": done, "failed": 0},
            "created_at": WHEN[0], "started_at": task["started_at"], "finished_at": task["finished_at"],
            "tasks": [task]}


def invalid_request() -> dict:
    """A 422: a misspelt field and a string where a number belongs."""
    errors = [{"loc": "metod", "msg": "unknown field 'metod': did you mean 'method'?"},
              {"loc": "experiments[0].time[3]",
               "msg": "Input should be a valid number: a JSON number is expected, not a string or true/false "
                      "(write 500, not \"500\")"}]
    return {"type": "https://greyfit.dev/problems/validation-error", "title": "Invalid request", "status": 422,
            "detail": "; ".join(f"{e['loc']}: {e['msg']}" for e in errors), "request_id": "3c1f7d0e9b2a4e61",
            "errors": errors}


def answer_examples() -> dict[tuple[str, str, str], dict]:
    """(method, path, status) -> an example answer body."""
    job = msd_job_record()
    summary = {k: v for k, v in job.items() if k != "tasks"}
    out: dict[tuple[str, str, str], dict] = {("get", "/healthz", "200"): {"status": "ok"},
           ("get", "/readyz", "200"): {"status": "ready", "executor": "local"},
           ("get", "/v1/jobs", "200"): {"data": [summary], "count": 1},
           ("get", "/v1/jobs/{job_id}", "200"): job,
           ("delete", "/v1/jobs/{job_id}", "200"): job,
           ("get", "/v1/jobs/{job_id}/results", "200"): {
               "id": JOB_ID, "status": "succeeded",
               "results": [{"index": 0, "status": "succeeded", "result": msd_result(), "error": None}]},
           ("post", "/v1/fits", "200"): msd_result()}
    for kind in KINDS.values():
        if kind.jobs_path is not None:
            out[("post", kind.jobs_path, "202")] = {**msd_job_record(finished=False), "kind": kind.name}
    return out


def add_answer_examples(spec: dict) -> None:
    """An example on each answer listed in `answer_examples`, and on every 422."""
    invalid, examples_by_answer = invalid_request(), answer_examples()
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            for status, answer in op.get("responses", {}).items():
                example = examples_by_answer.get((method, path, status)) if status != "422" else invalid
                for media in (answer.get("content") or {}).values() if example is not None else ():
                    media["example"] = example
