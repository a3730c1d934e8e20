"""Example request bodies for the OpenAPI description: real requests that work as sent.

FastAPI would generate an example from the schema alone (a state named "X1upTr6t…"), which "Try it
out" cannot send. These come from the repository's examples (copies shipped in
service/static/examples; tests/service/test_offline_docs.py keeps them equal), so each UI offers a
request that validates and converges.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

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


@dataclass(frozen=True)
class Example:
    name: str
    summary: str
    build: Callable[[], dict]


# path of a POST operation -> its example body
EXAMPLES: dict[str, Example] = {
    "/v1/fits": Example("msd_fit", "Mass-spring-damper m x'' + c x' + k x = u: c and k from noisy x and v",
                        msd_fit),
    "/v1/jobs": Example("msd_job", "The mass-spring-damper fit as a batch job of one request",
                        lambda: {"requests": [msd_fit()], "label": "demo"}),
    "/v1/discover": Example("msd_discover", "The mass-spring-damper fit, then a search for an effect it lacks "
                            "(its model is complete: nothing is added)",
                            lambda: {**msd_fit(), "discovery": {"max_terms": 1}}),
    "/v1/simulate": Example("msd_simulate", "The mass-spring-damper record simulated with c = 0.8, k = 5",
                            msd_simulation),
    "/v1/frequency-fits": Example("pi_loop", "A fourth-order plant measured in a PI loop at two controller "
                                  "settings (Parameter estimation from frequency data, Ohki)",
                                  lambda: example_request("frequency_pi_loop_request.json")),
}


def add_examples(spec: dict) -> None:
    """Give each request body in EXAMPLES its example (media-type `examples`, shown by both UIs)."""
    components = spec.setdefault("components", {}).setdefault("examples", {})
    for path, example in EXAMPLES.items():
        body = spec["paths"].get(path, {}).get("post", {}).get("requestBody")
        if body is None:
            continue
        components[example.name] = {"summary": example.summary, "value": example.build()}
        ref = {"$ref": f"#/components/examples/{example.name}"}
        body["content"]["application/json"]["examples"] = {example.name: ref}
