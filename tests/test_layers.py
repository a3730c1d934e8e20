"""A plain fit stays out of the discovery wing: the fit-time lack-of-fit screen lives in
`solvers/screening/`, below both the checks and discovery, so a fit loads no module of
`greyfit.solvers.discovery` (import-linter's layers contract in pyproject.toml sees only the imports
written down; this sees what a fit loads at run time, function-local imports included).

The fit runs in a fresh interpreter, since this test process has loaded discovery elsewhere."""
import json
import subprocess
import sys

# A first-order lag fitted by single shooting to a noisy step response: an output-error fit whose
# residual is not negligible, so the lack-of-fit check runs the screen (the screen's module must be loaded,
# or the fit never reached the import this test is about).
FIT = """
import json, sys
import numpy as np
import greyfit
t = np.linspace(0.0, 3.0, 61)
noise = 0.02 * np.random.default_rng(1).standard_normal(t.size)
model = greyfit.Model(states=["x"], inputs=["u"], equations={"x": "(K*u - x)/tau"},
                      parameters=[greyfit.Parameter("K", 1.0, lower=0),
                                  greyfit.Parameter("tau", 2.0, lower=0.01)])
record = greyfit.Experiment(time=t, inputs={"u": np.ones_like(t)},
                            outputs={"x": 2.0 * (1.0 - np.exp(-t / 0.5)) + noise}, initial_state={"x": 0.0})
result = greyfit.fit(model=model, experiments=[record], method="single_shooting")
print(json.dumps({"K": result.parameters["K"].value, "tau": result.parameters["tau"].value,
                  "warnings": [w.code for w in result.warnings],
                  "modules": sorted(m for m in sys.modules if m.startswith("greyfit."))}))
"""


def test_a_plain_fit_imports_no_discovery_module():
    done = subprocess.run([sys.executable, "-c", FIT], capture_output=True, text=True, timeout=300, check=True)
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert abs(out["K"] - 2.0) < 0.05 and abs(out["tau"] - 0.5) < 0.05   # the fit ran and found the truth
    assert "lack_of_fit_not_screened" not in out["warnings"]
    assert "greyfit.solvers.screening.screening" in out["modules"]     # the screen ran ...
    loaded = [m for m in out["modules"] if m.startswith("greyfit.solvers.discovery")]
    assert not loaded, f"a plain fit loaded the discovery wing: {loaded}"  # ... without discovery
