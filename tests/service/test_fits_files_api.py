"""POST /v1/fits/files (and /v1/discover/files): the README's request without records and examples/msd.csv
as a multipart form give the JSON request's estimates to the last digit; a bad file or option is a 422
naming it."""
from pathlib import Path

from tests.service.conftest import EXAMPLE, assert_problem

ROOT = Path(__file__).resolve().parents[2]
MODEL = (ROOT / "examples" / "msd_model.json").read_text()
CSV = (ROOT / "examples" / "msd.csv").read_bytes()


def upload(client, *, request: str = MODEL, files=(("data", "msd.csv", CSV),), **fields):
    return client.post("/v1/fits/files", data={"request": request, **fields},
                       files=[(field, (name, content, "application/octet-stream")) for field, name, content in files])


def test_a_multipart_fit_from_the_csv_gives_the_json_requests_estimates(client):
    by_json = client.post("/v1/fits", content=EXAMPLE.read_text(), headers={"content-type": "application/json"})
    by_file = upload(client, files=(("data", "msd.csv", CSV), ("validation", "held_out.csv", CSV)))
    assert by_json.status_code == 200 and by_file.status_code == 200, by_file.text
    a, b = by_json.json(), by_file.json()
    for key in ("parameters", "covariance", "metrics", "quality"):
        assert a[key] == b[key], key
    assert b["validation"]["experiments"][0]["name"] == "held_out"


def test_a_bad_file_is_a_422_naming_file_column_and_row(client):
    lines = CSV.decode().splitlines()
    lines[12] = lines[12].rsplit(",", 1)[0] + ",fast"
    resp = upload(client, files=(("data", "run7.csv", "\n".join(lines).encode()),))
    body = assert_problem(resp, 422, "run7.csv: column 'v', row 12 (line 13): 'fast' is not a number")
    assert body["title"] == "Invalid data"


def test_bad_options_and_requests_are_422s_naming_the_field(client):
    assert_problem(upload(client, columns='{"sample_rate": 20, "time": "t"}'), 422,
                   "columns", "give the time column or the sample rate, not both")
    assert_problem(upload(client, request=EXAMPLE.read_text()), 422, "request.experiments",
                   "give the records as files")
    assert_problem(upload(client, request='{"model": {"states": ["x"]}}'), 422, "request.model.equations")
    assert_problem(upload(client, columns="{"), 422, "columns", "not valid JSON")


def test_discovery_takes_files_too(client):
    found = client.post("/v1/discover/files", data={"request": MODEL}, files=[("data", ("msd.csv", CSV, "text/csv"))])
    assert found.status_code == 200, found.text
    result = found.json()
    assert result["steps"] == []    # the model is complete: nothing is added
    fitted = result["fit"]["parameters"]
    assert abs(fitted["k"]["value"] - 5.0) < 3 * fitted["k"]["stderr"]   # made with k = 5 N/m
    assert_problem(client.post("/v1/discover/files", data={"request": MODEL},
                               files=[("data", ("bad.mat", b"not a mat file", "application/octet-stream"))]),
                   422, "bad.mat: cannot be read as .mat")
