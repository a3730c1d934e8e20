"""Measurement files (CSV, Parquet, MATLAB .mat v5 and v7.3) and DataFrames read into records.

The readers are well-kept libraries, loaded only when a file of their kind is read (the `files`
extra: pandas for CSV, pandas with pyarrow for Parquet, scipy for .mat v5, h5py for .mat v7.3).
Columns are matched to the model's names by the header; every problem is one `DataFileError` line
naming the file, the column and the row (and, for a CSV, the line), so that a user can open the file
at that place.
"""
from __future__ import annotations

import importlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
from pydantic import ValidationError

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.files import TIME_UNITS, FileColumns
from greyfit.schemas.limits import MAX_NAME_LENGTH
from greyfit.schemas.model import Model
from greyfit.schemas.online import measured_output_inputs
from greyfit.solvers.errors import DataFileError

SUFFIXES = (".csv", ".txt", ".parquet", ".pq", ".mat")
TIME_NAMES = ("t", "time")
# `x [m]`, `x (m)`: a name and its unit, as loggers and spreadsheets write headers
_UNIT_SUFFIX = re.compile(r"^(?P<name>.*?)\s*(?:\[(?P<u1>[^\]]*)\]|\((?P<u2>[^)]*)\))\s*$")
_MISSING_TEXT = {"", "nan", "na", "null", "none", "n/a"}


@dataclass
class Table:
    """The columns of one file as read (any dtype); `csv` says whether row r sits on line r + 2."""

    label: str
    columns: dict[str, np.ndarray]
    csv: bool = False

    def where(self, column: str, row: Optional[int] = None) -> str:
        """`run1.csv: column 'x', row 12 (line 13)`, rows counted from 1 below the header.

        Parameters
        ----------
        column : str
            The column's name.
        row : int, optional
            The row (from 0); None names the column only.

        Returns
        -------
        str
            The place, for an error line.
        """
        at = f"{self.label}: column '{column}'"
        if row is None:
            return at
        return at + f", row {row + 1}" + (f" (line {row + 2})" if self.csv else "")


def _library(module: str, what: str) -> Any:
    """The reader's library, or one line naming the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise DataFileError(f"reading {what} needs {module.split('.')[0]}: pip install 'greyfit[files]'") from None


def read_table(path: str | Path, label: Optional[str] = None) -> Table:
    """Read a measurement file into its columns, by its suffix.

    Parameters
    ----------
    path : str or Path
        A `.csv` (or `.txt`) with a header line, a `.parquet`, or a MATLAB `.mat` (v5 or v7.3).
    label : str, optional
        How messages name the file (default: `path` as given).

    Returns
    -------
    Table
        Column name -> values as stored.

    Raises
    ------
    DataFileError
        No such file, an unknown suffix, a file its reader cannot read, or a missing reader.
    """
    path = Path(path)
    label = label or str(path)
    suffix = Path(label).suffix.lower()   # the user's name for the file says its kind
    if suffix not in SUFFIXES:
        raise DataFileError(f"{label}: unknown kind of file '{suffix}'; greyfit reads {', '.join(SUFFIXES)}")
    if not path.is_file():
        raise DataFileError(f"{label}: no such file")
    try:
        if suffix == ".mat":
            return _read_mat(path, label)
        pd = _library("pandas", f"{suffix} files")
        if suffix in (".csv", ".txt"):
            # the numbers exactly as written: pandas 3 parses so by default, pandas 2 when asked (its default
            # parser may miss the last digit); a .txt's separator (commas, tabs, spaces) is sniffed
            exact = {} if int(pd.__version__.split(".")[0]) >= 3 else {"float_precision": "round_trip"}
            how = {"sep": None, "engine": "python"} if suffix == ".txt" else {"sep": ",", **exact}
            frame = pd.read_csv(path, skip_blank_lines=False, skipinitialspace=True, **how)
            return Table(label, _frame_columns(frame), csv=True)
        _library("pyarrow", "Parquet files")
        return Table(label, _frame_columns(pd.read_parquet(path)))
    except DataFileError:
        raise
    except Exception as exc:   # the library's own words for a file it cannot read: one line
        said = (str(exc).splitlines() or ["no detail"])[0].replace(str(path), label)   # not where it is stored
        raise DataFileError(f"{label}: cannot be read as {suffix} ({type(exc).__name__}: {said})") from None


def table_from_dataframe(frame: Any, label: str = "DataFrame") -> Table:
    """A pandas DataFrame's columns (a named index, e.g. a time index, counts as a column).

    Parameters
    ----------
    frame : pandas.DataFrame
        The frame.
    label : str
        Names it in errors.

    Returns
    -------
    Table
        Its columns by name.
    """
    return Table(label, _frame_columns(frame))


def _frame_columns(frame: Any) -> dict[str, np.ndarray]:
    index = frame.index
    if index.name is not None or index.dtype.kind in "mM":   # a named or a time index is a column
        frame = frame.reset_index(names=index.name if index.name is not None else "time")
    return {str(name).strip(): frame[name].to_numpy() for name in frame.columns}


def _read_mat(path: Path, label: str) -> Table:
    """A .mat file's vectors (and a struct's, as `struct.field`); v7.3 files are HDF5."""
    with open(path, "rb") as fh:
        header = fh.read(128)
    if header.startswith(b"MATLAB 7.3"):
        h5py = _library("h5py", "MATLAB v7.3 files")
        columns: dict[str, np.ndarray] = {}
        with h5py.File(path, "r") as f:
            f.visititems(lambda name, obj: _h5_vector(columns, name, obj, h5py))
        return Table(label, columns)
    sio = _library("scipy.io", "MATLAB .mat files")
    content = sio.loadmat(path, squeeze_me=True, simplify_cells=True)
    columns = {}
    _mat_vectors(columns, "", {k: v for k, v in content.items() if not k.startswith("__")})
    return Table(label, columns)


def _mat_vectors(columns: dict[str, np.ndarray], prefix: str, content: dict) -> None:
    for name, value in content.items():
        if isinstance(value, dict):   # a struct: its fields
            _mat_vectors(columns, f"{prefix}{name}.", value)
        elif isinstance(value, np.ndarray) and value.ndim == 1:
            columns[prefix + name] = value


def _h5_vector(columns: dict[str, np.ndarray], name: str, obj: Any, h5py: Any) -> None:
    # MATLAB writes an N-vector as an (1, N) or (N, 1) dataset; text (uint16 with MATLAB_class char) and
    # the #refs# group of cell arrays are not signals
    if name.startswith("#") or obj.attrs.get("MATLAB_class") in (b"char", "char"):
        return
    if isinstance(obj, h5py.Dataset) and obj.dtype.kind in "fiub" and obj.ndim == 2 and 1 in obj.shape:
        columns[name.replace("/", ".")] = np.asarray(obj[()]).ravel()


def find_column(table: Table, wanted: str) -> Optional[str]:
    """The table's column called `wanted`, or written `wanted [unit]` / `wanted (unit)`.

    Parameters
    ----------
    table : Table
        The file's columns.
    wanted : str
        The model's name.

    Returns
    -------
    str or None
        The column's name, or None where none matches.
    """
    if wanted in table.columns:
        return wanted
    for column in table.columns:
        match = _UNIT_SUFFIX.match(column)
        if match and match.group("name") == wanted:
            return column
    return None


def numeric_column(table: Table, column: str, complete: bool) -> np.ndarray:
    """The column as finite floats, NaN where a sample is missing (allowed unless `complete`).

    Raises
    ------
    DataFileError
        A cell that is not a number, not finite, or missing where `complete`; the row is named.

    Parameters
    ----------
    table : Table
        The file's columns.
    column : str
        The column's name.
    complete : bool
        Whether every sample must be present (inputs, time).

    Returns
    -------
    numpy.ndarray
        The values.
    """
    raw = table.columns[column]
    if raw.size == 0:
        return np.zeros(0)
    if raw.dtype.kind in "mM":   # datetimes, time deltas: seconds since the first sample
        values = (raw - raw[0]) / np.timedelta64(1, "ns") * 1e-9
    elif raw.dtype.kind in "fiub":
        values = raw.astype(float)
    else:
        values = _numbers_in_text(table, column, raw)
    bad = np.flatnonzero(np.isinf(values))
    if bad.size:
        raise DataFileError(f"{table.where(column, int(bad[0]))}: {raw[bad[0]]} is not a finite number")
    missing = np.flatnonzero(np.isnan(values))
    if complete and missing.size:
        raise DataFileError(f"{table.where(column, int(missing[0]))}: the cell is empty; this column "
                            "must be complete (trim the record, or fill the gap)")
    return values


def _numbers_in_text(table: Table, column: str, raw: np.ndarray) -> np.ndarray:
    """Text cells as numbers; empty and NaN/NA cells missing; the first other text is an error."""
    text = np.array([("" if v is None else str(v)).strip() for v in raw], dtype=object)
    missing = np.array([s.lower() in _MISSING_TEXT for s in text], dtype=bool)
    values = np.full(text.size, np.nan)
    for i in np.flatnonzero(~missing):
        try:
            values[i] = float(text[i])
        except ValueError:
            raise DataFileError(f"{table.where(column, int(i))}: '{text[i]}' is not a number") from None
    return values


def record_from_table(table: Table, inputs: Sequence[str], outputs: Sequence[str], spec: FileColumns,
                      name: str, require_outputs: bool = True) -> Experiment:
    """The record of the model's `inputs` and `outputs` in `table`, as `spec` says to read it.

    Parameters
    ----------
    table : Table
        The file's columns.
    inputs, outputs : sequence of str
        The model's input and (measured) output names.
    spec : FileColumns
        Time column or sample rate, name mapping, units, segment, decimation, mean removal.
    name : str
        The record's name in results (a file's stem).
    require_outputs : bool
        Whether every output must be in the file (fits); a simulation takes the outputs there are.

    Returns
    -------
    Experiment
        Time in seconds, the series scaled as `spec.scale` says, `preprocess` set from `spec`.

    Raises
    ------
    DataFileError
        A column not found, a cell that is not a finite number, a gap in time or an input, a time
        that does not increase; one line naming the file, the column and the row.
    """
    _check_names(inputs, outputs, spec)
    time = _time(table, spec)
    series = {"inputs": _series(table, inputs, "input", spec, time.size, required=True),
              "outputs": _series(table, outputs, "output", spec, time.size, required=require_outputs)}
    try:
        return Experiment(name=name, time=time.tolist(), inputs=series["inputs"], outputs=series["outputs"],
                          preprocess=spec.preprocess(float(time[0]), float(time[-1])))
    except ValidationError as exc:   # e.g. more samples than a record may hold
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"][:2])
        raise DataFileError(f"{table.label}: {where}: {first['msg']}") from None


def _series(table: Table, names: Sequence[str], kind: str, spec: FileColumns, n: int,
            required: bool) -> dict[str, list]:
    """The model's inputs (complete) or outputs (a missing sample is None) found in the table, scaled."""
    out = {}
    for model_name in names:
        wanted = spec.columns.get(model_name, model_name)
        column = find_column(table, wanted)
        if column is None:
            if not required and model_name not in spec.columns:
                continue
            raise DataFileError(_not_found(table, wanted, f"model {kind} {model_name}",
                                           f"map it with --map {model_name}=COLUMN (`columns`)"))
        values = numeric_column(table, column, complete=kind == "input")
        if values.size != n:
            raise DataFileError(f"{table.where(column)}: {values.size} values, time has {n}")
        values = values * spec.scale.get(model_name, 1.0)
        out[model_name] = [None if v != v else v for v in values.tolist()]   # NaN: a missing sample
    return out


def _check_names(inputs: Sequence[str], outputs: Sequence[str], spec: FileColumns) -> None:
    unknown = sorted((set(spec.columns) | set(spec.scale)) - set(inputs) - set(outputs))
    if unknown:
        raise DataFileError(f"--map/--scale (`columns`/`scale`): '{unknown[0]}' is not an input or output of the "
                            f"model (inputs: {list(inputs)}, outputs: {list(outputs)})")


def _time(table: Table, spec: FileColumns) -> np.ndarray:
    """The time grid in seconds: the time column, or i / sample_rate; strictly increasing."""
    if spec.sample_rate is not None:
        rows = max((v.size for v in table.columns.values()), default=0)
        if rows < 2:
            raise DataFileError(f"{table.label}: {rows} row(s); a record needs at least 2")
        return np.arange(rows) / spec.sample_rate
    wanted = [spec.time] if spec.time is not None else list(TIME_NAMES)
    found = [c for c in (find_column(table, w) for w in wanted) if c is not None]
    if not found:
        raise DataFileError(_not_found(table, wanted[0], "time", "name the time column with --time (`time`), "
                                       "or give the sample rate with --sample-rate (`sample_rate`)"))
    column = found[0]
    t = numeric_column(table, column, complete=True) * TIME_UNITS[spec.time_unit]
    if t.size < 2:
        raise DataFileError(f"{table.where(column)}: {t.size} sample(s); a record needs at least 2")
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise DataFileError(f"{table.where(column, i)}: time {t[i]:g} s does not increase (the row before "
                            f"has {t[i - 1]:g} s); time must increase strictly")
    return t


def _not_found(table: Table, wanted: str, what: str, fix: str) -> str:
    shown = ", ".join(list(table.columns)[:12]) + (", ..." if len(table.columns) > 12 else "")
    where = f"{table.where(wanted)}, header" + (" (line 1)" if table.csv else "")
    return f"{where}: no such column ({what}); the file has {shown or 'no columns'}: {fix}"



def model_names(model: Model) -> tuple[list[str], list[str]]:
    """The inputs a file must hold (not those an ARMAX predictor reads from an output) and the outputs.

    Parameters
    ----------
    model : Model
        The model.

    Returns
    -------
    tuple of (list of str, list of str)
        The inputs and the outputs a file is read for.
    """
    fed = measured_output_inputs(model.template)
    return [u for u in model.inputs if u not in fed], list(model.measured_outputs())


def read_records(paths: Sequence[str | Path], model: Model, spec: FileColumns, require_outputs: bool = True,
                 labels: Optional[Sequence[str]] = None) -> list[Experiment]:
    """One record per file, named by the file's stem, its columns matched to `model`'s names.

    Parameters
    ----------
    paths : sequence of str or Path
        The measurement files.
    model : Model
        Whose inputs and outputs the files hold.
    spec : FileColumns
        How the columns are read (the same for every file).
    require_outputs : bool
        Whether every output must be in each file.
    labels : sequence of str, optional
        How messages and record names call the files (default: the paths as given).

    Returns
    -------
    list of Experiment

    Raises
    ------
    DataFileError
        One line per bad file (every file is read, so that all are named at once).
    """
    inputs, outputs = model_names(model)
    _check_names(inputs, outputs, spec)
    labels = list(labels) if labels is not None else [str(p) for p in paths]
    records, problems = [], []
    for path, label in zip(paths, labels):
        try:
            table = read_table(path, label)
            records.append(record_from_table(table, inputs, outputs, spec, record_name(label), require_outputs))
        except DataFileError as exc:
            problems.append(str(exc))
    if problems:
        raise DataFileError("\n".join(problems))
    return records


def record_name(label: str) -> str:
    """The file's stem as a record name (letters, digits and _ only).

    Parameters
    ----------
    label : str
        The file's name or label.

    Returns
    -------
    str
        A valid record name.
    """
    stem = re.sub(r"[^A-Za-z0-9_]", "_", Path(label).stem) or "record"
    return (stem if not stem[0].isdigit() else f"r_{stem}")[:MAX_NAME_LENGTH]
