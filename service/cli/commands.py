"""`greyfit` command line: fit, discover, batch, serve, simulate, report, design.

Exit codes: 0 done; 1 a batch in which every request failed; 2 bad input (file, JSON, request) or a
fit that could not be built; 3 the result's quality is one that `--fail-on` names; 130 interrupted
(Ctrl-C); 141 the reader of stdout left (a pipe closed).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
from pathlib import Path
from typing import NoReturn

from pydantic import ValidationError

EXIT_BAD_INPUT = 2
EXIT_QUALITY = 3
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141   # 128 + SIGPIPE, what a shell reports for a writer whose reader left
FAIL_ON = {"failed": ("failed",), "suspect": ("suspect", "failed")}


def _read_json(path: str) -> dict:
    from greyfit.service.http.json_parsing import loads_strict  # a key twice is an error, as over HTTP
    text = sys.stdin.read() if path == "-" else Path(path).read_text()
    return loads_strict(text)


def _validation_message(exc: ValidationError) -> str:
    from greyfit.service.http.error_text import error_lines  # experiments[0].time, as over HTTP
    return error_lines(exc)


def emit(result, args) -> None:
    """The result as JSON on stdout, or its text report with --summary; JSON to --output too."""
    if getattr(args, "output", None):
        Path(args.output).write_text(result.model_dump_json(indent=2 if args.pretty else None) + "\n")
    if args.summary:
        print(result.report())
    elif not getattr(args, "output", None):
        print(result.model_dump_json(indent=2 if args.pretty else None))


def quality_exit(fit, args) -> int:
    """0, or 3 when the fit's quality is one `--fail-on` names (a message on stderr says why)."""
    from greyfit.schemas.text_report import effective_quality
    quality = effective_quality(fit)
    if args.fail_on and quality in FAIL_ON[args.fail_on]:
        print(f"greyfit: the result is {quality} (--fail-on {args.fail_on}): {fit.message}", file=sys.stderr)
        return EXIT_QUALITY
    return 0


def cmd_fit(args) -> int:
    from greyfit.schemas import FitRequest
    from greyfit.service.cli.files import attach_files
    from greyfit.service.http.json_parsing import validate_strict
    from greyfit.solvers.fit import fit_model
    body = attach_files(_read_json(args.request), args)
    if isinstance(body, dict) and isinstance(body.get("model"), dict) and \
            body["model"].get("kind") in ("transfer_function", "linearised_ode"):   # a frequency-response fit
        from greyfit.schemas.frequency import FrequencyFitRequest
        from greyfit.solvers.frequency import fit_frequency_response
        result = fit_frequency_response(validate_strict(FrequencyFitRequest, body))
    else:
        result = fit_model(validate_strict(FitRequest, body))
    emit(result, args)
    return quality_exit(result, args)


def cmd_discover(args) -> int:
    from greyfit.schemas.discovery import DiscoverRequest
    from greyfit.service.cli.files import attach_files
    from greyfit.service.cli.progress import DiscoveryProgress
    from greyfit.service.http.json_parsing import validate_strict
    from greyfit.solvers.discovery import discover
    request = validate_strict(DiscoverRequest, attach_files(_read_json(args.request), args))
    progress = DiscoveryProgress(sys.stderr, quiet=args.quiet)
    result = discover(request, progress=progress)
    progress.close()
    emit(result, args)
    return quality_exit(result.fit, args)


def add_output_options(p, what: str, fail_on: bool = True) -> None:
    """--pretty, --summary, --output (and --fail-on) as every result-making command has them."""
    p.add_argument("--pretty", action="store_true", help="indent the JSON result")
    p.add_argument("--summary", action="store_true",
                   help=f"print a text report of the {what} (parameters, metrics, warnings) instead of the JSON")
    p.add_argument("-o", "--output", metavar="FILE",
                   help="write the JSON result to FILE instead of stdout (with --summary: the report on stdout, "
                        "the JSON in FILE)")
    if fail_on:
        p.add_argument("--fail-on", choices=list(FAIL_ON), default=None,
                       help="exit 3 when the result's quality is failed (failed), or suspect or failed (suspect); "
                            "default: exit 0 whatever the quality")


class _Version(argparse.Action):
    """--version, the version read only when asked (importlib.metadata costs every command ~20 ms)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from greyfit import __version__
        print(f"greyfit {__version__}")   # on stdout, as argparse's own version action prints it
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    from greyfit.service.cli.files import add_file_options
    from greyfit.service.cli.suggest import SuggestingArgumentParser  # "did you mean" for options
    parser = SuggestingArgumentParser(prog="greyfit", description=__doc__,
                                      formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action=_Version, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p_fit = sub.add_parser("fit", help="fit one request; result JSON (or --summary) on stdout",
                           description="Fit one FitRequest (or a FrequencyFitRequest: model kind transfer_function "
                                       "or linearised_ode) and print the FitResult.")
    p_fit.add_argument("request", help="the request JSON file, or - for stdin (without experiments with --data)")
    add_output_options(p_fit, "fit")
    add_file_options(p_fit)
    p_fit.set_defaults(func=cmd_fit)
    p_disc = sub.add_parser("discover", help="fit, find missing effects, refit; result JSON (or --summary) on stdout",
                            description="Run a DiscoverRequest: fit the declared model, screen the effect library "
                                        "on its residual, confirm by refits. Progress goes to stderr.")
    p_disc.add_argument("request", help="the DiscoverRequest JSON file, or - for stdin (without experiments "
                                        "with --data)")
    add_output_options(p_disc, "discovery and its final fit")
    add_file_options(p_disc)
    p_disc.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    p_disc.set_defaults(func=cmd_discover)
    for extra in _extra_commands():
        extra(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The command line; `argv` None: this process is the program (the `greyfit` script, `python -m`),
    which then ends at once with the code (`_leave`); a list: a call from Python, which gets it back."""
    code = _main(argv)
    if argv is None:
        _leave(code)
    return code


def _main(argv: list[str] | None) -> int:
    try:
        code = _run(argv)
        sys.stdout.flush()   # here, not at exit: a reader that has left is answered below
        return code
    except KeyboardInterrupt:
        return _interrupted()
    except BrokenPipeError:
        # the reader of stdout has gone (`| head`): stdout to /dev/null, so that the flush at exit
        # does not raise again (the Python documentation's advice for SIGPIPE)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        _stop_compiles()
        return EXIT_BROKEN_PIPE


def _leave(code: int) -> NoReturn:
    """Exit once the exit handlers have run and the output is flushed, without the interpreter's
    teardown: freeing a fit's CasADi objects one by one took 1.3-2.2 s after the answer was printed
    (measured on the README's first fit), time in which the command looked hung. Nothing is lost:
    files are written and closed by then, and temporary folders are removed by exit handlers."""
    import atexit
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(code)


def _run(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    from greyfit.solvers.errors import DataFileError, FitError
    code = EXIT_BAD_INPUT
    try:
        code = args.func(args)
    except FileNotFoundError as exc:
        print(f"greyfit: no such file: {exc.filename}", file=sys.stderr)
    except json.JSONDecodeError as exc:
        print(f"greyfit: not valid JSON: {exc}", file=sys.stderr)
    except ValidationError as exc:
        if exc.title == "Settings":   # the service's environment, read at start
            lines = "\n".join(f"GREYFIT_{'_'.join(map(str, e['loc'])).upper()}: {e['msg']}" for e in exc.errors())
            print(f"greyfit: invalid setting in the environment:\n{lines}", file=sys.stderr)
        else:
            print(f"greyfit: invalid request:\n{_validation_message(exc)}", file=sys.stderr)
    except DataFileError as exc:   # one line per bad file, naming the file, the column and the row
        for line in str(exc).splitlines():
            print(f"greyfit: {line}", file=sys.stderr)
    except FitError as exc:
        print(f"greyfit: {type(exc).__name__}: {exc}", file=sys.stderr)
    _hand_over_compiles(getattr(args, "quiet", False))   # not after Ctrl-C: `_interrupted` stops them
    return code


def _interrupted() -> int:
    """Ctrl-C: one line, no traceback, exit 130 (128 + SIGINT, as a shell reports it); the builds
    begun in the background are stopped and their temporary files removed."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # a second Ctrl-C does not interrupt the clean-up
    print(f"{chr(10) if sys.stderr.isatty() else ''}greyfit: interrupted", file=sys.stderr)   # after a progress line
    _stop_compiles()
    return EXIT_INTERRUPTED


def _stop_compiles() -> None:
    """End the builds begun in the background (compilers killed, temporary folders removed)."""
    compiled = sys.modules.get("greyfit.solvers.dynamics.compiled")
    if compiled is not None:
        compiled.abandon_builds(1.0)


def _hand_over_compiles(quiet: bool) -> None:
    """A fit of a new model structure ran interpreted (or on tcc's code) while gcc built its
    libraries in the background: the answer is printed, so the builds go on in a detached process
    (solvers/dynamics/detached.py) that leaves them in the disk cache (`GREYFIT_CACHE_DIR`, default
    ~/.cache/greyfit) for the next command, and this one exits at once (it used to wait for them,
    up to two minutes, saying nothing)."""
    compiled = sys.modules.get("greyfit.solvers.dynamics.compiled")
    if compiled is None or not compiled.building_any():
        return
    sys.stdout.flush()
    from greyfit.solvers.dynamics.detached import hand_over
    handed = hand_over()
    if handed is not None and not quiet:
        pid, count = handed
        print(f"greyfit: {count} compiled-code build{'s' if count != 1 else ''} of this model go on in a "
              f"detached process (pid {pid}); the next run of this model finds them in the cache",
              file=sys.stderr)


def _extra_commands():
    from greyfit.service.cli.design import add_design
    from greyfit.service.cli.keys import add_keys
    from greyfit.service.cli.serve import add_batch, add_serve
    from greyfit.service.cli.workflow import add_report, add_simulate
    return [add_serve, add_batch, add_simulate, add_report, add_design, add_keys]


if __name__ == "__main__":
    raise SystemExit(main())
