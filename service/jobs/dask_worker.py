"""A Dask worker that outlives its scheduler: `python -m greyfit.service.dask_worker tcp://host:8786`.

A `dask worker` ends when it loses its scheduler (distributed's Worker closes itself and its nanny),
so after a scheduler restart a cluster has no workers until something starts new ones, and greyfit's
jobs wait. This runs the same nanny and worker, and when they end because the scheduler went away,
starts them again: the new worker waits for the scheduler (retrying the connection) and registers
with it when it is back. SIGTERM or SIGINT stops it for good.
"""
from __future__ import annotations

import argparse
import asyncio
import logging
import signal
from typing import Optional, Sequence

log = logging.getLogger("greyfit.dask_worker")
RESTART_PAUSE = 1.0   # after the worker ended, before the next one is started


async def serve_worker(address: str, nthreads: int, stop: asyncio.Event, memory_limit: str = "auto") -> int:
    """Run a nanny-managed Dask worker for `address`, started again each time it ends, until `stop`.

    Parameters
    ----------
    address : str
        The scheduler's address, e.g. ``tcp://10.0.0.5:8786``.
    nthreads : int
        Threads of the worker (one per core suits fits: each is single-threaded).
    stop : asyncio.Event
        Set to stop for good (the signal handlers set it).
    memory_limit : str
        The nanny's memory limit (distributed's syntax: "auto", "4GB", ...).

    Returns
    -------
    int
        How many times a worker was started.
    """
    from distributed import Nanny

    starts = 0
    while not stop.is_set():
        starts += 1
        try:
            async with Nanny(address, nthreads=nthreads, memory_limit=memory_limit,
                             dashboard_address=None) as nanny:
                finished = asyncio.ensure_future(nanny.finished())
                stopping = asyncio.ensure_future(stop.wait())
                await asyncio.wait({finished, stopping}, return_when=asyncio.FIRST_COMPLETED)
                stopping.cancel()
                if stop.is_set():
                    await nanny.close()
                    finished.cancel()
                    break
        except Exception as exc:   # e.g. the nanny could not start its worker: try again
            log.warning("the Dask worker failed (%s: %s); starting another", type(exc).__name__, exc)
        if not stop.is_set():
            log.warning("the Dask worker ended (its scheduler was lost?); starting another that waits for it")
            try:
                await asyncio.wait_for(stop.wait(), RESTART_PAUSE)
            except asyncio.TimeoutError:
                pass
    return starts


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m greyfit.service.dask_worker", description=__doc__.splitlines()[0])
    parser.add_argument("scheduler", help="the scheduler's address, e.g. tcp://10.0.0.5:8786")
    parser.add_argument("--nthreads", type=int, default=1, help="threads of the worker (default 1)")
    parser.add_argument("--memory-limit", default="auto", help="the nanny's memory limit (default auto)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")

    async def run() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await serve_worker(args.scheduler, args.nthreads, stop, args.memory_limit)

    asyncio.run(run())


if __name__ == "__main__":
    main()
