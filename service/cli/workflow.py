"""`greyfit simulate` and `greyfit report`."""
from __future__ import annotations

import sys
from pathlib import Path

# what a SimulateRequest takes from a fit (or discover) request given with --result: its records
SIMULATE_KEYS = ("experiments", "options", "initial_states", "parameters", "horizon", "estimate_window")


def _read(path: str) -> dict:
    from greyfit.service.http.json_parsing import loads_strict  # a key twice is an error, as over HTTP
    return loads_strict(sys.stdin.read() if path == "-" else Path(path).read_text())


def simulate_body(args) -> dict:
    """The SimulateRequest: the file as it is, or with --result, its records and the result's model."""
    from greyfit.service.cli.files import attach_files
    body = _read(args.request)
    if not args.result:
        return attach_files(body, args, require_outputs=False)
    if not isinstance(body, dict):
        return body   # the schema names what is wrong
    body = {k: v for k, v in body.items() if k in SIMULATE_KEYS}
    body["fit_result"] = _read(args.result)
    return attach_files(body, args, require_outputs=False)


def cmd_simulate(args) -> int:
    from greyfit.schemas.simulate import SimulateRequest
    from greyfit.service.cli.commands import emit
    from greyfit.service.http.json_parsing import validate_strict
    from greyfit.solvers.simulation.simulate import simulate_request
    result = simulate_request(validate_strict(SimulateRequest, simulate_body(args)))
    emit(result, args)
    return 0


def cmd_report(args) -> int:
    from greyfit.schemas.report import ReportRequest
    from greyfit.service.http.json_parsing import validate_strict
    from greyfit.service.report.page import ReportDependencyMissing, write_report
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
    from greyfit.service.cli.commands import add_output_options
    from greyfit.service.cli.files import add_file_options
    p = sub.add_parser("simulate", help="simulate a model on experiments; result JSON (or --summary) on stdout",
                       description="Simulate a SimulateRequest; or, with --result, the records of any request "
                                   "file (its experiments) with the model and estimates a fit result carries.")
    p.add_argument("request", help="SimulateRequest JSON (or with --result: any JSON with `experiments`, "
                                   "e.g. a FitRequest), or - for stdin")
    p.add_argument("--result", metavar="RESULT",
                   help="a FitResult or DiscoveryResult JSON: its model, estimates and initial states are used "
                        "(the request then needs only the records)")
    add_output_options(p, "simulation", fail_on=False)
    add_file_options(p, validation=False)
    p.set_defaults(func=cmd_simulate)


def add_report(sub) -> None:
    p = sub.add_parser("report", help="figures and one HTML page for a fit, frequency-fit or discovery result",
                       description="Draw the figures of a result and write them with report.html into --out. "
                                   "The measured data for the compare figures come from --request, else from "
                                   "the result's traces (return_traces); a frequency fit needs neither.")
    p.add_argument("result", help="FitResult or DiscoveryResult JSON (as `greyfit fit` or `discover` wrote it)")
    p.add_argument("--request", help="the request of the fit (FitRequest, DiscoverRequest or FrequencyFitRequest): "
                                     "its measured data for the compare figures")
    p.add_argument("-o", "--out", required=True, metavar="DIR",
                   help="directory for the figures and report.html (made if missing)")
    p.add_argument("--formats", default="png,svg", help="figure files to write: png,svg (default both)")
    p.add_argument("--title", help="the page's title (default: greyfit fit report / discovery report)")
    p.set_defaults(func=cmd_report)
