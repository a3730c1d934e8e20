"""The FastAPI application factory."""
from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from typing import Optional

from fastapi import FastAPI, HTTPException
from starlette.types import ASGIApp, Receive, Scope, Send

from service.dispatcher import Dispatcher
from service.executors import make_executor
from service.metrics import Metrics
from service.problems import install_handlers, problem
from service.routes import discover, fits, frequency, health, jobs, ops
from service.routes import report as report_routes, simulate as simulate_routes
from service.settings import Settings, get_settings
from service.store import JobStore, make_engine

log = logging.getLogger("greyfit.service")


class BodyLimit:
    """Refuse bodies above max_body_bytes with 413 before they are read into memory."""

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        detail = (f"the body exceeds this server's limit of {self.max_bytes} bytes "
                  "(GREYFIT_MAX_BODY_BYTES); decimate the data or split it into several jobs")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            return await problem(413, "Request too large", detail, "request-too-large")(scope, receive, send)
        seen = 0

        async def limited() -> dict:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_bytes:   # a chunked body without Content-Length
                    raise HTTPException(413, detail)
            return message

        await self.app(scope, limited, send)


class CountRequests:
    """Pure ASGI middleware (not BaseHTTPMiddleware, which wraps errors raised while reading the body)."""

    def __init__(self, app: ASGIApp, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        status = [500]

        async def send_wrapper(message) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            self.metrics.count_request(scope["method"], getattr(route, "path", "unmatched"), status[0])


def create_app(settings: Optional[Settings] = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        store = JobStore(make_engine(settings.resolved_database_url()))
        executor = make_executor(settings)
        dispatcher = Dispatcher(store, executor, settings, app.state.metrics)
        app.state.store, app.state.dispatcher = store, dispatcher
        dispatcher.start()
        log.info("greyfit ready: %s executor, store %s", settings.executor, store.engine.url)
        try:
            yield
        finally:
            dispatcher.stop()
            store.engine.dispose()

    app = FastAPI(title="greyfit", version="0.1.0", lifespan=lifespan,
                  description="Fit the physical parameters of ODE models to measured data.")
    app.state.settings = settings
    app.state.metrics = Metrics()
    install_handlers(app)
    for router in (health.router, fits.router, discover.router, jobs.router, ops.router,
                   simulate_routes.router, report_routes.router, frequency.router):
        app.include_router(router)

    app.add_middleware(CountRequests, metrics=app.state.metrics)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    return app
