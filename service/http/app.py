"""The FastAPI application factory."""
from __future__ import annotations

import logging
import os
import re
import uuid
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Optional

from fastapi import FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send

from greyfit.service.http.admission import BodyBudget
from greyfit.service.http.auth import ApiKeyGate
from greyfit.service.http.clients import KeyStore
from greyfit.service.http.json_body import BodyParser, body_model
from greyfit.service.http.json_shape import ListLimits
from greyfit.service.http.logs import REQUEST_ID, configure_logging
from greyfit.service.http.openapi import install_docs, install_openapi
from greyfit.service.http.problems import install_handlers, route_methods
from greyfit.service.http.routes import files as file_routes
from greyfit.service.http.routes import health, jobs, ops
from greyfit.service.http.routes import report as report_routes
from greyfit.service.http.routes import simulate as simulate_routes
from greyfit.service.http.routes.tasks import task_routers
from greyfit.service.jobs.dispatcher import Dispatcher
from greyfit.service.jobs.executors import make_executor
from greyfit.service.jobs.store import JobStore, check_data_dir, make_engine
from greyfit.service.metrics import Metrics, service_gauges
from greyfit.service.settings import Settings, get_settings

log = logging.getLogger("greyfit.service")


class CountRequests:
    """Counts requests and gives each an id (X-Request-ID, echoed; the caller's own if it sent a plain
    one), which every log line about the request and every error body name. A 503 without
    Retry-After gets one (`retry_after` seconds): the OpenAPI promises it on every 503, and this is
    the one place every answer passes.

    Pure ASGI middleware (not BaseHTTPMiddleware, which wraps errors raised while reading the body)."""

    def __init__(self, app: ASGIApp, metrics: Metrics, retry_after: int = 2):
        self.app, self.metrics = app, metrics
        self.retry_after = str(retry_after).encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        status = [500]
        request_id = _request_id(scope)
        scope["greyfit.request_id"] = request_id
        REQUEST_ID.set(request_id)   # for the log lines and error bodies of this request (its own task)

        async def send_wrapper(message) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
                headers = [*message.get("headers", []), (b"x-request-id", request_id.encode())]
                if status[0] == 503 and not any(name.lower() == b"retry-after" for name, _ in headers):
                    headers.append((b"retry-after", self.retry_after))
                message["headers"] = headers
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            self.metrics.count_request(scope["method"], getattr(route, "path", "unmatched"), status[0])


# a caller's own X-Request-ID is kept when it is a plain token (it then names the request in both logs)
_CALLER_ID = re.compile(rb"^[A-Za-z0-9._:-]{1,64}$")


def _request_id(scope: Scope) -> str:
    for name, value in scope.get("headers", ()):
        if name == b"x-request-id" and _CALLER_ID.match(value):
            return value.decode("ascii")
    return uuid.uuid4().hex[:16]


def list_limits(settings: Settings) -> ListLimits:
    """The lists of models a body's shape is checked against before it is validated (service.http.json_shape)."""
    records = (settings.max_experiments, "GREYFIT_MAX_EXPERIMENTS")
    return ListLimits((("requests", settings.max_batch_requests, "GREYFIT_MAX_BATCH_REQUESTS"),
                       ("experiments", *records), ("validation", *records), ("data", *records)))


def create_app(settings: Optional[Settings] = None) -> FastAPI:
    settings = settings or get_settings()
    configure_logging(settings.log_format, settings.log_level)
    # refuse to start on a data directory that cannot be written, in one line (not a traceback of
    # the first SQLite write)
    check_data_dir(settings.data_dir, None if settings.database_url else settings.data_dir / "greyfit.db")

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        configure_logging(settings.log_format, settings.log_level)   # again: a server may have set its own
        # compiled model functions live beside the job store; workers spawned below inherit this
        os.environ.setdefault("GREYFIT_CACHE_DIR", str(Path(settings.data_dir).resolve() / "cache"))
        store = JobStore(make_engine(settings.resolved_database_url()))
        executor = make_executor(settings)
        dispatcher = Dispatcher(store, executor, settings, app.state.metrics)
        app.state.store, app.state.dispatcher = store, dispatcher
        app.state.keys = KeyStore(store.engine)   # the named API keys (ApiKeyGate reads them)
        app.state.metrics.watch(service_gauges(store, dispatcher, app.state.metrics))
        dispatcher.start()
        app.state.body_parser.start(body_modules)
        log.info("greyfit ready: %s executor, store %s", settings.executor, store.engine.url)
        try:
            yield
        finally:
            app.state.body_parser.shutdown()
            dispatcher.stop()
            store.engine.dispose()

    # docs_url/redoc_url None: install_docs serves both pages with local assets instead of a CDN's
    app = FastAPI(title="greyfit", version="0.1.0", lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="Fit the physical parameters of ODE models to measured data.")
    app.state.settings = settings
    app.state.metrics = Metrics()
    app.state.body_parser = BodyParser(settings.body_parser_processes, settings.retry_after_seconds,
                                       list_limits(settings), settings.max_parse_queue)
    install_handlers(app)
    routers = (health.router, *task_routers(), file_routes.router, jobs.router, ops.router, simulate_routes.router,
               report_routes.router)
    for router in routers:
        app.include_router(router)
    # what the parser processes import when they start: the schemas (a model defined in a route's
    # module would bring the whole web stack into them)
    body_modules = sorted({m.__module__ for r in routers for m in map(body_model, r.routes)
                           if m is not None and m.__module__.startswith("greyfit.schemas.")})

    install_openapi(app, settings)
    install_docs(app)
    # for the Allow header of a 405: every method served at a path, whichever route serves it
    app.state.route_methods = route_methods([*app.routes, *(route for r in routers for route in r.routes)])

    # outermost last: count -> key and rate limit -> body budget -> the app; no body byte is read
    # before the key is checked and the body admitted
    app.add_middleware(BodyBudget, max_body_bytes=settings.max_body_bytes,
                       max_inflight_bytes=settings.max_inflight_body_bytes, retry_after=settings.retry_after_seconds,
                       body_read_seconds=settings.body_read_seconds)
    app.add_middleware(ApiKeyGate, api_key=settings.api_key, rate_limit_per_minute=settings.rate_limit_per_minute)
    app.add_middleware(CountRequests, metrics=app.state.metrics, retry_after=settings.retry_after_seconds)
    return app
