"""/docs and /redoc work with no network: every asset comes from the server, and the example fits.

The pages are fetched with the in-process client, every asset they reference is fetched from the
same server, and a headless Chromium that cannot resolve any host but the loopback renders both
pages from a real `greyfit serve`. The example request that "Try it out" sends is the
mass-spring-damper fit; POSTed, it converges to the values the data were simulated with.
"""
import json
import re
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urljoin, urlsplit

import httpx
import pytest

from tests.servers import free_port, start_server, stop_server
from tests.service.test_report_browser import browser, chromium

ROOT = Path(__file__).resolve().parents[2]
MSD_TRUTH = {"c": 0.8, "k": 5.0}   # examples/msd_request.json was simulated with these (m = 2 fixed)
CONTENT_TYPES = {".js": "javascript", ".css": "text/css", ".png": "image/png", ".json": "application/json"}


class AssetLinks(HTMLParser):
    """The URLs a browser fetches to show the page: script src, link href, img src, redoc spec-url."""

    def __init__(self):
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag, attrs):
        wanted = {"script": "src", "link": "href", "img": "src", "redoc": "spec-url"}.get(tag)
        for name, value in attrs:
            if name == wanted and value:
                self.urls.append(value)


def page_assets(html: str) -> list[str]:
    parser = AssetLinks()
    parser.feed(html)
    # Swagger UI is given its description in the inline script: url: '/openapi.json'
    parser.urls += re.findall(r"""\burl:\s*['"]([^'"]+)['"]""", html)
    return parser.urls


def css_assets(css: str) -> list[str]:
    return [u for u in re.findall(r"""url\(\s*['"]?([^'")]+)['"]?\s*\)""", css) if not u.startswith("data:")]


def assert_local(url: str, page: str) -> None:
    parts = urlsplit(url)
    assert not parts.scheme and not parts.netloc, f"{page} loads {url} from another host"


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_page_and_every_asset_it_references_come_from_the_server(client, page):
    resp = client.get(page)
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/html")
    assert "cdn." not in resp.text and "fonts.googleapis" not in resp.text
    urls = page_assets(resp.text)
    assert any(u.endswith(".js") for u in urls) and any(u.endswith("openapi.json") for u in urls), urls
    seen = set()
    while urls:
        url = urls.pop()
        if url in seen:
            continue
        seen.add(url)
        assert_local(url, page)
        asset = client.get(urljoin(page, url))
        assert asset.status_code == 200, (url, asset.status_code)
        suffix = Path(urlsplit(url).path).suffix
        assert CONTENT_TYPES[suffix] in asset.headers["content-type"], (url, asset.headers["content-type"])
        assert len(asset.content) > 500, url
        if suffix == ".css":
            urls += [urljoin(url, u) for u in css_assets(asset.text)]


def documented_example(spec: dict, path: str) -> dict:
    """The request body of POST `path` as the OpenAPI description offers it to "Try it out"."""
    examples = spec["paths"][path]["post"]["requestBody"]["content"]["application/json"]["examples"]
    (example,) = examples.values()
    name = example["$ref"].rsplit("/", 1)[1]
    return spec["components"]["examples"][name]["value"]


def assert_converged_near_truth(result: dict) -> None:
    assert result["success"] is True and result["status"] == "success", result["message"]
    assert result["solver"]["return_status"] == "Solve_Succeeded"
    for name, truth in MSD_TRUTH.items():
        p = result["parameters"][name]
        # the estimate is within 1 % of the truth and within 4 standard errors of it
        assert abs(p["value"] - truth) < 0.01 * truth, (name, p)
        assert abs(p["value"] - truth) < 4 * p["stderr"], (name, p)


def test_the_documented_fit_example_is_the_msd_example_and_converges(client):
    spec = client.get("/openapi.json").json()
    body = documented_example(spec, "/v1/fits")
    assert body == json.loads((ROOT / "examples" / "msd_request.json").read_text())
    # a rough start: the example begins far from the answer
    start = {p["name"]: p["value"] for p in body["model"]["parameters"]}
    assert start["c"] < 0.5 * MSD_TRUTH["c"] and start["k"] < 0.5 * MSD_TRUTH["k"]
    resp = client.post("/v1/fits", json=body)
    assert resp.status_code == 200, resp.text
    assert_converged_near_truth(resp.json())


def test_the_documented_job_example_is_accepted_and_its_fit_converges(client):
    from tests.service.conftest import wait_for_job

    body = documented_example(client.get("/openapi.json").json(), "/v1/jobs")
    resp = client.post("/v1/jobs", json=body)
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client, resp.json()["id"])
    assert job["status"] == "succeeded", job
    (row,) = client.get(f"/v1/jobs/{job['id']}/results").json()["results"]
    assert_converged_near_truth(row["result"])


def test_every_shipped_example_is_a_copy_of_the_repository_example():
    shipped = ROOT / "service" / "http" / "static" / "examples"
    copies = {"msd_request.json": "msd_request.json", "msd_result.json": "msd_result.json",
              "frequency_pi_loop_request.json": "frequency_pi_loop_request.json"}
    assert {p.name for p in shipped.glob("*.json")} == set(copies)
    for name, source in copies.items():
        assert json.loads((shipped / name).read_text()) == json.loads((ROOT / "examples" / source).read_text())


def test_the_other_documented_examples_are_accepted_and_say_what_their_summary_does(client):
    spec = client.get("/openapi.json").json()
    documented = {path for path, ops in spec["paths"].items()
                  if "examples" in ops.get("post", {}).get("requestBody", {}).get("content", {}).get(
                      "application/json", {})}
    assert {"/v1/fits", "/v1/jobs", "/v1/discover", "/v1/simulate", "/v1/frequency-fits"} <= documented
    sim = client.post("/v1/simulate", json=documented_example(spec, "/v1/simulate"))
    assert sim.status_code == 200, sim.text
    # the true parameters reproduce the noisy record to its noise: fit % as high as the fit's own
    assert min(sim.json()["validation"]["fit_percent"].values()) > 97
    freq = client.post("/v1/frequency-fits", json=documented_example(spec, "/v1/frequency-fits"))
    assert freq.status_code == 200, freq.text
    result = freq.json()
    assert result["success"] is True and all(loop["stable"] for loop in result["frequency_response"]["loops"])
    truth = {"a1": 20, "a2": 500, "a3": 2000, "b1": 33.2224, "b2": 14840}   # docs/frequency.md
    for name, value in truth.items():
        assert abs(result["parameters"][name]["value"] / value - 1) < 0.02, (name, result["parameters"][name])
    disc = client.post("/v1/discover", json=documented_example(spec, "/v1/discover"))
    assert disc.status_code == 200, disc.text
    assert disc.json()["steps"] == [] and "no significant missing effect" in disc.json()["conclusion"]


@pytest.mark.slow
def test_headless_chromium_renders_both_pages_with_every_other_host_unreachable(tmp_path):
    exe = browser()
    port = free_port()
    server = start_server(tmp_path / "data", port, workers=1)
    base = f"http://127.0.0.1:{port}"
    try:
        fits = httpx.get(f"{base}/openapi.json", timeout=10).json()["paths"]["/v1/fits"]["post"]
        # Swagger UI's deep link opens the operation: #/<tag>/<operationId>
        deep_link = f"{base}/docs#/{fits['tags'][0]}/{fits['operationId']}"
        offline = ("--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1", "--virtual-time-budget=15000")
        swagger = chromium(exe, *offline, "--dump-dom", deep_link)
        redoc = chromium(exe, *offline, "--dump-dom", f"{base}/redoc")
    finally:
        stop_server(server)
    # what only the running scripts write (the pages as served hold an empty <div> / <redoc> element):
    # Swagger UI an operation block per route and the opened one's example body, ReDoc the operations
    # and their request samples
    assert swagger.returncode == 0, swagger.stderr[-2000:]
    assert re.search(r'class="opblock-summary-path"[^>]*data-path="/v1/frequency-fits"', swagger.stdout), \
        swagger.stdout[:2000]
    assert "Try it out" in swagger.stdout and "Mass-spring-damper" in swagger.stdout
    assert "(u - c*v - k*x)/m" in swagger.stdout
    assert redoc.returncode == 0, redoc.stderr[-2000:]
    assert "/v1/fits" in redoc.stdout and "/v1/frequency-fits" in redoc.stdout, redoc.stdout[:2000]
    assert "Request samples" in redoc.stdout and "(u - c*v - k*x)/m" in redoc.stdout
