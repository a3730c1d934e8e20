"""Query parameters typed as the OpenAPI describes them.

An integer query parameter is written in ASCII digits with an optional minus sign. Pydantic's lax
mode, which FastAPI applies to query strings, also takes "1.0", " 1", "+1" and "1_000" (Python's
int() syntax), which the OpenAPI's `type: integer` does not describe: a client fuzzing the
description would see them accepted, and another server of the same description refuse them.
"""
from __future__ import annotations

import re
from typing import Annotated, Any

from pydantic import BeforeValidator

_INTEGER = re.compile(r"-?[0-9]+")


def _digits_only(value: Any) -> Any:
    if isinstance(value, str) and not _INTEGER.fullmatch(value):
        raise ValueError("must be an integer written in digits, e.g. 20 (no sign, spaces, point or exponent)")
    return value


QueryInt = Annotated[int, BeforeValidator(_digits_only)]
