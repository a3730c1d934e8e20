"""The job machinery: the job store, the dispatcher thread, the executors (local worker processes
or a Dask cluster) and what a worker runs. It knows nothing of HTTP (an import-linter contract):
a task's end crosses the process boundary as an `Outcome` (jobs/outcome.py), and the HTTP edge
turns it into an answer."""
