"""Back-pressure on the job store: a limit on its queued tasks, reached → 503 with Retry-After.

Without it, 20 jobs of 1 000 tasks were all accepted and the store grew without bound. The limit is
store-wide (every server sharing the store counts the same tasks). A job is refused whole, before
anything of it is stored, so nothing accepted is ever dropped: what was accepted runs, and the
refused job is sent again later. A job larger than the limit itself could never be accepted: 422.
"""
from __future__ import annotations

from fastapi import Request

from greyfit.service.problems import LimitExceeded, Overloaded


def check_queue_room(request: Request, tasks: int) -> None:
    """Raise Overloaded (503 + Retry-After) if `tasks` more would take the store's queued tasks past
    GREYFIT_MAX_QUEUED_TASKS; LimitExceeded (422) if they never could.

    Per-client limits hook in here: with a client identity on the request (service.auth), count the
    client's own queued tasks beside the store's."""
    state = request.app.state
    limit = state.settings.max_queued_tasks
    if tasks > limit:
        raise LimitExceeded("requests", f"{tasks} requests, more than the job queue holds ({limit}, "
                            "GREYFIT_MAX_QUEUED_TASKS); split the batch")
    queued = state.store.task_counts().get("queued", 0)
    if queued + tasks > limit:
        state.metrics.refused.labels("queued_tasks").inc()
        raise Overloaded(f"the job queue holds {queued} tasks and takes at most {limit} "
                         "(GREYFIT_MAX_QUEUED_TASKS); retry later: accepted jobs are not affected")
