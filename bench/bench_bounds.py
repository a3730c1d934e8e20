"""What hostile small bodies cost a real `greyfit serve` (issue 41, item 1): 250 000 empty requests
in a job body, an unknown field holding 10^6 zeros, an unknown field holding an object of 10^6 keys,
and an object of 10^6 keys where any key is accepted (a model's definitions). For each: the answer's
status and time, the slowest /healthz probe meanwhile (one every 25 ms), and the web process's
resident memory before and at its peak (VmHWM from /proc, reset between bodies where allowed).
The parser processes' memory is their own (they are bounded by the same walk).

    nice -n 10 python bench/bench_bounds.py
"""
from __future__ import annotations

import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_reads import kb, reset_peak  # noqa: E402
from tests.servers import free_port, large_fit_request, probe_healthz, start_server, stop_server  # noqa: E402

EXAMPLE = (Path(__file__).resolve().parents[1] / "examples" / "msd_request.json").read_text()


def bodies() -> dict[str, tuple[str, bytes]]:
    zeros = "[" + ",".join(["0"] * 10**6) + "]"
    keys = "{" + ",".join(f'"k{i}":0' for i in range(10**6)) + "}"
    return {
        "250 000 empty requests (job)": ("/v1/jobs", b'{"requests":[' + b",".join([b"{}"] * 250_000) + b"]}"),
        "unknown field of 10^6 zeros (job)": ("/v1/jobs", f'{{"requests":[{EXAMPLE}],"junk":{zeros}}}'.encode()),
        "unknown field of 10^6 keys (fit)": ("/v1/fits", f'{{"junk":{keys},{EXAMPLE[1:]}'.encode()),
        "10^6 definitions (fit)": ("/v1/fits", ('{"model":{"definitions":' + keys.replace(":0", ':"1"')
                                                + "}}").encode()),
        # the baseline: a valid fit of 12 MB (parsed and validated, then 413: too large to fit synchronously)
        "valid 12 MB fit (baseline)": ("/v1/fits", json.dumps(large_fit_request(12)).encode()),
    }


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        server = start_server(Path(tmp), port, workers=1)
        base = f"http://127.0.0.1:{port}"
        try:
            httpx.post(f"{base}/v1/jobs", content=bodies()["250 000 empty requests (job)"][1],
                       headers={"content-type": "application/json"}, timeout=120)   # the parser warmed up
            for what, (path, body) in bodies().items():
                reset_peak(server.pid)
                before = kb(server.pid, "VmRSS")
                stop = threading.Event()
                latencies: list[float] = []
                prober = threading.Thread(target=lambda stop=stop, latencies=latencies:
                                          latencies.extend(probe_healthz(base, stop)))
                prober.start()
                time.sleep(0.1)
                started = time.perf_counter()
                resp = httpx.post(base + path, content=body, headers={"content-type": "application/json"},
                                  timeout=600)
                took = time.perf_counter() - started
                stop.set()
                prober.join()
                print(f"{what:38s} {len(body) / 1e6:5.2f} MB -> {resp.status_code} ({len(resp.content)} B) in "
                      f"{took:5.2f} s; /healthz slowest {max(latencies) * 1000:5.0f} ms; web RSS "
                      f"{before / 1024:4.0f} MB -> peak {kb(server.pid, 'VmHWM') / 1024:4.0f} MB; "
                      f"{json.loads(resp.content).get('detail', '')[:60]!r}")
        finally:
            stop_server(server)


if __name__ == "__main__":
    main()
