"""greyfit against the peers an expert would write, in one interleaved run (issue #26's table).

    python bench/bench_peers.py [--repeats 5] [--problems a b c d e] [--fits 200] [--cold 5]

Peers, installed only for benchmarks (`pip install -e .[bench]`):
- a hand-written CasADi single shooting as CasADi's own system-identification example writes it: an
  RK4 step Function expanded to SX, `mapaccum` over the samples, Ipopt with a Gauss-Newton Hessian
  (JᵀJ), every NLP function JIT-compiled with gcc -O3; the data enter as NLP parameters, so one
  compiled solver serves every record of a shape;
- JAX + optimistix Levenberg-Marquardt (RK4 in `jax.lax.scan`, float64, `jax.jit`); skipped, and said
  so, where JAX or optimistix is not installed.
Every tool fits the same data from the same start with the same discretisation (RK4, the same
substeps, inputs linear between samples, known initial states) and the same weighted least squares
(each output weighted by 1/std, as greyfit does), so all reach one optimum.

Each tool runs in its own spawned process (its peak RSS is its own), set up and warmed first (greyfit
until every library its fits ask for, the checks' included, is built: a warm service worker); then
the parent asks every process for one fit in turn, round after round (ABAB...), and prints the
medians of CPU and wall time, the accuracy against the true parameters and the largest relative
difference from the hand-written CasADi optimum. Problem e (200 fits of 401 samples) goes through a
real `greyfit serve` with 2 workers and its jobs API, against one Python loop of the CasADi peer and
one `jax.vmap` (its compile time apart). For the seat (b), `--cold` fresh processes per setting, each
with an empty compile cache, time greyfit's first fit with compiling (`auto`, with the quick tier: tcc
where it is installed), with gcc alone (`auto`, `GREYFIT_QUICK_COMPILER=off`) and without compiling
(`never`), in turns, against the warm interpreted fit: one first fit per process is a single sample.

The arithmetic floor: the per-sample RK4 step and its forward sensitivity (∂x+/∂x·S + ∂x+/∂θ) as
CasADi SX, their operation counts after common-subexpression elimination, plus the JᵀJ and Jᵀr
accumulation per sample; the rate is measured on the same sensitivity kernel generated as C and
compiled with gcc -O3 on this machine. Floor of one Gauss-Newton iteration = samples × ops / rate.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_methods import start_guess  # noqa: E402
from tests.servers import unix_time  # noqa: E402
from tests.systems import (  # noqa: E402
    MSD_TRUTH,
    SEAT_MASSES,
    SEAT_TRUTH,
    msd_input,
    msd_model,
    seat_model,
    simulate_msd,
    simulate_seat,
)

SEAT_STATES = ["q1", "q2", "q3", "q4", "v1", "v2", "v3", "v4"]
TITLES = {"a": "2 states, 101 samples", "b": "seat model, 8 states, 1 000 samples",
          "c": "2 states, 40 000 samples", "d": "2 states, 200 000 samples",
          "e": "small fits (401 samples), one job or loop or vmap"}


# --- the problems: data made once by the parent, read by every tool's process ------------------
def msd_rhs(x, u, p, stack):
    m, c, k = p[0], p[1], p[2]
    return stack([x[1], (u[0] - c * x[1] - k * x[0]) / m])


def seat_rhs(x, u, p, stack):
    m1, m2, m3, m4 = SEAT_MASSES
    d1, d2, d3, d4, k1, k2, k3, k4 = (p[i] for i in range(8))
    q1, q2, q3, q4, v1, v2, v3, v4 = (x[i] for i in range(8))
    w, wd = u[0], u[1]
    return stack([v1, v2, v3, v4,
                  -(d1 * (v1 - v2) + k1 * (q1 - q2)) / m1,
                  -(d1 * (v2 - v1) + d2 * (v2 - v3) + k1 * (q2 - q1) + k2 * (q2 - q3)) / m2,
                  -(d2 * (v3 - v2) + d3 * (v3 - v4) + k2 * (q3 - q2) + k3 * (q3 - q4)) / m3,
                  -(d3 * (v4 - v3) + d4 * (v4 - wd) + k3 * (q4 - q3) + k4 * (q4 - w)) / m4])


RHS = {"msd": msd_rhs, "seat": seat_rhs}


def msd_states(t: np.ndarray) -> np.ndarray:
    """The truth simulation: scipy's DOP853 (tests.systems) up to 50 000 samples; beyond, CVODES at
    the same tolerances with the input as a function of time (a Python right-hand side called millions
    of times would take longer than every fit of the record)."""
    if t.size <= 50_000:
        return simulate_msd(t)
    import casadi as ca
    x, tt = ca.SX.sym("x", 2), ca.SX.sym("t")
    m, c, k = MSD_TRUTH["m"], MSD_TRUTH["c"], MSD_TRUTH["k"]
    u = ca.sin(tt) + 0.5 * ca.sin(3.3 * tt) + 0.3 * ca.sin(0.7 * tt) ** 3   # tests.systems.msd_input
    sim = ca.integrator("truth", "cvodes", {"x": x, "t": tt, "ode": ca.vertcat(x[1], (u - c * x[1] - k * x[0]) / m)},
                        float(t[0]), t[1:].tolist(), {"abstol": 1e-13, "reltol": 1e-11, "max_num_steps": 100_000})
    return np.hstack([[[0.1], [0.0]], np.asarray(sim(x0=[0.1, 0.0])["xf"])])


def make_problem(key: str, fits: int) -> dict:
    """Arrays of one problem: t, u (nu, N), y (records, ny, N), the measured states, x0, start, truth."""
    if key == "b":
        t, x, _dx, w, wd = simulate_seat(seed=0)
        rng = np.random.default_rng(3)
        y = x + 0.01 * np.sqrt(np.mean(x ** 2, axis=1, keepdims=True)) * rng.standard_normal(x.shape)
        return dict(kind="seat", t=t, u=np.vstack([w, wd]), y=y[None], measured=np.arange(8), x0=np.zeros(8),
                    start=np.array(list(start_guess().values())), truth=np.array(list(SEAT_TRUTH.values())),
                    free=np.arange(8), substeps=2)
    n, noise, outputs, start = {"a": (101, 0.005, 2, (2.0, 0.5, 3.0)), "c": (40_000, 0.01, 1, (2.0, 0.4, 3.0)),
                                "d": (200_000, 0.01, 1, (2.0, 0.4, 3.0)),
                                "e": (401, 0.005, 2, (2.0, 0.5, 3.0))}[key]
    t = np.linspace(0, 10, n) if key in "ae" else np.arange(n) * 0.01
    x = msd_states(t)
    records = fits if key == "e" else 1
    y = np.stack([x[:outputs] + noise * np.random.default_rng(s).standard_normal((outputs, n))
                  for s in range(records)])
    return dict(kind="msd", t=t, u=msd_input(t)[None], y=y, measured=np.arange(outputs), x0=np.array([0.1, 0.0]),
                start=np.array(start), truth=np.array(list(MSD_TRUTH.values())), free=np.array([1, 2]), substeps=1)


def load(path: str) -> dict:
    with np.load(path) as z:
        prob = {k: z[k] for k in z.files}
    prob["kind"] = str(prob["kind"])
    prob["substeps"] = int(prob["substeps"])
    prob["weights"] = 1.0 / prob["y"].std(axis=2)   # (records, ny): greyfit's default 1/std per output
    return prob


def fit_request(prob: dict, record: int, method: str, options: str = "pinned") -> dict:
    """The same fit as greyfit's JSON request: `options` "pinned" (the peers' substeps and foh), "foh"
    (only the interpolation pinned) or "none" (every option left to greyfit: what a user sends)."""
    if prob["kind"] == "seat":
        model = seat_model(dict(zip(SEAT_TRUTH, prob["start"])))
        names, inputs = SEAT_STATES, {"w": prob["u"][0].tolist(), "wd": prob["u"][1].tolist()}
    else:
        model = msd_model(m=prob["start"][0], c=prob["start"][1], k=prob["start"][2])
        names, inputs = ["x", "v"], {"u": prob["u"][0].tolist()}
        model["outputs"] = {s: s for s in names[:len(prob["measured"])]}
    exp = {"name": "e1", "time": prob["t"].tolist(), "inputs": inputs,
           "outputs": {names[i]: prob["y"][record, j].tolist() for j, i in enumerate(prob["measured"])},
           "initial_state": dict(zip(names, prob["x0"].tolist()))}
    return {"model": model, "experiments": [exp], "method": method,
            "options": {"pinned": {"substeps": prob["substeps"], "input_interpolation": "foh"},
                        "foh": {"input_interpolation": "foh"}, "none": {}}[options]}


def vertcat(parts):
    import casadi as ca
    return ca.vertcat(*parts)


def rk4(rhs, x, u0, u1, p, dt, substeps, stack):
    """One sample interval: `substeps` RK4 steps, inputs linear between the samples (greyfit's foh)."""
    h = dt / substeps
    for i in range(substeps):
        a, b, c = u0 + (u1 - u0) * (i / substeps), u0 + (u1 - u0) * ((i + 0.5) / substeps), \
            u0 + (u1 - u0) * ((i + 1) / substeps)
        k1 = rhs(x, a, p, stack)
        k2 = rhs(x + h / 2 * k1, b, p, stack)
        k3 = rhs(x + h / 2 * k2, b, p, stack)
        k4 = rhs(x + h * k3, c, p, stack)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


# --- the tools: each returns fit(record) -> (free parameters, iterations, compiled, solve seconds) ---
# (compiled: greyfit's solver.compiled, the vmap's compile CPU; solve seconds: greyfit's solve stage, its
# result's solver.timings, None for the peers, whose whole fit is a solve)
def setup_greyfit(prob: dict, method: str, options: str = "pinned"):
    import greyfit
    import greyfit.solvers.timing as timing
    timing._now = time.process_time   # the stages' times in CPU, to set beside the peers' CPU
    requests = [greyfit.FitRequest.model_validate(fit_request(prob, r, method, options))
                for r in range(len(prob["y"]))]
    names = ["d1", "d2", "d3", "d4", "k1", "k2", "k3", "k4"] if prob["kind"] == "seat" else ["c", "k"]

    def fit(record: int):
        res = greyfit.fit(requests[record])
        return (np.array([res.parameters[k].value for k in names]), res.solver.iterations, res.solver.compiled,
                res.solver.timings["solve"])
    return fit


def setup_casadi(prob: dict):
    import casadi as ca
    nx, nu, (_, ny, n) = len(prob["x0"]), len(prob["u"]), prob["y"].shape
    free, scale = prob["free"], prob["start"][prob["free"]]
    x, u0, u1, p = ca.SX.sym("x", nx), ca.SX.sym("u0", nu), ca.SX.sym("u1", nu), ca.SX.sym("p", len(prob["start"]))
    dt = float(prob["t"][1] - prob["t"][0])
    one_sample = ca.Function("one_sample", [x, u0, u1, p],
                             [rk4(RHS[prob["kind"]], x, u0, u1, p, dt, prob["substeps"], vertcat)])
    simulate = one_sample.mapaccum("simulate", n - 1)
    theta = ca.MX.sym("theta", len(free))
    data = ca.MX.sym("data", nu * n + ny * n + ny)   # inputs, measured outputs, weights
    U = ca.reshape(data[:nu * n], nu, n)
    Y = ca.reshape(data[nu * n:nu * n + ny * n], ny, n)
    W = data[nu * n + ny * n:]
    full = ca.MX(prob["start"])
    for j, i in enumerate(free):
        full[int(i)] = theta[j] * scale[j]
    X = simulate(ca.DM(prob["x0"]), U[:, :-1], U[:, 1:], ca.repmat(full, 1, n - 1))
    e = ca.vec(ca.repmat(W, 1, n - 1) * (X[prob["measured"].tolist(), :] - Y[:, 1:]))
    J = ca.jacobian(e, theta)
    sigma, lam_g = ca.MX.sym("sigma"), ca.MX.sym("lam_g", 0)
    jit = {"jit": True, "compiler": "shell", "jit_options": {"flags": ["-O3"], "verbose": False}}
    hess = ca.Function("nlp_hess_l", [theta, data, sigma, lam_g], [sigma * ca.triu(ca.mtimes(J.T, J))],
                       ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"], jit)
    solver = ca.nlpsol("solver", "ipopt", {"x": theta, "p": data, "f": 0.5 * ca.sumsqr(e)},
                       dict(jit, hess_lag=hess, print_time=False,
                            ipopt={"print_level": 0, "sb": "yes", "tol": 1e-8}))
    params = [np.concatenate([prob["u"].ravel(order="F"), prob["y"][r].ravel(order="F"), prob["weights"][r]])
              for r in range(len(prob["y"]))]

    def fit(record: int):
        sol = solver(x0=np.ones(len(free)), p=params[record], lbx=0)
        return np.asarray(sol["x"]).ravel() * scale, int(solver.stats()["iter_count"]), True, None
    return fit


def jax_residual(prob: dict):
    import jax.numpy as jnp
    from jax import lax
    free, scale = prob["free"], prob["start"][prob["free"]]
    dt, rhs = float(prob["t"][1] - prob["t"][0]), RHS[prob["kind"]]
    x0, measured, start = jnp.asarray(prob["x0"]), jnp.asarray(prob["measured"]), jnp.asarray(prob["start"])

    def residual(theta, args):
        u, y, w = args   # (N, nu), (ny, N), (ny,)
        p = start.at[free].set(theta * scale)

        def step(xk, uu):
            xn = rk4(rhs, xk, uu[0], uu[1], p, dt, prob["substeps"], jnp.stack)
            return xn, xn[measured]
        _, ys = lax.scan(step, x0, (u[:-1], u[1:]))
        return (w[:, None] * (ys.T - y[:, 1:])).ravel()
    return residual


def setup_jax(prob: dict, batched: bool = False):
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import optimistix as optx
    residual, scale = jax_residual(prob), prob["start"][prob["free"]]
    lm = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)

    def solve(y, w):
        args = (jnp.asarray(prob["u"].T), y, w)
        sol = optx.least_squares(residual, lm, jnp.ones(len(scale)), args=args, max_steps=200, throw=False)
        return sol.value, sol.stats["num_steps"]
    ys, ws = jnp.asarray(prob["y"]), jnp.asarray(prob["weights"])
    if batched:
        c0 = time.process_time()
        compiled = jax.jit(jax.vmap(solve)).lower(ys, ws).compile()
        compile_cpu = time.process_time() - c0

        def fit_all(_record: int):
            value, steps = jax.block_until_ready(compiled(ys, ws))
            return np.asarray(value) * scale, int(np.max(steps)), compile_cpu, None
        return fit_all
    compiled = jax.jit(solve).lower(ys[0], ws[0]).compile()

    def fit(record: int):
        value, steps = jax.block_until_ready(compiled(ys[record], ws[record]))
        return np.asarray(value) * scale, int(steps), True, None
    return fit


def setup_casadi_loop(prob: dict):
    fit_one = setup_casadi(prob)

    def fit_all(_record: int):
        out = [fit_one(r) for r in range(len(prob["y"]))]
        return np.array([o[0] for o in out]), max(o[1] for o in out), True, None
    return fit_all


TOOLS = {"greyfit default": lambda prob: setup_greyfit(prob, "auto"),
         "greyfit MS": lambda prob: setup_greyfit(prob, "multiple_shooting"),
         "greyfit SS": lambda prob: setup_greyfit(prob, "single_shooting"),
         "greyfit default, foh only": lambda prob: setup_greyfit(prob, "auto", "foh"),
         "greyfit default, no options": lambda prob: setup_greyfit(prob, "auto", "none"),
         "CasADi SS jit -O3": setup_casadi, "JAX optimistix LM": setup_jax,
         "CasADi SS loop": setup_casadi_loop, "JAX vmap LM": lambda prob: setup_jax(prob, batched=True)}


def tool_process(tool: str, path: str, cache: str, conn) -> None:
    """Set up one tool, fit once cold (and warm it), then fit on request until told to stop."""
    os.environ.update(GREYFIT_CACHE_DIR=cache, OPENBLAS_NUM_THREADS="1")
    prob = load(path)
    c0, w0 = time.process_time(), time.perf_counter()
    fit = TOOLS[tool](prob)
    out = fit(0)
    cold = (time.perf_counter() - w0, time.process_time() - c0, out[2])
    deadline = time.monotonic() + 120
    while out[2] is False and time.monotonic() < deadline:   # greyfit compiles in the background
        time.sleep(0.5)
        out = fit(0)
    if tool.startswith("greyfit"):
        # warm as a service worker is warm: the checks' kernels are built on their first use, after
        # the solve's, and a fit timed before they are ready runs them interpreted (and shares the
        # CPUs with gcc)
        from greyfit.solvers.dynamics.compiled import wait_for_builds
        for _ in range(3):
            wait_for_builds(120)
            out = fit(0)
        wait_for_builds(120)
    conn.send(cold)
    record = 0
    while conn.recv() == "fit":
        record = (record + 1) % len(prob["y"])
        c0, w0 = time.process_time(), time.perf_counter()
        value, iters, compiled, solve = fit(record)
        conn.send((time.perf_counter() - w0, time.process_time() - c0, value, iters, compiled, record, solve))
    conn.send(peak_rss_mb())


def peak_rss_mb() -> float:
    """This process's own peak RSS: VmHWM (ru_maxrss keeps the spawning parent's peak across exec)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def jax_available() -> bool:
    try:
        import jax  # noqa: F401
        import optimistix  # noqa: F401
    except ImportError:
        return False
    return True


# --- problem e through the service: one server, 2 workers, one job of all the fits per round -----
class JobsRunner:
    """A real `greyfit serve --workers 2`, warm; `fit` posts one job of every record and waits."""

    def __init__(self, prob: dict, workers: int = 2):
        import httpx

        from bench.bench_service import CpuMeter, serve, wait_for_builds
        from tests.servers import free_port
        self.tmp = tempfile.TemporaryDirectory()
        port = free_port()
        self.proc = serve(workers, self.tmp.name, port)
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120)
        requests = [fit_request(prob, r, "auto") for r in range(len(prob["y"]))]   # the default method
        self.body = json.dumps({"requests": requests}).encode()
        first = json.dumps(requests[0]).encode()
        self._wait(self.client.post("/v1/jobs", json={"requests": requests[:workers]}).json()["id"])
        wait_for_builds(self.client, first, self.tmp.name, workers)
        self.meter = CpuMeter(self.proc.pid)

    def _wait(self, job_id: str) -> dict:
        while (job := self.client.get(f"/v1/jobs/{job_id}").json())["status"] in ("queued", "running"):
            time.sleep(0.1)
        return job

    def fit(self):
        self.meter.start()
        t0 = time.time()
        job_id = self.client.post("/v1/jobs", content=self.body,
                                  headers={"content-type": "application/json"}).json()["id"]
        job = self._wait(job_id)
        server, workers = self.meter.stop()
        results = self.client.get(f"/v1/jobs/{job_id}/results").json()["results"]
        names = ["c", "k"]
        values = np.array([[r["result"]["parameters"][k]["value"] for k in names] for r in results])
        return (unix_time(job["finished_at"]) - t0, server + workers, values,
                max(r["result"]["solver"]["iterations"] for r in results),
                None)   # the workers' stage times are wall (their clock is their own): no CPU to compare

    def close(self) -> None:
        from tests.servers import stop_server
        self.client.close()
        stop_server(self.proc)
        self.tmp.cleanup()


# --- the arithmetic floor --------------------------------------------------------------------------
def count_ops(f) -> int:
    import casadi as ca
    skip = {ca.OP_INPUT, ca.OP_OUTPUT, ca.OP_CONST, ca.OP_PARAMETER}
    return sum(1 for k in range(f.n_instructions()) if f.instruction_id(k) not in skip)


def floor_kernels(prob: dict):
    """(step, step + sensitivity) as SX Functions of one sample, and the JᵀJ + Jᵀr flops per sample."""
    import casadi as ca
    nx, nu, nf, ny = len(prob["x0"]), len(prob["u"]), len(prob["free"]), len(prob["measured"])
    x, u0, u1, th = ca.SX.sym("x", nx), ca.SX.sym("u0", nu), ca.SX.sym("u1", nu), ca.SX.sym("theta", nf)
    p = ca.SX(prob["start"])
    for j, i in enumerate(prob["free"]):
        p[int(i)] = th[j]
    dt = float(prob["t"][1] - prob["t"][0])
    xn = rk4(RHS[prob["kind"]], x, u0, u1, p, dt, prob["substeps"], vertcat)
    S = ca.SX.sym("S", nx, nf)
    Sn = ca.mtimes(ca.jacobian(xn, x), S) + ca.jacobian(xn, th)
    step = ca.Function("step", [x, u0, u1, th], [ca.cse(xn)])
    outs = ca.cse([xn, Sn])
    sens = ca.Function("sens", [x, S, u0, u1, th], outs)
    # per output row of J: the weighted row (nf), Jᵀr (2 nf), the upper triangle of JᵀJ (nf (nf+1)), r (2)
    accumulate = ny * (nf + 2 * nf + nf * (nf + 1) + 2)
    return step, sens, accumulate


DRIVER = r"""
#include <math.h>
#include <stdio.h>
#include <time.h>
int sens(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem);
int main(void) {
  static casadi_real x[2][NX], S[2][NX * NF], u0[NU], u1[NU], th[NF] = {THETA}, w[SZ_W + 1];
  static casadi_int iw[SZ_IW + 1];
  const casadi_real* arg[SZ_ARG + 1]; casadi_real* res[SZ_RES + 1];
  long n = SAMPLES; int a = 0;
  clock_t t0 = clock();
  for (long i = 0; i < n; ++i) {   /* chained: each sample starts from the last one's x and S */
    for (int j = 0; j < NU; ++j) { u0[j] = 1e-3 * sin(1e-2 * i + j); u1[j] = 1e-3 * sin(1e-2 * (i + 1) + j); }
    arg[0] = x[a]; arg[1] = S[a]; arg[2] = u0; arg[3] = u1; arg[4] = th; res[0] = x[1 - a]; res[1] = S[1 - a];
    sens(arg, res, iw, w, 0);
    a = 1 - a;
  }
  double cpu = (double)(clock() - t0) / CLOCKS_PER_SEC;
  printf("%.9e %.3e\n", cpu / n, x[a][0] + S[a][0]);
  return 0;
}
"""


def floor_program(prob: dict, sens, folder: str, samples: int = 2_000_000) -> str:
    """A program that prints the CPU seconds per sample of the per-sample sensitivity kernel,
    generated as C by CasADi and compiled gcc -O3, looped over `samples` chained samples by a plain C
    driver (no CasADi machinery between samples); the inputs' sines are the driver's, outside the
    count. Returns its path (in `folder`)."""
    import casadi as ca
    theta = ", ".join(repr(float(v)) for v in prob["start"][prob["free"]])
    sizes = dict(NX=len(prob["x0"]), NF=len(prob["free"]), NU=len(prob["u"]), SZ_W=sens.sz_w(), SZ_IW=sens.sz_iw(),
                 SZ_ARG=sens.sz_arg(), SZ_RES=sens.sz_res(), SAMPLES=samples)
    cg = ca.CodeGenerator("kernel.c")
    cg.add(sens)
    cg.generate(folder + os.sep)
    driver = DRIVER.replace("THETA", theta)
    for k, v in sizes.items():
        driver = driver.replace(k, str(v))
    header = "#define casadi_real double\n#define casadi_int long long int\n"
    Path(folder, "driver.c").write_text(header + driver)
    exe = os.path.join(folder, "floor")
    subprocess.run(["gcc", "-O3", os.path.join(folder, "kernel.c"), os.path.join(folder, "driver.c"), "-lm", "-o", exe],
                   check=True)
    return exe


def floor_seconds_per_sample(exe: str) -> float:
    """One run of `floor_program`'s program: CPU seconds per sample."""
    return float(subprocess.run([exe], check=True, capture_output=True, text=True).stdout.split()[0])


class Floor:
    """The arithmetic floor of one Gauss-Newton iteration: the kernels' operation count, and the rate
    the sensitivity kernel runs at, measured once per round of the benchmark (beside the tools, so
    the machine's drift through a run moves the floor as it moves them); the median rate counts."""

    def __init__(self, prob: dict, folder: str):
        step, sens, self.accumulate = floor_kernels(prob)
        self.n_step, self.n_sens = count_ops(step), count_ops(sens)
        self.flops = prob["y"].shape[2] * (self.n_sens + self.accumulate)
        self.exe = floor_program(prob, sens, folder)
        self.per_sample: list[float] = []

    def measure(self) -> None:
        self.per_sample.append(floor_seconds_per_sample(self.exe))

    def result(self) -> dict:
        rate = self.n_sens / float(np.median(self.per_sample))
        return dict(step=self.n_step, sensitivity=self.n_sens - self.n_step, accumulate=self.accumulate,
                    flops=self.flops, rate=rate, seconds=self.flops / rate, runs=len(self.per_sample))


# --- the run ---------------------------------------------------------------------------------------
def start_tool(tool: str, path: str, cache: str):
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=tool_process, args=(tool, path, cache, child))
    env = {"GREYFIT_COMPILE": "never"} if tool.endswith("interpreted") else {}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)   # a spawned child reads its environment at start
    proc.start()
    child.close()   # a child that dies now ends the parent's recv with EOFError instead of a hang
    for k, v in old.items():
        os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
    return proc, parent, parent.recv()


def cold_process(path: str, cache: str, conn) -> None:
    """A fresh process's first fit of greyfit's default method, its setup included (wall seconds)."""
    os.environ.update(GREYFIT_CACHE_DIR=cache, OPENBLAS_NUM_THREADS="1")
    prob = load(path)
    w0 = time.perf_counter()
    TOOLS["greyfit default"](prob)(0)
    conn.send(time.perf_counter() - w0)


# the settings of the cold first fits: (label, environment)
COLD_SETTINGS = {"GREYFIT_COMPILE=auto": {"GREYFIT_COMPILE": "auto"},
                 "GREYFIT_COMPILE=auto, GREYFIT_QUICK_COMPILER=off": {"GREYFIT_COMPILE": "auto",
                                                                      "GREYFIT_QUICK_COMPILER": "off"},
                 "GREYFIT_COMPILE=never": {"GREYFIT_COMPILE": "never"}}


def cold_starts(path: str, tmp: str, count: int) -> dict[str, list[float]]:
    """`count` fresh processes with an empty compile cache each, per setting of `COLD_SETTINGS` in
    turns: one first fit per process is a single sample, and it moves with the machine."""
    ctx = mp.get_context("spawn")
    out: dict[str, list[float]] = {label: [] for label in COLD_SETTINGS}
    for i in range(count):
        for k, (label, env) in enumerate(COLD_SETTINGS.items()):
            parent, child = ctx.Pipe()
            old = {name: os.environ.get(name) for name in ("GREYFIT_COMPILE", "GREYFIT_QUICK_COMPILER")}
            os.environ.pop("GREYFIT_QUICK_COMPILER", None)
            os.environ.update(env)
            proc = ctx.Process(target=cold_process, args=(path, os.path.join(tmp, f"cold-{k}-{i}"), child))
            proc.start()
            for name, value in old.items():
                os.environ.pop(name, None) if value is None else os.environ.__setitem__(name, value)
            child.close()
            out[label].append(parent.recv())
            proc.join()
    return out


def tools_for(key: str, with_jax: bool) -> list[str]:
    if key == "e":
        names = ["CasADi SS loop", "JAX vmap LM"]
    else:
        names = ["greyfit default", "greyfit default, foh only", "greyfit default, no options", "greyfit MS",
                 "greyfit SS", "CasADi SS jit -O3", "JAX optimistix LM"]
        if key == "b":   # the cold first fit is set against the warm interpreted fit of the default method
            names += ["greyfit default interpreted", "greyfit MS interpreted"]
    return [n for n in names if with_jax or not n.startswith("JAX")]


TOOLS["greyfit MS interpreted"] = TOOLS["greyfit MS"]
TOOLS["greyfit default interpreted"] = TOOLS["greyfit default"]


def run_problem(key: str, args, with_jax: bool, tmp: str) -> dict:
    prob = make_problem(key, args.fits)
    path = os.path.join(tmp, f"{key}.npz")
    np.savez(path, **prob)
    prob = load(path)
    names = tools_for(key, with_jax)
    procs = {n: start_tool(n, path, os.path.join(tmp, f"cache-{key}-{i}")) for i, n in enumerate(names)}
    runner = JobsRunner(prob) if key == "e" else None
    floor_dir = os.path.join(tmp, f"floor-{key}")
    os.makedirs(floor_dir, exist_ok=True)
    floor = Floor(prob, floor_dir)
    rows: dict[str, list] = {n: [] for n in (["greyfit jobs API, 2 workers"] if runner else []) + names}
    load_before = os.getloadavg()
    for _ in range(args.repeats):   # ABAB: every tool once per round, the same order each round
        if runner is not None:
            rows["greyfit jobs API, 2 workers"].append(runner.fit())
        for n, (_proc, conn, _cold) in procs.items():
            conn.send("fit")
            wall, cpu, value, iters, _compiled, _record, solve = conn.recv()
            rows[n].append((wall, cpu, value, iters, solve))
        floor.measure()
    load_after = os.getloadavg()
    peak, cold = {}, {}
    for n, (proc, conn, first) in procs.items():
        conn.send("stop")
        peak[n], cold[n] = conn.recv(), first
        proc.join()
    if runner is not None:
        runner.close()
    starts = cold_starts(path, tmp, args.cold) if key == "b" and args.cold else {}
    return dict(prob=prob, rows=rows, peak=peak, cold=cold, load=(load_before, load_after),
                floor=floor.result(), starts=starts)


def report(key: str, out: dict) -> list[str]:
    prob, rows, floor = out["prob"], out["rows"], out["floor"]
    truth = prob["truth"][prob["free"]]
    ref_name = "CasADi SS loop" if key == "e" else "CasADi SS jit -O3"
    ref = [np.atleast_2d(r[2]) for r in rows[ref_name]]
    cpu = {n: float(np.median([r[1] for r in rs])) for n, rs in rows.items()}
    peers = [cpu[n] for n in cpu if not n.startswith("greyfit")]
    lines = [f"({key}) {TITLES[key]}: load average {out['load'][0][0]:.2f} before, {out['load'][1][0]:.2f} after; "
             f"floor {floor['flops'] / 1e6:.2f} MFLOP per Gauss-Newton iteration (step {floor['step']}, "
             f"sensitivity {floor['sensitivity']}, JᵀJ+Jᵀr {floor['accumulate']} ops per sample) at "
             f"{floor['rate'] / 1e9:.2f} GFLOP/s (median of {floor['runs']} runs, one per round) = "
             f"{1e3 * floor['seconds']:.3f} ms"]
    lines.append(f"  {'tool':28s} {'CPU ms':>9s} {'wall ms':>9s} {'/best peer':>10s} {'iter':>4s} "
                 f"{'err vs truth':>12s} {'vs CasADi':>9s} {'x floor/it':>10s} {'peak MB':>8s} {'first fit s':>11s} "
                 f"{'solve ms':>8s} {'solve/best peer':>15s}")
    for n, rs in rows.items():
        values = [np.atleast_2d(r[2]) for r in rs]
        err = max(float(np.median(np.max(np.abs(v / truth - 1), axis=1))) for v in values)
        agree = max(float(np.max(np.abs(v / r - 1))) for v, r in zip(values, ref))
        iters = int(np.median([r[3] for r in rs]))
        wall = float(np.median([r[0] for r in rs]))
        fits = len(prob["y"])
        per_iter = cpu[n] / fits / max(iters, 1)
        best = f"{cpu[n] / min(peers):10.2f}" if peers else f"{'':10s}"
        first = out["cold"].get(n)
        first_txt = f"{first[0]:11.2f}" if first else f"{'':11s}"
        if n == "JAX vmap LM" and first:
            first_txt += f"  (compile {first[2]:.1f} s CPU)"
        mem = f"{out['peak'][n]:8.0f}" if n in out["peak"] else f"{'':8s}"
        solves = [r[4] for r in rs if r[4] is not None]
        solve_txt = ""
        if solves:   # greyfit's solve stage (CPU), its checks apart: the peers' whole fit is a solve
            solve = float(np.median(solves))
            solve_txt = f" {1e3 * solve:8.1f}" + (f" {solve / min(peers):15.2f}" if peers else "")
        lines.append(f"  {n:28s} {1e3 * cpu[n]:9.1f} {1e3 * wall:9.1f} {best} {iters:4d} {err:12.2e} "
                     f"{agree:9.1e} {per_iter / floor['seconds']:10.1f} {mem} {first_txt:11s}{solve_txt}".rstrip())
    starts = out.get("starts")
    if starts and "greyfit default interpreted" in rows:
        warm = float(np.median([r[0] for r in rows["greyfit default interpreted"]]))
        for how, walls in starts.items():
            med = float(np.median(walls))
            lines.append(f"  first fit in a fresh process, empty cache, {how}: median {med:.2f} s of "
                         f"{len(walls)} ({min(walls):.2f}-{max(walls):.2f}), {med / warm:.2f}x the warm interpreted "
                         f"fit ({warm:.2f} s wall)")
    return lines


def main() -> None:
    os.environ["OPENBLAS_NUM_THREADS"] = "1"   # inherited by the spawned tools (see bench_speed.py)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--problems", nargs="*", default=list(TITLES), choices=list(TITLES))
    parser.add_argument("--fits", type=int, default=200, help="fits in problem e")
    parser.add_argument("--skip-jax", action="store_true")
    parser.add_argument("--cold", type=int, default=5,
                        help="fresh processes per setting for the seat's first fit (problem b; 0: none)")
    args = parser.parse_args()
    with_jax = jax_available() and not args.skip_jax
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; CPU and wall: medians of "
          f"{args.repeats} interleaved rounds, warm (the first fit of each process apart)")
    if not with_jax:
        print("JAX + optimistix: not installed (pip install -e .[bench]) or --skip-jax; its rows are left out")
    with tempfile.TemporaryDirectory() as tmp:
        for key in args.problems:
            print("\n".join(report(key, run_problem(key, args, with_jax, tmp))), flush=True)
    print("err vs truth: largest relative parameter error (problem e: median over the fits); vs CasADi: the "
          "largest relative difference from the hand-written CasADi optimum; x floor/it: CPU per iteration over "
          "the floor of one Gauss-Newton iteration; problem e's CPU: server + workers for greyfit, all fits; "
          "solve ms: greyfit's solve stage alone (solver.timings, CPU; none for problem e, whose workers time "
          "stages in wall), the checks and diagnostics apart, over the better peer's whole CPU. greyfit default, "
          "foh only: substeps left to greyfit; no options: nothing given (inputs read as greyfit decides), "
          "each beside its pinned row.")


if __name__ == "__main__":
    main()
