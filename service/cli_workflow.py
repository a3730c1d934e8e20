"""`greyfit simulate` and `greyfit report`."""
from __future__ import annotations

import sys
from pathlib import Path


def _read(path: str) -> dict:
    from greyfit.service.json_parsing import loads_strict  # a key twice is an error, as over HTTP
    return loads_strict(sys.stdin.read() if path == "-" else Path(path).read_text())


def cmd_simulate(args) -> int:
    from greyfit.schemas.simulate import SimulateRequest
    from greyfit.service.json_parsing import validate_strict
    from greyfit.solvers.simulation.simulate import simulate_request
    result = simulate_request(validate_strict(SimulateRequest, _read(args.request)))
    print(result.model_dump_json(indent=2 if args.pretty else None))
    return 0


def cmd_report(args) -> int:
    from greyfit.schemas.report import ReportRequest
    from greyfit.service.json_parsing import validate_strict
    from greyfit.service.report import ReportDependencyMissing, write_report
    body = {"result": _read(args.result), "title": args.title}
    if args.request:
        body["request"] = _read(args.request)
    try:
        paths = write_report(validate_strict(ReportRequest, body), Path(args.out),
                             tuple(args.formats.split(",")))
    except ReportDependencyMissing as exc:
        print(f"greyfit: {exc}", file=sys.stderr)
        return 2
    for p in paths:
        print(p)
    return 0


def add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="simulate a model on experiments (SimulateRequest JSON); result on stdout")
    p.add_argument("request")
    p.add_argument("--pretty", action="store_true")
    p.set_defaults(func=cmd_simulate)


def add_report(sub) -> None:
    p = sub.add_parser("report", help="figures and one HTML page for a fit or discovery result")
    p.add_argument("result", help="FitResult or DiscoveryResult JSON")
    p.add_argument("--request", help="the request of the fit: measured data for the compare figures")
    p.add_argument("--out", required=True, help="directory for the figures and report.html")
    p.add_argument("--formats", default="png,svg", help="figure files to write: png,svg (default both)")
    p.add_argument("--title")
    p.set_defaults(func=cmd_report)
