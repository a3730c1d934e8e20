"""`python -m greyfit.service.dask_worker tcp://host:8786`, the documented command: it runs
`greyfit.service.jobs.dask_worker`, a Dask worker that outlives its scheduler."""
from greyfit.service.jobs.dask_worker import main, serve_worker

__all__ = ["main", "serve_worker"]

if __name__ == "__main__":
    main()
