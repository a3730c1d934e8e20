"""The OpenAPI description says what the service really sends, and the pages that show it offline.

FastAPI documents only the success and a 422 of its own shape; this adds, to every operation, the
problem+json answers the middleware and handlers give (400, 401, 404, 408, 413, 415, 422, 429, 500,
503, and 501 and 504 for synchronous fits) and the bearer security scheme, real example requests and
answers (service/http/openapi_examples.py) where FastAPI would generate junk, so "Try it out" sends a fit
that works, and operationIds written by hand.

`/docs` (Swagger UI) and `/redoc` (ReDoc) load their scripts from `service/http/static/`, served by the
service itself: FastAPI's defaults load them from a CDN and stay blank on a machine without network.
"""
from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from greyfit.service.http.openapi_examples import add_answer_examples, add_examples
from greyfit.service.http.problems import PROBLEM, Problem
from greyfit.service.settings import Settings
from greyfit.service.task_kinds import JOB_KINDS, KINDS

SCHEME = "bearerAuth"
ANSWERS = {
    "400": "the body is not UTF-8 JSON or is nested too deeply",
    "401": "missing or wrong API key (only when GREYFIT_API_KEY is set)",
    "404": "no such job or route",
    "408": "the body did not arrive within GREYFIT_BODY_READ_SECONDS of the request's start (a slow sender)",
    "413": "the body (or, for synchronous fits, its data) is larger than this server takes",
    "415": "the body was not sent as JSON: send it with 'Content-Type: application/json'",
    "422": "invalid request: `errors` lists each location (e.g. experiments[0].outputs.x) and what to fix",
    "429": "more requests a minute than GREYFIT_RATE_LIMIT_PER_MINUTE allows; see Retry-After",
    "500": "a bug in the server; logged under `request_id`",
    "501": "an optional part of this server is not installed (e.g. the report extra, matplotlib)",
    "503": "at capacity (bodies in flight, synchronous queue), the job store cannot be written, "
           "or shutting down; see Retry-After",
    "504": "the synchronous fit (or report) exceeded its CPU- or wall-time limit",
}
# answered by a worker while the client waits (501, 504): every kind's sync route, and the job report
SYNC_PATHS = tuple(k.sync_path for k in KINDS.values() if k.sync_path) + ("/v1/jobs/{job_id}/report",)
PUBLIC = ("/healthz", "/readyz")
JOB_PATHS = tuple(k.jobs_path for k in KINDS.values() if k.jobs_path)
IDEMPOTENCY_HEADER = {
    "name": "Idempotency-Key", "in": "header", "required": False,
    "schema": {"type": "string", "minLength": 1, "maxLength": 200, "pattern": "^[\\x21-\\x7e]+$"},
    "description": "makes a retry safe: the same key with the same body returns the job made the first time "
                   "(never a second one); with another body, 422"}

# written by hand: client generators name their methods after these (FastAPI's own are
# `create_fit_v1_fits_post`); tests/service/test_openapi_descriptions.py checks every operation has one
OPERATION_IDS = {
    ("get", "/healthz"): "get_health",
    ("get", "/readyz"): "get_readiness",
    ("get", "/metrics"): "get_metrics",
    ("post", "/v1/simulate"): "create_simulation",
    ("post", "/v1/report"): "create_report",
    ("post", "/v1/fits/files"): "create_fit_from_files",
    ("post", "/v1/discover/files"): "create_discovery_from_files",
    ("get", "/v1/jobs"): "list_jobs",
    ("get", "/v1/jobs/{job_id}"): "get_job",
    ("delete", "/v1/jobs/{job_id}"): "cancel_job",
    ("get", "/v1/jobs/{job_id}/results"): "get_job_results",
    ("get", "/v1/jobs/{job_id}/report"): "get_job_report",
    # the generated routes of the task kinds: the names their entries give
    **{("post", k.sync_path): k.operation for k in KINDS.values() if k.generate and k.sync_path},
    **{("post", k.jobs_path): k.job_operation for k in KINDS.values() if k.jobs_path},
}

STATIC = Path(__file__).resolve().parent / "static"
STATIC_URL = "/static"


def _problem_response(description: str, headers: bool) -> dict:
    out = {"description": description,
           "content": {PROBLEM: {"schema": {"$ref": "#/components/schemas/Problem"}}}}
    if headers:
        out["headers"] = {"Retry-After": {"schema": {"type": "integer"}, "description": "seconds to wait"}}
    return out


# pydantic's names of bounds and JSON Schema's: a bound given on an annotated parameter (QueryInt with
# Query(ge=0), and its Optional) reaches FastAPI's description under pydantic's name, which JSON Schema
# and every client ignore
_BOUNDS = {"ge": "minimum", "le": "maximum", "gt": "exclusiveMinimum", "lt": "exclusiveMaximum"}


def _publish_bounds(schema: dict) -> None:
    """Rename pydantic's bounds to JSON Schema's in a parameter's schema, its anyOf members included."""
    for ours, theirs in _BOUNDS.items():
        if ours in schema:
            schema[theirs] = schema.pop(ours)
    for member in schema.get("anyOf", []):
        _publish_bounds(member)


def describe(app: FastAPI, settings: Settings) -> dict:
    spec = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    components = spec.setdefault("components", {})
    schemas = components.setdefault("schemas", {})
    problem_schema = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(problem_schema.pop("$defs", {}))
    schemas["Problem"] = problem_schema
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    if "JobPublic" in schemas:   # the job kinds are the task-kind table's (schemas/ cannot import it)
        schemas["JobPublic"]["properties"]["kind"]["enum"] = list(JOB_KINDS)
    components["securitySchemes"] = {SCHEME: {"type": "http", "scheme": "bearer",
                                              "description": "GREYFIT_API_KEY, when the server sets one"}}
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            responses = op.setdefault("responses", {})
            for parameter in op.get("parameters", []):
                _publish_bounds(parameter.get("schema", {}))
            codes = ["500"] if path == "/healthz" else ["500", "503"]
            if path not in PUBLIC:
                codes += ["401", "404", "413", "422", "429"]
                op["security"] = [{SCHEME: []}] if settings.api_key else [{}, {SCHEME: []}]
            if "requestBody" in op:
                codes += ["400", "408", "415"]
            if path in SYNC_PATHS:
                codes += ["501", "504"]
            if method == "post" and path in JOB_PATHS:
                op.setdefault("parameters", []).append(IDEMPOTENCY_HEADER)
            for code in sorted(set(codes)):
                responses[code] = _problem_response(ANSWERS[code], code in ("429", "503"))
            op["operationId"] = OPERATION_IDS.get((method, path), op.get("operationId"))
    add_examples(spec)
    add_answer_examples(spec)
    return spec


def install_openapi(app: FastAPI, settings: Settings) -> None:
    def openapi() -> dict:
        if app.openapi_schema is None:
            app.openapi_schema = describe(app, settings)
        return app.openapi_schema

    app.openapi = openapi   # type: ignore[method-assign]  # FastAPI's documented way to replace the description


def install_docs(app: FastAPI) -> None:
    """Serve /docs (Swagger UI) and /redoc (ReDoc) with assets from service/http/static/, no network needed."""
    app.mount(STATIC_URL, StaticFiles(directory=STATIC), name="static")
    spec_url = app.openapi_url or "/openapi.json"   # (create_app always serves the description)

    def url(request: Request, path: str) -> str:
        # behind a proxy that strips a prefix, the browser must ask for the prefixed path
        return request.scope.get("root_path", "").rstrip("/") + path

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=url(request, spec_url), title=f"{app.title} - Swagger UI",
            swagger_js_url=url(request, f"{STATIC_URL}/swagger-ui/swagger-ui-bundle.js"),
            swagger_css_url=url(request, f"{STATIC_URL}/swagger-ui/swagger-ui.css"),
            swagger_favicon_url=url(request, f"{STATIC_URL}/swagger-ui/favicon-32x32.png"),
            swagger_ui_parameters={"validatorUrl": None})   # no badge fetched from the validator's site

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        return get_redoc_html(
            openapi_url=url(request, spec_url), title=f"{app.title} - ReDoc",
            redoc_js_url=url(request, f"{STATIC_URL}/redoc/redoc.standalone.js"),
            redoc_favicon_url=url(request, f"{STATIC_URL}/swagger-ui/favicon-32x32.png"),
            with_google_fonts=False)
