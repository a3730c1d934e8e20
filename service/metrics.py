"""Prometheus metrics through prometheus_client: each app its own registry, with the process's own
metrics (memory, CPU, open files, garbage collections) beside greyfit's.

Counters are counted where things happen (requests, fits, lost workers, tasks given back to the
queue, store errors); the gauges (queues, running tasks, the executor's state) are read when
/metrics is scraped, from the dispatcher and the job store (`watch`).
"""
from __future__ import annotations

import logging
from typing import Callable, Iterable, Optional

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector

log = logging.getLogger("greyfit.service")
BUCKETS = (0.01, 0.05, 0.1, 0.5, 1, 2, 5, 10, 30, 60, 300, 1200)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

# a gauge read at scrape time: (name, help, labels, [(label values, value)])
Gauge = tuple[str, str, tuple[str, ...], list[tuple[tuple[str, ...], float]]]


class _Gauges:
    """A collector that asks `read()` for its gauges at each scrape (none before `watch`)."""

    def __init__(self) -> None:
        self.read: Optional[Callable[[], list[Gauge]]] = None

    def collect(self) -> Iterable[Metric]:
        if self.read is None:
            return []
        out = []
        for name, doc, labels, samples in self.read():
            family = GaugeMetricFamily(name, doc, labels=list(labels))
            for values, value in samples:
                family.add_metric(list(values), value)
            out.append(family)
        return out


class Metrics:
    def __init__(self) -> None:
        self.registry = registry = CollectorRegistry()
        for collector in (ProcessCollector, PlatformCollector, GCCollector):
            collector(registry=registry)
        self.requests = Counter("greyfit_http_requests", "HTTP requests by method, route and status.",
                                ["method", "route", "status"], registry=registry)
        self.fits = Counter("greyfit_fits", "Fits (and discoveries) finished, by kind and status.",
                            ["kind", "status"], registry=registry)
        self.durations = Histogram("greyfit_fit_duration_seconds", "Wall time of finished fits.", ["kind"],
                                   buckets=BUCKETS, registry=registry)
        self.worker_losses = Counter("greyfit_worker_losses", "Tasks whose worker was lost mid-task (crashed, "
                                     "killed, hung, or replaced before it began).", ["kind"], registry=registry)
        self.give_backs = Counter(
            "greyfit_task_give_backs", "Tasks given back to the queue: lost_worker (its worker died), expired "
            "(its server stopped renewing the lease), lost_claim (a claim whose answer was lost), shutdown.",
            ["reason"], registry=registry)
        self.store_errors = Counter("greyfit_store_errors", "Job store errors, by where they were met "
                                    "(http: a request answered 503; dispatcher: a round of the dispatcher).",
                                    ["where"], registry=registry)
        self.refused = Counter("greyfit_refused", "Requests refused at a capacity limit (503), by limit.",
                               ["limit"], registry=registry)
        self._gauges = _Gauges()
        registry.register(self._gauges)

    def watch(self, read: Callable[[], list[Gauge]]) -> None:
        """The gauges, read at each scrape (service.http.app sets it when the dispatcher starts)."""
        self._gauges.read = read

    def count_request(self, method: str, route: str, status: int) -> None:
        self.requests.labels(method, route, str(status)).inc()

    def count_fit(self, kind: str, status: str, seconds: float | None) -> None:
        self.fits.labels(kind, status).inc()
        if seconds is not None:
            self.durations.labels(kind).observe(seconds)

    def render(self) -> bytes:
        return generate_latest(self.registry)


def service_gauges(store, dispatcher, metrics: Metrics) -> Callable[[], list[Gauge]]:
    """The gauges of a server: its queues and running tasks, the job store's, the executor's state."""
    def read() -> list[Gauge]:
        executor = dispatcher.executor
        name = type(executor).__name__
        reason = executor.unready()
        out: list[Gauge] = [
            ("greyfit_sync_queue_depth", "Synchronous fits waiting for a worker.", (),
             [((), dispatcher.sync_waiting())]),
            ("greyfit_tasks_running", "Tasks running on this server's executor.", (),
             [((), dispatcher.running_count())]),
            ("greyfit_executor_ready", "1 if the executor can run tasks (for Dask: a scheduler and workers).",
             ("executor",), [((name,), 0.0 if reason else 1.0)]),
            ("greyfit_executor_capacity", "Tasks the executor runs at once (Dask: the cluster's threads).",
             ("executor",), [((name,), executor.capacity() if not reason else 0)]),
            ("greyfit_worker_replacements", "Local worker processes replaced since the server started.",
             ("executor",), [((name,), executor.replaced)])]
        try:
            counts = store.task_counts()
        except Exception as exc:   # the store out of reach: its gauges left out, the error counted
            log.warning("metrics: the job store did not answer (%s)", type(exc).__name__)
            metrics.store_errors.labels("metrics").inc()
            return out
        # tasks this server has claimed for its next free workers are waiting too
        out += [("greyfit_queue_depth", "Tasks waiting in the job store (and claimed by this server, not started).",
                 (), [((), counts.get("queued", 0) + len(dispatcher.ready))]),
                ("greyfit_store_tasks", "Unfinished tasks in the job store (every server's), by status.", ("status",),
                 [((s,), counts.get(s, 0)) for s in ("queued", "running")])]
        return out

    return read
