"""`--data` and `--validation`: measurement files as the records of a request read from MODEL.json.

`greyfit fit MODEL.json --data run1.csv --data run2.parquet --validation run3.mat`: MODEL.json is a
request without `experiments`; each file becomes one record, its columns matched to the model's time,
inputs and outputs by name (solvers/data/files.py reads them; the options are schemas.files.FileColumns).
"""
from __future__ import annotations

import argparse
from typing import Any, Optional

from pydantic import ValidationError

from greyfit.solvers.errors import DataFileError

# the options of FileColumns as they are spelt on the command line
_OPTIONS = {"time": "--time", "sample_rate": "--sample-rate", "time_unit": "--time-unit", "columns": "--map",
            "scale": "--scale", "start": "--from", "stop": "--to", "decimate": "--decimate",
            "remove_means": "--remove-means"}


def add_file_options(p: argparse.ArgumentParser, validation: bool = True) -> None:
    """--data, --validation and how their columns are read."""
    g = p.add_argument_group("measurement files (REQUEST is then a request without experiments)")
    g.add_argument("--data", action="append", metavar="FILE", default=[],
                   help="a record to fit: .csv (with a header), .parquet or MATLAB .mat (v5 or v7.3); repeat for more")
    if validation:
        g.add_argument("--validation", action="append", metavar="FILE", default=[],
                       help="a record kept for validation (not fitted); repeat for more")
    g.add_argument("--time", metavar="COLUMN", help="the time column (default: t or time)")
    g.add_argument("--sample-rate", type=float, metavar="HZ", help="samples per second, for files without time")
    g.add_argument("--time-unit", choices=["s", "ms", "us", "ns", "min", "h"], default=None,
                   help="the unit of the time column (default s)")
    g.add_argument("--map", action="append", metavar="NAME=COLUMN", default=[],
                   help="the file's column for a model input or output whose name differs")
    g.add_argument("--scale", action="append", metavar="NAME=FACTOR", default=[],
                   help="multiply a column by FACTOR (units: 0.001 for mm into m)")
    g.add_argument("--from", dest="t_from", type=float, metavar="T0", help="keep the samples from T0 s on")
    g.add_argument("--to", dest="t_to", type=float, metavar="T1", help="keep the samples up to T1 s")
    g.add_argument("--decimate", type=int, metavar="K", help="keep every K-th sample (anti-alias filtered)")
    g.add_argument("--remove-means", action="store_true", help="subtract each input's and output's mean")


def file_columns(args) -> Any:
    """The FileColumns the options say (a DataFileError naming the option when one is malformed)."""
    from greyfit.schemas.files import FileColumns
    spec: dict[str, Any] = {"time": args.time, "sample_rate": args.sample_rate, "decimate": args.decimate,
                            "start": args.t_from, "stop": args.t_to,
                            "remove_means": args.remove_means, "columns": _pairs(args.map, "--map", str, "u=force"),
                            "scale": _pairs(args.scale, "--scale", float, "x=0.001")}
    if args.time_unit:
        spec["time_unit"] = args.time_unit
    try:
        return FileColumns.model_validate({k: v for k, v in spec.items() if v is not None})
    except ValidationError as exc:
        first = exc.errors()[0]
        option = _OPTIONS.get(str(first["loc"][0]) if first["loc"] else "", "--time/--sample-rate/--from/--to")
        raise DataFileError(f"{option}: {first['msg'].removeprefix('Value error, ')}") from None


def _pairs(items: list[str], option: str, kind, example: str) -> dict[str, Any]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise DataFileError(f"{option} {item!r}: write NAME=VALUE, e.g. {option} {example}")
        try:
            out[name.strip()] = kind(value.strip())
        except ValueError:
            raise DataFileError(f"{option} {item!r}: {value.strip()!r} is not a number") from None
    return out


def attach_files(body: Any, args, require_outputs: bool = True) -> Any:
    """The request with its records read from --data (and --validation) files; unchanged without them."""
    data, validation = args.data, getattr(args, "validation", [])
    if not data and not validation:
        given = [option for option, value in _given(args).items() if value]
        if given:
            raise DataFileError(f"{given[0]} says how --data files are read, and no --data file is given")
        return body
    if not isinstance(body, dict):
        return body   # the schema names what is wrong
    if "experiments" in body:
        raise DataFileError("the request has experiments and --data gives more: give the records one way "
                         "(a request without experiments, with --data files)")
    model = _model(body)
    if model is None:
        return body   # the request's validation names what is wrong with its model
    from greyfit.solvers.data.files import read_records
    spec = file_columns(args)
    body, problems = dict(body), []
    for key, paths, outputs_needed in (("experiments", data, require_outputs), ("validation", validation, False)):
        if not paths:
            continue
        try:
            body[key] = [e.model_dump(exclude_unset=True)
                         for e in read_records(paths, model, spec, outputs_needed)]
        except DataFileError as exc:   # every bad file named, the validation records' too
            problems.append(str(exc))
    if problems:
        raise DataFileError("\n".join(dict.fromkeys(problems)))
    return body


def _given(args) -> dict[str, Any]:
    return {"--time": args.time, "--sample-rate": args.sample_rate, "--time-unit": args.time_unit,
            "--map": args.map, "--scale": args.scale, "--from": args.t_from is not None,
            "--to": args.t_to is not None, "--decimate": args.decimate, "--remove-means": args.remove_means}


def _model(body: dict) -> Optional[Any]:
    """The request's model (or, for `simulate --result`, the result's), if it is a valid one."""
    from greyfit.schemas.model import Model
    raw = body.get("model")
    if raw is None and isinstance(body.get("fit_result"), dict):
        raw = body["fit_result"].get("model")
    try:
        return Model.model_validate(raw)
    except ValidationError:
        return None
