"""Structured logs: JSON lines with time, level, logger, message, request id and task id; warnings
through the same handler. (The lines of a real server: tests/service/test_real_server_client.py.)"""
import contextvars
import json
import logging
import re
import warnings

import pytest

from greyfit.service.http.logs import REQUEST_ID, configure_logging

KEYS = {"time", "level", "logger", "message", "request_id", "task_id"}


@pytest.fixture
def json_logs():
    handler = configure_logging("json", "INFO")
    yield
    logging.getLogger().removeHandler(handler)
    logging.captureWarnings(False)


def lines(err: str) -> list[dict]:
    return [json.loads(line) for line in err.splitlines() if line.strip()]


def test_a_line_is_one_json_object_with_the_ids(json_logs, capsys):
    log = logging.getLogger("greyfit.dispatcher")
    log.warning("task %s re-queued: %s", "job1:3", "worker lost", extra={"task_id": "job1:3"})

    def in_a_request() -> None:
        REQUEST_ID.set("req-7")
        logging.getLogger("greyfit.service").info("ready")

    contextvars.copy_context().run(in_a_request)
    log.debug("not at INFO")
    logging.getLogger("some.library").info("other libraries log at WARNING and above")
    first, second = lines(capsys.readouterr().err)
    assert set(first) == KEYS and set(second) == KEYS
    assert first["level"] == "WARNING" and first["logger"] == "greyfit.dispatcher"
    assert first["message"] == "task job1:3 re-queued: worker lost"
    assert first["task_id"] == "job1:3" and first["request_id"] is None
    assert second["request_id"] == "req-7" and second["task_id"] is None and second["level"] == "INFO"
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", first["time"])


def test_warnings_and_exceptions_are_lines_too(json_logs, capsys):
    warnings.warn("a solver's warning", RuntimeWarning, stacklevel=1)
    try:
        {}["missing"]
    except KeyError:
        logging.getLogger("greyfit.service").exception("unhandled")
    warning, error = lines(capsys.readouterr().err)
    assert warning["logger"] == "py.warnings" and "a solver's warning" in warning["message"]
    assert error["level"] == "ERROR" and "KeyError: 'missing'" in error["exception"]


def test_configuring_twice_keeps_one_handler(json_logs, capsys):
    configure_logging("json", "INFO")
    logging.getLogger("greyfit").warning("once")
    assert len(lines(capsys.readouterr().err)) == 1


def test_text_format_has_the_same_fields(capsys):
    handler = configure_logging("text", "INFO")
    try:
        logging.getLogger("greyfit.dispatcher").warning("hello", extra={"task_id": "j:0"})
    finally:
        logging.getLogger().removeHandler(handler)
        logging.captureWarnings(False)
    line = capsys.readouterr().err.strip()
    assert re.fullmatch(r"\S+ \S+ WARNING greyfit.dispatcher \[- j:0\] hello", line), line
