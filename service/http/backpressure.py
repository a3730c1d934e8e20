"""Back-pressure on the job store: a limit on its queued tasks, reached → 503 with Retry-After.

Without it, 20 jobs of 1 000 tasks were all accepted and the store grew without bound. The limit is
store-wide (every server sharing the store counts the same tasks). A job is refused whole, before
anything of it is stored, so nothing accepted is ever dropped: what was accepted runs, and the
refused job is sent again later. A job larger than the limit itself could never be accepted: 422.
"""
from __future__ import annotations

from fastapi import Request

from greyfit.service.http.deps import client_of
from greyfit.service.http.problems import LimitExceeded, Overloaded


def check_queue_room(request: Request, tasks: int) -> None:
    """Raise Overloaded (503 + Retry-After) if `tasks` more would take the store's queued tasks past
    GREYFIT_MAX_QUEUED_TASKS; LimitExceeded (422) if they never could.

    With GREYFIT_MAX_QUEUED_TASKS_PER_CLIENT set, a client (an API key: service.http.auth put it on the
    request) also has a limit of its own: one client filling the queue does not stop the others."""
    state = request.app.state
    limit = state.settings.max_queued_tasks
    if tasks > limit:
        raise LimitExceeded("requests", f"{tasks} requests, more than the job queue holds ({limit}, "
                            "GREYFIT_MAX_QUEUED_TASKS); split the batch")
    _check_client_room(request, tasks)
    queued = state.store.task_counts().get("queued", 0)
    if queued + tasks > limit:
        state.metrics.refused.labels("queued_tasks").inc()
        raise Overloaded(f"the job queue holds {queued} tasks and takes at most {limit} "
                         "(GREYFIT_MAX_QUEUED_TASKS); retry later: accepted jobs are not affected")


def _check_client_room(request: Request, tasks: int) -> None:
    per_client = request.app.state.settings.max_queued_tasks_per_client
    client = client_of(request)
    if not per_client or client.sees_all:   # no limit of its own, or an open server's anonymous caller
        return
    if tasks > per_client:
        raise LimitExceeded("requests", f"{tasks} requests, more than one client may queue ({per_client}, "
                            "GREYFIT_MAX_QUEUED_TASKS_PER_CLIENT); split the batch")
    queued = request.app.state.store.queued_of(client.owner)
    if queued + tasks > per_client:
        request.app.state.metrics.refused.labels("client_queued_tasks").inc()
        raise Overloaded(f"this client has {queued} tasks queued and may have at most {per_client} "
                         "(GREYFIT_MAX_QUEUED_TASKS_PER_CLIENT); retry later: its accepted jobs are not affected")
