"""Fit workers die with their server: a `greyfit serve` killed with SIGKILL mid-fit leaves no worker
computing (before: both were still at it 150 s later, beside the restarted server's), and a server
starting on a data folder kills the workers a dead server registered there."""
import os
import signal
import subprocess
import sys

import httpx

from greyfit.service.jobs.lifeline import WorkerRegistry, start_time
from tests.servers import children_of, free_port, long_fit, start_server, stop_server, wait_gone, wait_running


def test_workers_of_a_killed_server_die_and_its_tasks_run_again(tmp_path):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(tmp_path, port, workers=2)
    restarted = None
    try:
        job = httpx.post(f"{base}/v1/jobs", json={"requests": [long_fit(), long_fit()]}, timeout=60).json()
        wait_running(base, job["id"], attempts=1)   # both fits acknowledged by their workers
        workers = {int(line.split("-")[0]) for f in (tmp_path / "workers").glob("*.pids")
                   for line in f.read_text().split()}
        assert len(workers) == 2 and workers <= children_of(server.pid)
        children = children_of(server.pid)
        os.kill(server.pid, signal.SIGKILL)
        server.wait(timeout=10)
        assert wait_gone(children) == set()

        # the job is not lost: the restarted server runs both tasks again (their second start)
        restarted = start_server(tmp_path, port, workers=2)
        tasks = wait_running(base, job["id"], attempts=2)
        assert [(t["status"], t["attempts"]) for t in tasks] == [("running", 2)] * 2
    finally:
        for proc in (server, restarted):
            if proc is not None and proc.poll() is None:
                stop_server(proc)


SLEEPER = "import time; time.sleep(120)"


def test_a_starting_server_sweeps_the_workers_a_dead_server_registered(tmp_path):
    """A worker that escaped its server's death (none should, but a sweep does not rely on it) is
    killed by the next server on the same folder; a live server's workers and other processes are not."""
    folder = tmp_path / "workers"
    # a "server" that registers a child (no parent-death signal) and is then killed
    script = (f"import subprocess, sys, time; from greyfit.service.jobs.lifeline import WorkerRegistry; "
              f"r = WorkerRegistry({str(folder)!r}); "
              f"p = subprocess.Popen([sys.executable, '-c', {SLEEPER!r}], start_new_session=True); "
              f"r.record(p.pid); print(p.pid, flush=True); time.sleep(120)")
    dead = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    orphan = int(dead.stdout.readline())
    bystander = subprocess.Popen([sys.executable, "-c", SLEEPER])
    live = WorkerRegistry(folder)   # this process plays a live server with a registered worker
    live.record(bystander.pid)
    try:
        dead.kill()
        dead.wait(timeout=10)
        assert start_time(orphan) is not None    # it outlived its server
        assert WorkerRegistry(folder).sweep() == 1
        assert wait_gone({orphan}) == set()
        assert bystander.poll() is None and live.path.exists()
        assert [f.name for f in folder.glob("*.pids")] == [live.path.name]
    finally:
        bystander.kill()
        if start_time(orphan) is not None:
            os.kill(orphan, signal.SIGKILL)
