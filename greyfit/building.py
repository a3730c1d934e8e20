"""A model and its records built in Python: `Parameter`, `Model`, `Experiment` (with file readers).

They are the request schemas themselves (a `greyfit.Model` is a `greyfit.schemas.Model`), with what a
Python user writes by hand made short: a parameter's name and value by position, numpy arrays for
series, and records read from measurement files by the model's names::

    import greyfit
    model = greyfit.Model(states=["x", "v"], inputs=["u"],
                          parameters=[greyfit.Parameter("m", 2.0, fixed=True),
                                      greyfit.Parameter("c", 0.3, lower=0, unit="N s/m"),
                                      greyfit.Parameter("k", 2.0, lower=0, unit="N/m")],
                          equations={"x": "v", "v": "(u - c*v - k*x)/m"})
    record = greyfit.Experiment.from_csv("examples/msd.csv", model)
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Sequence, Union

from greyfit.schemas.experiment import Experiment as ExperimentSchema
from greyfit.schemas.files import FileColumns
from greyfit.schemas.model import Model
from greyfit.schemas.model import Parameter as ParameterSchema

__all__ = ["Model", "Parameter", "Experiment"]


class Parameter(ParameterSchema):
    """An unknown constant: `Parameter("k", 2.0, lower=0, unit="N/m")` (lmfit's order: name, value,
    bounds); `fixed=True` keeps it at `value`. Every field of `greyfit.schemas.Parameter` is taken."""

    def __init__(self, name: str, value: float, lower: Optional[float] = None, upper: Optional[float] = None,
                 unit: Optional[str] = None, **fields: Any):
        given: dict[str, Any] = {"lower": lower, "upper": upper, "unit": unit}
        # the bounds and unit left out stay unset (not null), as in a request written by hand
        fields.update({k: v for k, v in given.items() if v is not None})
        super().__init__(name=name, value=value, **fields)


ModelLike = Union[Model, dict, Any]


class Experiment(ExperimentSchema):
    """One record: `Experiment(time=t, inputs={"u": u}, outputs={"x": x})` (lists or numpy arrays), or
    read from a file by the model's names with `from_csv`, `from_parquet`, `from_mat`, `from_dataframe`.

    The readers take the model (or a request carrying one) whose inputs and outputs the file holds,
    or `inputs=` and `outputs=` lists, and the options of `greyfit.schemas.files.FileColumns`:
    `time` (the time column; default t or time) or `sample_rate`, `time_unit`, `columns` (model name
    -> column where they differ), `scale` (model name -> factor), `start`/`stop` (a segment, seconds),
    `decimate`, `remove_means`. A bad file raises `greyfit.solvers.errors.DataFileError`, one line
    naming the file, the column and the row.
    """

    @classmethod
    def from_file(cls, path: Union[str, Path], model: ModelLike = None, *, inputs: Optional[Sequence[str]] = None,
                  outputs: Optional[Sequence[str]] = None, name: Optional[str] = None,
                  require_outputs: bool = True, **columns: Any) -> "Experiment":
        """A record from a .csv, .parquet or .mat file (by its suffix)."""
        from greyfit.solvers.data.files import read_table, record_name
        return cls._from_table(read_table(path), model, inputs, outputs, name or record_name(str(path)),
                               require_outputs, columns)

    @classmethod
    def from_csv(cls, path: Union[str, Path], model: ModelLike = None, **options: Any) -> "Experiment":
        """A record from a CSV file with a header line (needs pandas: the `files` extra)."""
        return cls.from_file(_suffixed(path, (".csv", ".txt")), model, **options)

    @classmethod
    def from_parquet(cls, path: Union[str, Path], model: ModelLike = None, **options: Any) -> "Experiment":
        """A record from a Parquet file (needs pandas and pyarrow: the `files` extra)."""
        return cls.from_file(_suffixed(path, (".parquet", ".pq")), model, **options)

    @classmethod
    def from_mat(cls, path: Union[str, Path], model: ModelLike = None, **options: Any) -> "Experiment":
        """A record from a MATLAB .mat file, v5 (scipy) or v7.3 (h5py): its vectors are the columns,
        a struct's fields are `struct.field`."""
        return cls.from_file(_suffixed(path, (".mat",)), model, **options)

    @classmethod
    def from_dataframe(cls, frame: Any, model: ModelLike = None, *, inputs: Optional[Sequence[str]] = None,
                       outputs: Optional[Sequence[str]] = None, name: str = "experiment",
                       require_outputs: bool = True, **columns: Any) -> "Experiment":
        """A record from a pandas DataFrame (a named index, e.g. time, counts as a column)."""
        from greyfit.solvers.data.files import table_from_dataframe
        return cls._from_table(table_from_dataframe(frame), model, inputs, outputs, name, require_outputs,
                               columns)

    @classmethod
    def _from_table(cls, table, model: ModelLike, inputs, outputs, name: str, require_outputs: bool,
                    columns: dict) -> "Experiment":
        from greyfit.solvers.data.files import model_names, record_from_table
        if model is not None:
            inputs, outputs = model_names(_as_model(model))
        elif inputs is None or outputs is None:
            raise TypeError("give the model (or a request carrying one), or inputs= and outputs= lists")
        record = record_from_table(table, list(inputs), list(outputs), FileColumns(**columns), name,
                                   require_outputs)
        return cls.model_validate(record.model_dump(exclude_unset=True))


def _as_model(model: ModelLike) -> Model:
    """A Model from a Model, a dict, or anything with a `model` (a request, a result)."""
    if isinstance(model, Model):
        return model
    if isinstance(model, dict):
        return Model.model_validate(model.get("model", model))
    return _as_model(model.model)


def _suffixed(path: Union[str, Path], suffixes: tuple[str, ...]) -> Path:
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"{path}: expected a {' or '.join(suffixes)} file")
    return path
