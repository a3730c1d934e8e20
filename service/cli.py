"""`greyfit` command line: fit, discover, batch, serve, simulate, report."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from pydantic import ValidationError


def _read_json(path: str) -> dict:
    from greyfit.service.json_parsing import loads_strict  # a key twice is an error, as over HTTP
    text = sys.stdin.read() if path == "-" else Path(path).read_text()
    return loads_strict(text)


def _validation_message(exc: ValidationError) -> str:
    from greyfit.service.error_text import error_lines  # experiments[0].time, as over HTTP
    return error_lines(exc)


def cmd_fit(args) -> int:
    from greyfit.schemas import FitRequest
    from greyfit.service.json_parsing import validate_strict
    from greyfit.solvers.fit import fit_model
    body = _read_json(args.request)
    if isinstance(body, dict) and isinstance(body.get("model"), dict) and \
            body["model"].get("kind") in ("transfer_function", "linearised_ode"):   # a frequency-response fit
        from greyfit.schemas.frequency import FrequencyFitRequest
        from greyfit.solvers.frequency import fit_frequency_response
        result = fit_frequency_response(validate_strict(FrequencyFitRequest, body))
    else:
        result = fit_model(validate_strict(FitRequest, body))
    print(result.model_dump_json(indent=2 if args.pretty else None))
    return 0


def cmd_discover(args) -> int:
    from greyfit.schemas.discovery import DiscoverRequest
    from greyfit.service.json_parsing import validate_strict
    from greyfit.solvers.discovery import discover
    request = validate_strict(DiscoverRequest, _read_json(args.request))
    result = discover(request)
    print(result.model_dump_json(indent=2 if args.pretty else None))
    if args.summary:
        print(format_discovery(result), file=sys.stderr)
    return 0


def format_discovery(result) -> str:
    """A before/after table for people."""
    lines = [f"conclusion: {result.conclusion}", ""]
    if not result.before.success:
        lines += [f"the declared model's fit did not succeed (status: {result.before.status})", ""]
    lines.append(f"{'output':12s} {'data':10s} {'RMSE before':>12s} {'RMSE after':>12s} {'fit % before':>13s} "
                 f"{'fit % after':>12s}")
    rows = [("estimation", result.before, result.after)]
    if result.before.validation is not None and result.after.validation is not None:
        rows.append(("validation", result.before.validation, result.after.validation))
    for name in result.before.rmse:
        for label, b, a in rows:
            if name in b.rmse and name in a.rmse:
                lines.append(f"{name:12s} {label:10s} {b.rmse[name]:12.4g} {a.rmse[name]:12.4g} "
                             f"{b.fit_percent[name]:13.2f} {a.fit_percent[name]:12.2f}")
    lines.append(f"{'BIC':23s} {result.before.bic:12.1f} {result.after.bic:12.1f}")
    for step in result.steps:
        params = ", ".join(f"{p.name} = {p.value:.4g} ± {p.stderr:.2g}" if p.stderr else f"{p.name} = {p.value:.4g}"
                           for p in step.parameters)
        where = step.equation if step.equation.startswith("output") else f"d{step.equation}/dt"
        lines.append(f"+ {step.effect} in {where}: {step.term}  [{params}]  "
                     f"explains {100 * step.evidence.explained_variance:.0f} % of the "
                     f"{'output' if step.evidence.scored_on != 'equations' else 'equation'} residual, "
                     f"BIC -{step.evidence.bic_drop:.0f}" + ("  (specific to this record)" if step.record_specific else ""))
    for rej in result.rejected:
        lines.append(f"- not kept: {rej.effect} ({rej.term}): {rej.reason}: {rej.detail}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from greyfit.service.cli_suggest import SuggestingArgumentParser  # "did you mean" for options
    parser = SuggestingArgumentParser(prog="greyfit", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p_fit = sub.add_parser("fit", help="fit one request (JSON file or - for stdin); result JSON on stdout")
    p_fit.add_argument("request")
    p_fit.add_argument("--pretty", action="store_true")
    p_fit.set_defaults(func=cmd_fit)
    p_disc = sub.add_parser("discover", help="fit, find missing effects, refit; result JSON on stdout")
    p_disc.add_argument("request")
    p_disc.add_argument("--pretty", action="store_true")
    p_disc.add_argument("--summary", action="store_true", help="also print a before/after table on stderr")
    p_disc.set_defaults(func=cmd_discover)
    for extra in _extra_commands():
        extra(sub)
    args = parser.parse_args(argv)
    from greyfit.solvers.errors import FitError
    try:
        return args.func(args)
    except FileNotFoundError as exc:
        print(f"greyfit: no such file: {exc.filename}", file=sys.stderr)
    except json.JSONDecodeError as exc:
        print(f"greyfit: not valid JSON: {exc}", file=sys.stderr)
    except ValidationError as exc:
        print(f"greyfit: invalid request:\n{_validation_message(exc)}", file=sys.stderr)
    except FitError as exc:
        print(f"greyfit: {type(exc).__name__}: {exc}", file=sys.stderr)
    return 2


def _extra_commands():
    from greyfit.service.cli_service import add_batch, add_serve
    from greyfit.service.cli_workflow import add_report, add_simulate
    return [add_serve, add_batch, add_simulate, add_report]


if __name__ == "__main__":
    raise SystemExit(main())
