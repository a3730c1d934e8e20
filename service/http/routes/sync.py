"""What every synchronous route does: check the limits, refuse data too large to wait for, run, wait.

The route handlers stay one call; the size of "too large" and where to send it instead differ.
"""
from __future__ import annotations

import asyncio
from typing import Callable, TypeVar

from fastapi import HTTPException, Request, Response
from pydantic import BaseModel

from greyfit.service.http.json_body import validated_text
from greyfit.service.http.problems import Overloaded, RequestTooLarge
from greyfit.service.http.runner import outcome_or_raise
from greyfit.service.settings import Settings

M = TypeVar("M", bound=BaseModel)

DISCONNECT_POLL_SECONDS = 0.25


async def run_sync_request(request: Request, kind: str, body: M, *,
                           check: Callable[[M, Settings], None], count: Callable[[M], int],
                           elsewhere: str) -> Response:
    """Check `body` against this server's limits (422 naming the field), refuse it with 413 if its
    data carry more numbers than a synchronous request may (`elsewhere` says where to send it),
    else run it as task `kind` and answer its result."""
    settings = request.app.state.settings
    check(body, settings)
    values = count(body)
    if values > settings.sync_max_values:
        raise RequestTooLarge(f"the data carry {values} numbers; synchronous requests take at most "
                              f"{settings.sync_max_values}. {elsewhere}")
    # the body's own JSON text: validated once here, and once in the worker (tasks._parse)
    return await run_sync(request, kind, validated_text(request, body))


async def run_sync(request: Request, kind: str, payload: dict | str):
    """Hand the task to the dispatcher and wait; stop its worker if the client goes away.

    uvicorn does not cancel a handler whose client disconnected, so the wait polls for it.
    """
    state = request.app.state
    dispatcher, settings = state.dispatcher, state.settings
    if dispatcher.sync_waiting() >= settings.max_sync_queue:
        raise Overloaded(f"{dispatcher.sync_waiting()} synchronous fits are waiting for a worker "
                         f"(GREYFIT_MAX_SYNC_QUEUE); retry later or submit a job: POST /v1/jobs")
    fut = dispatcher.submit_sync(kind, payload)
    waiter = asyncio.wrap_future(fut)
    loop = asyncio.get_running_loop()
    deadline = loop.time() + settings.task_wall_seconds + 30
    try:
        while not waiter.done():
            # asyncio.wait does not cancel the waiter when it times out
            await asyncio.wait({waiter}, timeout=DISCONNECT_POLL_SECONDS)
            if waiter.done():
                break
            if await request.is_disconnected():
                dispatcher.cancel_sync(fut, kind)
                return Response(status_code=499)   # nginx's "client closed request"; nobody reads it
            if loop.time() > deadline:
                dispatcher.cancel_sync(fut, kind)
                raise HTTPException(504, "the fit did not finish in time; submit it as a job")
    except asyncio.CancelledError:   # the server cancelled the handler: free the worker too
        dispatcher.cancel_sync(fut, kind)
        raise
    if waiter.cancelled():
        raise HTTPException(503, "the fit was cancelled: the server is shutting down; retry",
                            headers={"Retry-After": str(settings.retry_after_seconds)})
    exc = waiter.exception()
    if exc is not None:               # the dispatcher stopped (shutdown) before the fit ran
        raise HTTPException(503, f"{exc}; retry", headers={"Retry-After": str(settings.retry_after_seconds)})
    return outcome_or_raise(waiter.result(), settings.retry_after_seconds)
