"""Measurement files read into records (solvers/data/files.py): every format gives the numbers of the
JSON request to the last digit; columns by name, units, segments; one line per bad file."""
import json
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import scipy.io

from greyfit.building import Experiment
from greyfit.schemas.files import FileColumns
from greyfit.schemas.fit import FitRequest
from greyfit.solvers.data import files
from greyfit.solvers.errors import DataFileError

ROOT = Path(__file__).resolve().parents[2]
REQUEST = json.loads((ROOT / "examples" / "msd_request.json").read_text())
RECORD = REQUEST["experiments"][0]
MODEL = FitRequest.model_validate(REQUEST).model


def columns() -> dict[str, np.ndarray]:
    return {"t": np.array(RECORD["time"]), "u": np.array(RECORD["inputs"]["u"]),
            "x": np.array(RECORD["outputs"]["x"]), "v": np.array(RECORD["outputs"]["v"])}


def same_numbers(exp: Experiment) -> None:
    assert exp.time == RECORD["time"]
    assert exp.inputs == RECORD["inputs"] and exp.outputs == RECORD["outputs"]


def test_the_example_csv_is_the_json_request_record():
    same_numbers(Experiment.from_csv(ROOT / "examples" / "msd.csv", MODEL))


def test_parquet_and_mat_v5_and_v73_read_to_the_same_numbers(tmp_path):
    pd.DataFrame(columns()).to_parquet(tmp_path / "run.parquet")
    scipy.io.savemat(tmp_path / "v5.mat", {k: v.reshape(-1, 1) for k, v in columns().items()})
    with h5py.File(tmp_path / "v73.mat", "w", userblock_size=512) as f:   # MATLAB's layout: (1, N) doubles
        for name, values in columns().items():
            f.create_dataset(name, data=values.reshape(1, -1))
    with open(tmp_path / "v73.mat", "r+b") as f:
        f.write(b"MATLAB 7.3 MAT-file, written by the test".ljust(116))
    same_numbers(Experiment.from_parquet(tmp_path / "run.parquet", MODEL))
    same_numbers(Experiment.from_mat(tmp_path / "v5.mat", MODEL))
    same_numbers(Experiment.from_mat(tmp_path / "v73.mat", MODEL))


def test_a_struct_in_a_mat_file_and_names_that_differ(tmp_path):
    c = columns()
    scipy.io.savemat(tmp_path / "log.mat", {"log": {"time_ms": c["t"] * 1000, "force": c["u"], "pos_mm": c["x"] * 1000,
                                                    "vel": c["v"]}})
    exp = Experiment.from_mat(tmp_path / "log.mat", MODEL, time="log.time_ms", time_unit="ms",
                              columns={"u": "log.force", "x": "log.pos_mm", "v": "log.vel"}, scale={"x": 1e-3})
    assert np.allclose(exp.time, RECORD["time"], rtol=1e-15, atol=1e-15)
    assert np.allclose(exp.outputs["x"], RECORD["outputs"]["x"], rtol=1e-15)
    assert exp.inputs == RECORD["inputs"]


def test_a_dataframe_with_a_time_index_units_in_headers_and_a_sample_rate():
    c = columns()
    frame = pd.DataFrame({"u [N]": c["u"], "x (m)": c["x"], "v": c["v"]}, index=pd.Index(c["t"], name="time"))
    same_numbers(Experiment.from_dataframe(frame, MODEL))
    by_rate = Experiment.from_dataframe(frame.reset_index(drop=True), MODEL, sample_rate=20.0)
    assert np.allclose(by_rate.time, RECORD["time"], atol=1e-12) and by_rate.outputs == RECORD["outputs"]
    logged = frame.set_axis(pd.to_datetime("2026-12-07 09:00") + pd.to_timedelta(c["t"], unit="s"))  # a logger's clock
    assert np.allclose(Experiment.from_dataframe(logged, MODEL).time, RECORD["time"], atol=1e-9)


def test_segment_decimation_and_means_are_the_records_preprocess_and_said_in_the_result():
    import greyfit
    exp = Experiment.from_csv(ROOT / "examples" / "msd.csv", MODEL, start=1.0, stop=8.0, decimate=2,
                              remove_means=True)
    assert exp.preprocess.window == (1.0, 8.0) and exp.preprocess.decimate == 2
    assert exp.preprocess.detrend == "mean"
    only_start = Experiment.from_csv(ROOT / "examples" / "msd.csv", MODEL, start=2.0)
    assert only_start.preprocess.window == (2.0, RECORD["time"][-1])
    result = greyfit.fit(model=MODEL, experiments=[only_start], method="multiple_shooting", options={"substeps": 2})
    done = result.preprocessing.experiments[0]
    assert done.window == (2.0, RECORD["time"][-1]) and done.samples_in == 201 and done.samples_out == 161
    assert result.parameters["k"].value == pytest.approx(5.0, rel=0.01)   # the record was made with k = 5


def _csv(tmp_path, name: str, edit) -> Path:
    lines = (ROOT / "examples" / "msd.csv").read_text().splitlines()
    edit(lines)
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _cell(lines: list[str], line: int, col: int, value: str) -> None:
    cells = lines[line - 1].split(",")
    cells[col] = value
    lines[line - 1] = ",".join(cells)


@pytest.mark.parametrize("name, edit, fragments", [
    ("missing.csv", lambda ls: ls.__setitem__(slice(None), [",".join(c for j, c in enumerate(x.split(",")) if j != 1)
                                                            for x in ls]),
     ["missing.csv: column 'u', header (line 1): no such column (model input u)", "--map u=COLUMN"]),
    ("text.csv", lambda ls: _cell(ls, 13, 2, "abc"), ["text.csv: column 'x', row 12 (line 13): 'abc' is not a number"]),
    ("back.csv", lambda ls: _cell(ls, 41, 0, "1.5"),
     ["back.csv: column 't', row 40 (line 41): time 1.5 s does not increase (the row before has 1.9 s)"]),
    ("gap.csv", lambda ls: _cell(ls, 30, 1, ""), ["gap.csv: column 'u', row 29 (line 30): the cell is empty"]),
    ("inf.csv", lambda ls: _cell(ls, 7, 3, "inf"), ["inf.csv: column 'v', row 6 (line 7): inf is not a finite"]),
])
def test_a_bad_file_is_one_line_naming_file_column_and_row(tmp_path, name, edit, fragments):
    with pytest.raises(DataFileError) as info:
        files.read_records([_csv(tmp_path, name, edit)], MODEL, FileColumns())
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message


def test_every_bad_file_is_named_and_a_missing_output_sample_is_null(tmp_path):
    gap = _csv(tmp_path, "outgap.csv", lambda ls: _cell(ls, 5, 2, ""))
    assert Experiment.from_csv(gap, MODEL).outputs["x"][3] is None
    bad = [_csv(tmp_path, "a.csv", lambda ls: _cell(ls, 3, 0, "x")), gap, tmp_path / "none.parquet",
           tmp_path / "b.xlsx"]
    with pytest.raises(DataFileError) as info:
        files.read_records(bad, MODEL, FileColumns())
    lines = str(info.value).splitlines()
    assert len(lines) == 3
    assert "a.csv: column 't', row 2 (line 3)" in lines[0] and "none.parquet: no such file" in lines[1]
    assert "b.xlsx: unknown kind of file '.xlsx'" in lines[2]


def test_a_missing_reader_names_the_extra(tmp_path, monkeypatch):
    real = files.importlib.import_module

    def without_pandas(name, *args):
        if name == "pandas":
            raise ImportError(name)
        return real(name, *args)

    monkeypatch.setattr(files.importlib, "import_module", without_pandas)
    with pytest.raises(DataFileError, match=r"reading \.csv files needs pandas: pip install 'greyfit\[files\]'"):
        files.read_table(ROOT / "examples" / "msd.csv")
