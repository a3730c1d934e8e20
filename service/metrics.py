"""Prometheus text exposition of a few counters, histograms and gauges (no extra dependency)."""
from __future__ import annotations

import threading
from collections import defaultdict

BUCKETS = (0.01, 0.05, 0.1, 0.5, 1, 2, 5, 10, 30, 60, 300, 1200)


class Metrics:
    def __init__(self):
        self.lock = threading.Lock()
        self.requests: dict[tuple[str, str, int], int] = defaultdict(int)
        self.fits: dict[tuple[str, str], int] = defaultdict(int)
        self.durations: dict[str, list[int]] = defaultdict(lambda: [0] * (len(BUCKETS) + 1))
        self.duration_sum: dict[str, float] = defaultdict(float)

    def count_request(self, method: str, route: str, status: int) -> None:
        with self.lock:
            self.requests[(method, route, status)] += 1

    def count_fit(self, kind: str, status: str, seconds: float | None) -> None:
        with self.lock:
            self.fits[(kind, status)] += 1
            if seconds is not None:
                counts = self.durations[kind]
                for i, b in enumerate(BUCKETS):
                    if seconds <= b:
                        counts[i] += 1
                counts[-1] += 1
                self.duration_sum[kind] += seconds

    def render(self, queue_depth: int, running: int) -> str:
        out = ["# HELP greyfit_http_requests_total HTTP requests by method, route and status.",
               "# TYPE greyfit_http_requests_total counter"]
        with self.lock:
            for (m, r, s), n in sorted(self.requests.items()):
                out.append(f'greyfit_http_requests_total{{method="{m}",route="{r}",status="{s}"}} {n}')
            out += ["# HELP greyfit_fits_total Fits (and discoveries) finished, by kind and status.",
                    "# TYPE greyfit_fits_total counter"]
            for (k, s), n in sorted(self.fits.items()):
                out.append(f'greyfit_fits_total{{kind="{k}",status="{s}"}} {n}')
            out += ["# HELP greyfit_fit_duration_seconds Wall time of finished fits.",
                    "# TYPE greyfit_fit_duration_seconds histogram"]
            for k, counts in sorted(self.durations.items()):
                for b, c in zip(BUCKETS, counts):
                    out.append(f'greyfit_fit_duration_seconds_bucket{{kind="{k}",le="{b}"}} {c}')
                out.append(f'greyfit_fit_duration_seconds_bucket{{kind="{k}",le="+Inf"}} {counts[-1]}')
                out.append(f'greyfit_fit_duration_seconds_sum{{kind="{k}"}} {self.duration_sum[k]}')
                out.append(f'greyfit_fit_duration_seconds_count{{kind="{k}"}} {counts[-1]}')
        out += ["# HELP greyfit_queue_depth Tasks waiting in the job store.", "# TYPE greyfit_queue_depth gauge",
                f"greyfit_queue_depth {queue_depth}",
                "# HELP greyfit_tasks_running Tasks running on this server's executor.",
                "# TYPE greyfit_tasks_running gauge", f"greyfit_tasks_running {running}"]
        return "\n".join(out) + "\n"
