"""Fuzzing a real server: schemathesis from its own OpenAPI, and mutations of valid fit requests.

Both demand zero 5xx, and every answer as the OpenAPI describes it (a 200 FitResult schema-valid,
errors as problem+json). Bounded: a fixed number of examples, a fixed seed, tiny fits with a
6-second CPU limit per task. CI runs fewer examples (5 generated cases an operation, 100 fit mutations,
100 of the other operations: with 50, no mutated discovery request was valid); `GREYFIT_FUZZ_FULL=1`
runs the long version (15, 300 and 150), as before a release or after a change to the validation:

    GREYFIT_FUZZ_FULL=1 .venv/bin/python -m pytest -q tests/service/test_fuzzing.py
"""
import copy
import json
import math
import os
import random
from pathlib import Path
from typing import NamedTuple

import httpx
import jsonschema_rs
import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import response_schema_conformance

from tests.service.conftest import msd_request
from tests.service.test_real_server import free_port, start_server, stop_server

KEY = "fuzz-key"
AUTH = {"Authorization": f"Bearer {KEY}"}
FULL = os.environ.get("GREYFIT_FUZZ_FULL", "") not in ("", "0")
EXAMPLES = 15 if FULL else 5            # generated cases per operation (schemathesis)
MUTATIONS = 300 if FULL else 100        # mutated fit requests
OTHER_MUTATIONS = 150 if FULL else 100  # mutated requests of the other synchronous operations
ROOT = Path(__file__).resolve().parents[2]
SEED = 20240917


class Fuzzed(NamedTuple):
    url: str
    log: Path

    def log_tail(self, lines: int = 60) -> str:
        """The server's last log lines: a 5xx's reason (a worker's trace, a timeout) is logged there."""
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    port = free_port()
    data_dir = tmp_path_factory.mktemp("fuzz")
    # the CPU limit bounds generated fits; a worker's first report (importing matplotlib, perhaps
    # building its font cache) takes up to ~2 s, which a limit of 2 s turned into a 504 now and then
    proc = start_server(data_dir, port, workers=2, log=data_dir / "server.log", GREYFIT_API_KEY=KEY,
                        GREYFIT_TASK_CPU_SECONDS="6", GREYFIT_TASK_WALL_SECONDS="20")
    yield Fuzzed(f"http://127.0.0.1:{port}", data_dir / "server.log")
    stop_server(proc)


@pytest.mark.slow
def test_openapi_fuzz_no_server_error_and_schema_conformance(server):
    """Every operation of /openapi.json, `EXAMPLES` generated cases each, derandomized (a fixed seed).

    Driven by hand rather than by schemathesis' pytest plugin, whose lazy loader does not run
    under pytest 9.2; no shrinking, so a failure costs no extra time.
    """
    schema = schemathesis.openapi.from_url(f"{server.url}/openapi.json", headers=AUTH)
    failures, operations = [], 0
    for result in schema.get_all_operations():
        operation = result.ok()
        operations += 1

        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                  phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
        def check(case):
            response = case.call(headers=AUTH, timeout=30)
            try:
                case.validate_response(response, checks=[not_a_server_error, response_schema_conformance])
            except Exception as exc:   # a failure group says only "Server error": add what was answered
                exc.add_note(f"answered {response.status_code} after {response.elapsed:.2f} s: "
                             f"{response.text[:400]}")
                raise

        try:
            check()
        except Exception as exc:   # collect every operation's failure, then report them together
            notes = "\n".join(getattr(exc, "__notes__", []))
            failures.append(f"{operation.method.upper()} {operation.path}: {str(exc)[:600]}\n{notes}")
    assert operations >= 10
    assert not failures, "\n\n".join(failures) + f"\n\nthe server's log ends:\n{server.log_tail()}"


# --- mutation fuzzer of valid fit requests ---------------------------------------------------------

NUMBERS = [math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, -1.0, 1e-308, 10 ** 30]
STRINGS = ["", "x" * 5000, "é漢字", "\u0000", "1/0", "1e999", "__import__('os')", "(" * 70 + "x" + ")" * 70,
           " ", "NaN", "x^x^x^x^x^x", "exp(exp(exp(x)))"]


def leaves(node, path=()):
    """(path, value) of every number, string and list of the request."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from leaves(v, path + (k,))
    elif isinstance(node, list):
        yield path, node
        if node and not isinstance(node[0], (int, float)):
            for i, v in enumerate(node):
                yield from leaves(v, path + (i,))
    elif isinstance(node, (int, float, str)) and not isinstance(node, bool):
        yield path, node


def mutate(body: dict, rng: random.Random) -> tuple[dict, list[str]]:
    body, notes = copy.deepcopy(body), []
    for _ in range(rng.randint(1, 3)):
        path, value = rng.choice(list(leaves(body)))   # again: an earlier mutation may have cut a list
        parent = body
        for p in path[:-1]:
            parent = parent[p]
        if isinstance(value, list):
            if value and isinstance(value[0], (int, float)) and rng.random() < 0.5:
                i = rng.randrange(len(value))          # one sample of a series
                new = list(value)
                new[i] = rng.choice(NUMBERS)
                notes.append(f"{'.'.join(map(str, path))}[{i}] = {new[i]}")
            else:
                new = value[: rng.choice([0, 1, len(value) // 2])]
                notes.append(f"{'.'.join(map(str, path))} truncated to {len(new)}")
        elif isinstance(value, str):
            new = rng.choice(STRINGS)
            notes.append(f"{'.'.join(map(str, path))} = {new[:30]!r}")
        else:
            new = rng.choice(NUMBERS + [-value, int(-1)])
            notes.append(f"{'.'.join(map(str, path))} = {new}")
        parent[path[-1]] = new
    return body, notes


def base_requests() -> list[dict]:
    out = []
    for method in ("equation_error", "single_shooting", "multiple_shooting"):
        body = msd_request(0, n=21)
        body["method"] = method
        body["options"] = {"max_cpu_time": 1.0, "return_traces": True, "multistart": 2, "seed": 1,
                           "output_weights": {"x": 1.0}, "derivative_window": 5}
        body["model"]["constants"] = {"g": 9.81}
        body["model"]["definitions"] = {"spring": "k*x"}
        body["model"]["equations"]["v"] = "(u - c*v - spring)/m"
        out.append(body)
    return out


def strict_json(text: str):
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")
    return json.loads(text, parse_constant=refuse)


RESULTS = {"/v1/fits": "FitResult", "/v1/frequency-fits": "FitResult", "/v1/simulate": "SimulateResult",
           "/v1/discover": "DiscoveryResult", "/v1/report": None}   # the report is an HTML page


def run_mutations(server: Fuzzed, bases: list[tuple[str, dict]], count: int, seed: int) -> dict[str, dict]:
    """POST `count` mutations of the (path, valid body) pairs in turn; fail on any 5xx or an answer
    the OpenAPI does not describe; return the statuses seen per path."""
    spec = httpx.get(f"{server.url}/openapi.json", headers=AUTH).json()
    validate = {name: jsonschema_rs.validator_for({"$ref": f"#/components/schemas/{name}",
                                                  "components": spec["components"]})
                for name in {"Problem", *filter(None, RESULTS.values())}}
    rng = random.Random(seed)
    failures, statuses = [], {}
    with httpx.Client(base_url=server.url, headers=AUTH, timeout=60) as http:
        for path, base in bases:   # the unmutated requests succeed: the fuzzer starts from valid ground
            resp = http.post(path, json=base)
            assert resp.status_code == 200, (path, resp.text[:300])
        for n in range(count):
            path, base = bases[n % len(bases)]
            body, notes = mutate(base, rng)
            text = json.dumps(body, allow_nan=True)
            resp = http.post(path, content=text, headers={"content-type": "application/json"})
            seen = statuses.setdefault(path, {})
            seen[resp.status_code] = seen.get(resp.status_code, 0) + 1
            kind = RESULTS[path] if resp.status_code == 200 else "Problem"
            if kind is None:
                if resp.status_code >= 500 or not resp.headers["content-type"].startswith("text/html"):
                    failures.append((path, resp.status_code, notes, resp.text[:200]))
                continue
            try:
                payload = strict_json(resp.text)
            except ValueError as exc:
                failures.append((path, resp.status_code, notes, f"not strict JSON: {exc}"))
                continue
            errors = [f"{'/'.join(map(str, e.instance_path))}: {e.message}"[:300]
                      for e in validate[kind].iter_errors(payload)][:3]
            if resp.status_code >= 500 or errors:
                failures.append((path, resp.status_code, notes, errors or payload.get("detail")))
    summary = "\n".join(f"{p} {s} {n} -> {e}" for p, s, n, e in failures[:15])
    assert not failures, (f"{len(failures)} of {count} mutations failed (statuses {statuses}):\n{summary}"
                          f"\n\nthe server's log ends:\n{server.log_tail()}")
    return statuses


@pytest.mark.slow
def test_mutated_fit_requests_get_no_5xx_and_schema_valid_results(server):
    statuses = run_mutations(server, [("/v1/fits", b) for b in base_requests()], MUTATIONS, SEED)["/v1/fits"]
    # both paths were exercised: over 300 mutations more than 20 fits and 50 refusals, in proportion when fewer
    assert statuses.get(200, 0) > 20 * MUTATIONS // 300 and statuses.get(422, 0) > 50 * MUTATIONS // 300, statuses


@pytest.mark.slow
def test_mutated_requests_of_the_other_synchronous_operations_get_no_5xx(server):
    """Reports, simulations, discovery and frequency fits, from valid requests that reach the workers
    (schemathesis' generated ones almost never do). A helper's longer run of this found 500s in
    frequency fits and a schema violation in discovery."""
    fit_request = msd_request(0, n=101)
    fit_request["options"] = {"return_traces": True}
    fit = httpx.post(f"{server.url}/v1/fits", json=fit_request, headers=AUTH, timeout=60).json()
    discover = msd_request(0, n=101)
    discover["options"] = {"max_cpu_time": 1.0}
    bases = [("/v1/report", {"result": fit, "request": fit_request, "title": "t"}),
             ("/v1/simulate", {"model": fit_request["model"], "experiments": fit_request["experiments"],
                               "fit_result": fit, "parameters": {"c": 0.5}, "horizon": 5}),
             ("/v1/discover", discover),
             ("/v1/frequency-fits", json.loads((ROOT / "examples" / "frequency_pi_loop_request.json").read_text())),
             ("/v1/report", {"result": fit})]
    statuses = run_mutations(server, bases, OTHER_MUTATIONS, SEED + 1)
    for path in RESULTS.keys() - {"/v1/fits"}:
        assert statuses[path].get(422, 0) > 0 and statuses[path].get(200, 0) > 0, statuses   # both paths
