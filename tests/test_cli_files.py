"""`greyfit fit MODEL.json --data FILE` as a user runs it: the README's first fit from examples/msd.csv
gives the JSON request's estimates to the last digit; a bad file is one line and exit 2."""
import json

from greyfit.service.cli.commands import main
from tests.test_cli import EXAMPLE, ROOT, run_cli

MODEL = ROOT / "examples" / "msd_model.json"
CSV = ROOT / "examples" / "msd.csv"


def same_fit(a: dict, b: dict) -> None:
    """The same estimates, covariance, metrics and verdict (the records' names differ: e1, msd)."""
    for key in ("parameters", "covariance", "correlation", "metrics", "quality", "success"):
        assert a[key] == b[key], key
    assert list(a["initial_states"].values()) == list(b["initial_states"].values())


def test_the_readme_fit_from_the_csv_gives_the_json_requests_estimates(tmp_path):
    from greyfit.schemas import FitRequest
    from greyfit.solvers.fit import fit_model
    from_json = fit_model(FitRequest.model_validate_json(EXAMPLE.read_text())).model_dump(mode="json")
    from_csv = run_cli("fit", str(MODEL), "--data", str(CSV), "--validation", str(CSV))
    assert from_csv.returncode == 0, from_csv.stderr
    by_file = json.loads(from_csv.stdout)
    same_fit(from_json, by_file)
    assert by_file["validation"]["experiments"][0]["name"] == "msd"   # named by the file


def cli(capsys, *args) -> tuple[int, str]:
    """The command run in this process (no fit runs: the files are refused first)."""
    code = main(list(args))
    return code, capsys.readouterr().err


def test_bad_files_are_one_line_each_naming_file_column_and_row_exit_2(tmp_path, capsys):
    lines = CSV.read_text().splitlines()
    (tmp_path / "no_u.csv").write_text("\n".join(",".join(c for j, c in enumerate(x.split(",")) if j != 1)
                                                 for x in lines) + "\n")
    text = list(lines)
    text[12] = text[12].replace(text[12].split(",")[2], "n/a?", 1)
    (tmp_path / "text.csv").write_text("\n".join(text) + "\n")
    back = list(lines)
    back[40] = "1.5," + back[40].split(",", 1)[1]
    (tmp_path / "back.csv").write_text("\n".join(back) + "\n")
    code, err = cli(capsys, "fit", str(MODEL), *[a for name in ("no_u", "text", "back")
                                                 for a in ("--data", str(tmp_path / f"{name}.csv"))])
    assert code == 2
    said = err.strip().splitlines()
    assert len(said) == 3, err
    assert said[0].startswith(f"greyfit: {tmp_path / 'no_u.csv'}: column 'u', header (line 1): no such column")
    assert said[1] == f"greyfit: {tmp_path / 'text.csv'}: column 'x', row 12 (line 13): 'n/a?' is not a number"
    assert said[2].startswith(f"greyfit: {tmp_path / 'back.csv'}: column 't', row 40 (line 41): time 1.5 s does "
                              "not increase")


def test_records_given_twice_and_a_malformed_option_are_refused(capsys):
    code, err = cli(capsys, "fit", str(EXAMPLE), "--data", str(CSV))
    assert code == 2 and "give the records one way" in err
    code, err = cli(capsys, "simulate", str(MODEL), "--data", str(CSV), "--map", "u")
    assert code == 2 and "--map 'u': write NAME=VALUE" in err
    code, err = cli(capsys, "fit", str(EXAMPLE), "--time", "time_s")
    assert code == 2 and "--time says how --data files are read, and no --data file is given" in err
    code, err = cli(capsys, "discover", str(MODEL), "--data", str(CSV), "--from", "3", "--to", "1")
    assert code == 2 and "--time/--sample-rate/--from/--to: the segment from 3.0 to 1.0 s is empty" in err
