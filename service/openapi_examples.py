"""Example request bodies for the OpenAPI description: real requests that work as sent.

FastAPI would generate an example from the schema alone (a state named "X1upTr6t…"), which "Try it
out" cannot send. These come from the repository's examples (copies shipped in
service/static/examples; tests/service/test_offline_docs.py keeps them equal), so each UI offers a
request that validates and converges. Each task kind names its example on its entry in
service/task_kinds.py; the builders are here.
"""
from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from greyfit.service.task_kinds import KINDS, Example

EXAMPLES_DIR = Path(__file__).resolve().parent / "static" / "examples"


@lru_cache(maxsize=None)
def example_request(filename: str) -> dict:
    """A request shipped in service/static/examples (a copy of examples/<filename> or its source)."""
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
