"""`greyfit design`: the input of the next experiment, from a DesignRequest (or a fit result and limits)."""
from __future__ import annotations

import sys
from pathlib import Path


def _read(path: str) -> dict:
    from greyfit.service.http.json_parsing import loads_strict  # a key twice is an error, as over HTTP
    return loads_strict(sys.stdin.read() if path == "-" else Path(path).read_text())


def design_body(args) -> dict:
    """The DesignRequest: the file as it is, with --result's fit result (estimates, covariance, model) added."""
    body = _read(args.request)
    if args.result and isinstance(body, dict):
        body["fit_result"] = _read(args.result)
    if args.criterion and isinstance(body, dict):
        body["criterion"] = args.criterion
    return body


def cmd_design(args) -> int:
    from greyfit.schemas.design import DesignRequest
    from greyfit.service.cli.commands import emit
    from greyfit.service.http.json_parsing import validate_strict
    from greyfit.solvers.design import design_experiment
    request = validate_strict(DesignRequest, design_body(args))
    result = design_experiment(request)
    emit(result, args)
    return _write_report(result, request, args.report) if args.report else 0


def _write_report(result, request, out: str) -> int:
    """The design's page (designed input, predicted outputs, predicted gain) written to `out`."""
    from greyfit.schemas.report import ReportRequest
    from greyfit.service.report.page import ReportDependencyMissing, write_report
    try:
        paths = write_report(ReportRequest(result=result, request=request), Path(out), ("png",))
    except ReportDependencyMissing as exc:
        print(f"greyfit: {exc}", file=sys.stderr)
        return 2
    print(f"greyfit: report written to {paths[-1]}", file=sys.stderr)
    return 0


def add_design(sub) -> None:
    from greyfit.service.cli.commands import add_output_options
    p = sub.add_parser("design", help="design the next experiment's input; result JSON (or --summary) on stdout",
                       description="Design an input signal (DesignRequest): D-, A- or E-optimal for the parameters' "
                                   "intervals, or T-optimal to tell rival models apart. The result's `experiment` "
                                   "is the input to apply.")
    p.add_argument("request", help="the DesignRequest JSON file, or - for stdin")
    p.add_argument("--result", metavar="RESULT",
                   help="a FitResult JSON: its estimates, covariance and model are designed for (the request then "
                        "needs only the limits, outputs and duration)")
    p.add_argument("--criterion", choices=["D", "A", "E", "T"], help="override the request's criterion")
    p.add_argument("--report", metavar="DIR",
                   help="also write the design's report (report.html and PNG figures: the designed input beside "
                        "the baseline's, the predicted outputs, the predicted gain) to DIR")
    add_output_options(p, "design", fail_on=False)
    p.set_defaults(func=cmd_design)
