"""`greyfit serve` and `greyfit batch`."""
from __future__ import annotations

import json
import sys
import time
from collections import deque
from pathlib import Path

from greyfit.service.task_kinds import JOB_KINDS, KINDS

# how long `greyfit batch` lets its workers finish compiling at the end: a compile's own limit
# (solvers/dynamics/compiled.py's COMPILE_TIMEOUT_S, not imported here: that would load CasADi)
BUILD_GRACE_S = 130.0


def add_serve(sub) -> None:
    p = sub.add_parser("serve", help="run the HTTP service (uvicorn)",
                       description="Run the HTTP service: the /v1 routes, jobs in worker processes, /docs.")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; 0.0.0.0 for all)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    p.add_argument("--workers", type=int, default=None, help="fit worker processes (default: cores)")
    p.add_argument("--data-dir", default=None, help="where the SQLite job store lives (default ./data)")
    p.set_defaults(func=cmd_serve)


def cmd_serve(args) -> int:
    import gc

    import uvicorn

    from greyfit.service.http.app import create_app
    from greyfit.service.jobs.store import DataDirNotWritable
    from greyfit.service.settings import Settings
    overrides = {}
    if args.workers:
        overrides["workers"] = args.workers
    if args.data_dir:
        overrides["data_dir"] = Path(args.data_dir)
    settings = Settings(**overrides)
    try:
        app = create_app(settings)
    except DataDirNotWritable as exc:   # one line, not the traceback of the first SQLite write
        print(f"greyfit serve: {exc}", file=sys.stderr)
        return 2
    # what is loaded by now lives as long as the server: keep it out of the collector's full passes,
    # which would otherwise stall the event loop ~0.1 s each (longer on a busy machine)
    gc.collect()
    gc.freeze()
    # httptools (a dependency): h11, uvicorn's pure-Python fallback, would hold the interpreter for
    # every chunk of a large body and stall /healthz during uploads
    # log_config=None: uvicorn's lines go through greyfit's JSON handler (service.http.logs), not its own
    # (greyfit's subclass of it bounds a connection's idle time and answers what uvicorn cannot parse
    # as problem+json: service.http.protocol)
    from greyfit.service.http.protocol import bounded_protocol
    uvicorn.run(app, host=args.host, port=args.port, log_level="info", log_config=None,
                http=bounded_protocol(settings.request_head_seconds), timeout_keep_alive=settings.keep_alive_seconds)   # type: ignore[arg-type]  # declared int, used as a float (loop.call_later)
    return 0




def add_batch(sub) -> None:
    p = sub.add_parser("batch", help="many fits locally in parallel; resumable",
                       description="Fit every line of a JSON-lines file in worker processes; results are "
                                   "appended to --out as they finish, so an interrupted run resumes.")
    p.add_argument("requests", help="JSON lines, one request (of --kind) per line")
    p.add_argument("--out", required=True, help="JSON lines of results; lines already there are skipped")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: cores)")
    p.add_argument("--fail-on", choices=["failed", "suspect"], default=None,
                   help="exit 3 when any result's quality is failed (failed), or suspect or failed (suspect)")
    p.add_argument("--kind", choices=list(JOB_KINDS), default="fit",
                   help="the kind of every request: " + ", ".join(
                       f"{k}: {KINDS[k].request.rpartition(':')[2]}" for k in JOB_KINDS))
    p.set_defaults(func=cmd_batch)


def cmd_batch(args) -> int:
    from pydantic import ValidationError

    from greyfit.service.http.error_text import error_lines
    from greyfit.service.http.json_parsing import loads_strict, validate_strict
    from greyfit.service.jobs.executors import LocalWorkerPool
    from greyfit.service.settings import Settings
    settings = Settings(**({"workers": args.workers} if args.workers else {}))
    schema = KINDS[args.kind].request_schema()
    out_path = Path(args.out)
    done: set[int] = set()
    if out_path.exists():
        for line in out_path.read_text().splitlines():
            try:
                done.add(int(json.loads(line)["line"]))
            except (ValueError, KeyError, TypeError):
                continue   # a line cut off by an interrupted run is simply redone
    todo: list[tuple[int, str]] = []
    bad: list[dict] = []
    for i, line in enumerate(Path(args.requests).read_text().splitlines(), start=1):
        if not line.strip() or i in done:
            continue
        try:
            body = loads_strict(line)
            validate_strict(schema, body)     # a bad line fails here, named, not in a worker
            todo.append((i, line))            # the worker parses the text itself: no pickled dict
        except (json.JSONDecodeError, ValidationError) as exc:
            detail = error_lines(exc) if isinstance(exc, ValidationError) else str(exc)   # experiments[0].time
            bad.append({"line": i, "status": "failed", "error": {"type": type(exc).__name__, "detail": detail}})
    total = len(todo) + len(bad)
    print(f"greyfit batch: {len(done)} already done, {total} to do", file=sys.stderr)
    pool = LocalWorkerPool(settings.workers, settings.task_cpu_seconds, settings.task_wall_seconds)
    counts = {"finished": 0, "succeeded": 0, "flagged": 0}
    started = time.monotonic()
    with out_path.open("a") as out:
        for record in bad:
            out.write(json.dumps(record) + "\n")
            counts["finished"] += 1
        try:
            _run_batch(pool, todo, args, out, counts, total, started)
        finally:
            # a worker that met a new model structure finishes compiling it for the next run (the
            # libraries are cached on disk); the results are all written by then
            pool.shutdown(grace=BUILD_GRACE_S)
    print(file=sys.stderr)
    succeeded, flagged = counts["succeeded"], counts["flagged"]
    if total and not succeeded:   # like a job: failed when no task succeeded
        print(f"greyfit batch: all {total} requests failed; see the errors in {out_path}", file=sys.stderr)
        return 1
    if flagged:
        print(f"greyfit batch: {flagged} result(s) are {args.fail_on} or worse (--fail-on {args.fail_on})",
              file=sys.stderr)
        return 3
    return 0


def _run_batch(pool, todo: list[tuple[int, str]], args, out, counts: dict, total: int, started: float) -> None:
    """The jobs API's hand-over without the store: each worker holds about QUEUE_SECONDS of work,
    given in one message, and the outcomes of a round are written together."""
    from greyfit.service.jobs.dispatcher import MAX_QUEUED, QUEUE_SECONDS
    queue = deque(todo)
    task_seconds: float | None = None
    while queue or pool.free() < pool.capacity():
        if task_seconds is not None:
            pool.depth = 1 + max(1, min(MAX_QUEUED, int(QUEUE_SECONDS / max(task_seconds, 1e-6))))
            pool.task_seconds = task_seconds
        room = pool.free() * pool.depth + pool.queue_room()
        if queue and room:
            batch = [queue.popleft() for _ in range(min(room, len(queue)))]
            left = pool.submit_batch([(str(i), args.kind, line) for i, line in batch])
            queue.extendleft(reversed([(int(key), line) for key, _, line in left]))
        pool.wait(0.5)
        outcomes = pool.poll()
        pool.started()   # (a start matters to the job store's attempts only)
        for key, outcome in outcomes:
            if outcome.status == "not_started":   # its worker was replaced before it began
                queue.appendleft((int(key), next(line for i, line in todo if i == int(key))))
                continue
            if outcome.seconds is not None:
                task_seconds = outcome.seconds if task_seconds is None else \
                    0.8 * task_seconds + 0.2 * outcome.seconds
            if outcome.status == "succeeded" and outcome.result_json is not None:
                counts["succeeded"] += 1
                counts["flagged"] += flags_quality(outcome.result_json, args.fail_on)
                out.write(f'{{"line": {int(key)}, "status": "succeeded", "result": {outcome.result_json}}}\n')
            else:
                out.write(json.dumps({"line": int(key), **outcome.as_dict()}) + "\n")
            counts["finished"] += 1
        if outcomes:
            out.flush()
            _progress(counts["finished"], total, started)


def flags_quality(result_json: str, fail_on: str | None) -> int:
    """1 when --fail-on names the quality of this result (a fit's, or a discovery's final fit)."""
    if fail_on is None:
        return 0
    from greyfit.service.cli.commands import FAIL_ON
    result = json.loads(result_json)
    fit = result.get("fit", result)
    quality = fit.get("quality", "good")
    if quality == "good" and fit.get("success") is False:   # as schemas.text_report.effective_quality
        quality = "failed"
    return int(quality in FAIL_ON[fail_on])


def _progress(done: int, total: int, started: float) -> None:
    width = 30
    filled = int(width * done / max(total, 1))
    rate = done / max(time.monotonic() - started, 1e-9)
    sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total}  {rate:.1f} fits/s")
    sys.stderr.flush()
