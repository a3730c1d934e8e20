"""Structured logs: one JSON object a line, with the request and task each line is about.

    {"time": "2026-12-01T17:40:02.123Z", "level": "WARNING", "logger": "greyfit.dispatcher",
     "message": "task 3f..:0 re-queued: ...", "request_id": null, "task_id": "3f..:0"}

The request id is the one the answer carries (X-Request-ID header, `request_id` of an error body):
set per request by the app's outermost middleware in a context variable, so every line logged
while the request is handled (uvicorn's access line too) names it. A task id comes with the log
call (`extra={"task_id": key}`) or from TASK_ID. Python warnings go through the same handler
(logging.captureWarnings), not the interpreter's last-resort printer without time or level.
"""
from __future__ import annotations

import json
import logging
import sys
import time
from contextvars import ContextVar
from typing import Literal, Optional

REQUEST_ID: ContextVar[Optional[str]] = ContextVar("greyfit_request_id", default=None)
TASK_ID: ContextVar[Optional[str]] = ContextVar("greyfit_task_id", default=None)

# uvicorn's loggers: handed to the root handler so that their lines are JSON as well
SERVER_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access", "uvicorn.asgi")
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s [%(request_id)s %(task_id)s] %(message)s"


class JsonLines(logging.Formatter):
    """A record as one JSON object: time (UTC, ISO 8601, ms), level, logger, message, request_id,
    task_id (null when the line is about none), exception (when there is one)."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {"time": _utc(record.created), "level": record.levelname, "logger": record.name,
                 "message": record.getMessage(), **ids(record)}
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        elif record.stack_info:
            entry["stack"] = record.stack_info
        return json.dumps(entry, default=str, ensure_ascii=False)


class TextLines(logging.Formatter):
    """The same fields as plain text, for a person at a terminal (GREYFIT_LOG_FORMAT=text)."""

    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT)

    def format(self, record: logging.LogRecord) -> str:
        for key, value in ids(record).items():
            setattr(record, key, value or "-")
        return super().format(record)


class _CurrentStderr(logging.StreamHandler):
    """Writes to whatever sys.stderr is when a line is written (test runners swap it)."""

    def __init__(self) -> None:
        super().__init__()

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


def ids(record: logging.LogRecord) -> dict[str, Optional[str]]:
    """The record's request and task ids: given with the call (`extra=`), else the context's."""
    request_id = record.__dict__.get("request_id") or REQUEST_ID.get()
    task_id = record.__dict__.get("task_id") or TASK_ID.get()
    return {"request_id": request_id, "task_id": task_id}


def _utc(created: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(created)) + f".{int(created % 1 * 1000):03d}Z"


def configure_logging(fmt: Literal["json", "text"] = "json", level: str = "INFO") -> logging.Handler:
    """One handler on the root logger (replacing the one a previous call installed): greyfit's
    loggers at `level`, other libraries at WARNING, uvicorn's lines through the same handler,
    Python warnings as log lines. Returns the handler."""
    root = logging.getLogger()
    for old in [h for h in root.handlers if isinstance(h, _CurrentStderr)]:
        root.removeHandler(old)
    handler = _CurrentStderr()
    handler.setFormatter(JsonLines() if fmt == "json" else TextLines())
    root.addHandler(handler)
    if root.level == logging.NOTSET or root.level > logging.WARNING:
        root.setLevel(logging.WARNING)
    logging.getLogger("greyfit").setLevel(level.upper())
    for name in SERVER_LOGGERS:
        server = logging.getLogger(name)
        server.handlers.clear()
        server.propagate = True
    logging.captureWarnings(True)
    return handler
