"""A body's shape checked before it is parsed into objects: list lengths, key counts, unknown fields.

Validating a body item by item costs far more than its bytes when the items are empty: 250 000
`{}` in a job body (0.72 MB) made 500 000 "field required" errors, 8 s and 530 MB in pydantic
before the 1 000-request limit applied; an unknown field holding an object of 10^6 keys was parsed
into a Python dict (twice) to be named in an error. This pass walks the JSON text beside the body
model's types, without building it: an array of numbers (most of a large body) is skipped by one
regular expression; elsewhere each key is compared with the fields of the model found there and
each list of objects is counted. It stops at the first list longer than this server's limit, the
first object of more keys than any model has, the first unknown field (before its value is read)
or past a budget of objects, keys and strings; pydantic then validates only a body of a bounded
shape.

Standard library and pydantic only: a body-parser process runs it (service.http.json_parsing).
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Any, Optional

from pydantic import BaseModel

from greyfit.service.http.error_text import _members, _step

# at most this many keys in one object: more than any model has fields, parameters or outputs
MAX_KEYS = 10_000
# at most this many objects, arrays and strings in one array (a list of models has its own limit);
# numbers among them are not counted: a record of data with one bad value is the model's to name
MAX_ITEMS = 100_000
# objects, arrays, keys and strings in one body at most (a job of 1 000 requests holds ~50 000)
MAX_ELEMENTS = 2_000_000

_WS = re.compile(rb"[ \t\n\r]*")
_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"')
# an array of numbers (and nulls): data. One character class (the letters of null in it), which the
# regular expression engine repeats in C; an alternation with "null" was 20 times slower
_NUMBERS = re.compile(rb"\[[-+0-9.eE,\snul]*\]")
_SCALAR = re.compile(rb"-?[0-9][-+0-9.eE]*|true|false|null")


@dataclass(frozen=True)
class ListLimits:
    """Longest list of models accepted per field name (the server's settings)."""

    by_field: tuple[tuple[str, int, str], ...] = ()   # (field, limit, the setting that sets it)

    def of(self, field: str) -> Optional[tuple[int, str]]:
        return next(((n, s) for f, n, s in self.by_field if f == field), None)


class ShapeError(ValueError):
    """A body refused by its shape: `kind` "limit" (too many items or keys) or "unknown" (a field)."""

    def __init__(self, kind: str, loc: tuple, msg: str):
        super().__init__(msg)
        self.kind, self.loc, self.msg = kind, loc, msg


class _Malformed(Exception):
    """Not JSON as this walk reads it: the parser says what is wrong."""


def worth_checking(body: bytes) -> bool:
    """Whether the body holds enough objects and strings for validating it to cost more than parsing
    it (a few thousand: any fit, or a job of tens of requests). Counted at C speed."""
    return body.count(b"{") + body.count(b'"') // 2 > 5_000


def check_shape(model: type[BaseModel], body: bytes, limits: ListLimits) -> Optional[int]:
    """Raise ShapeError at the first list or object beyond its limit or unknown field; return the
    number of the body's `requests`, if it has them. A body this walk cannot read passes: the
    parser's error names the place."""
    walk = _Walk(body, limits)
    try:
        walk.value(walk.skip(0), [model], ())
    except _Malformed:
        return None
    except RecursionError:
        return None
    return walk.requests


def _models(types_here: list[Any]) -> list[type[BaseModel]]:
    return [m for tp in types_here for m in _members(tp) if isinstance(m, type) and issubclass(m, BaseModel)]


def _fields(models: list[type[BaseModel]]) -> Optional[set[str]]:
    """The keys an object of one of `models` may have, or None where any key is accepted."""
    if not models or any(m.model_config.get("extra") != "forbid" for m in models):
        return None
    names = set()
    for m in models:
        for name, info in m.model_fields.items():
            names.add(info.alias or name)
            if m.model_config.get("populate_by_name"):
                names.add(name)
    return names


class _Walk:
    def __init__(self, body: bytes, limits: ListLimits):
        self.body, self.limits = body, limits
        self.elements = 0
        self.requests: Optional[int] = None

    def skip(self, pos: int) -> int:
        return _WS.match(self.body, pos).end()   # type: ignore[union-attr]

    def count(self) -> None:
        self.elements += 1
        if self.elements > MAX_ELEMENTS:
            raise ShapeError("limit", (), f"more than {MAX_ELEMENTS} objects, arrays, keys and strings in one "
                             "body; split it into several")

    def value(self, pos: int, types_here: list[Any], loc: tuple) -> int:
        char = self.body[pos:pos + 1]
        if char == b"{":
            return self.object(pos, types_here, loc)
        if char == b"[":
            numbers = _NUMBERS.match(self.body, pos)
            return numbers.end() if numbers else self.array(pos, types_here, loc)
        match = (_STRING if char == b'"' else _SCALAR).match(self.body, pos)
        if match is None:
            raise _Malformed
        if char == b'"':
            self.count()
        return match.end()

    def object(self, pos: int, types_here: list[Any], loc: tuple) -> int:
        self.count()
        fields = _fields(_models(types_here))
        pos, keys = self.skip(pos + 1), 0
        if self.body[pos:pos + 1] == b"}":
            return pos + 1
        while True:
            key = _STRING.match(self.body, pos)
            if key is None:
                raise _Malformed
            raw = key.group()
            try:   # a key with escapes (\u0061) is the text they stand for
                name = json.loads(raw) if b"\\" in raw else raw[1:-1].decode("utf-8")
            except ValueError:
                raise _Malformed from None
            keys += 1
            self.count()
            if fields is not None and name not in fields:
                raise ShapeError("unknown", (*loc, name), "unknown field")
            if keys > MAX_KEYS:
                raise ShapeError("limit", loc, f"more than {MAX_KEYS} keys in one object")
            pos = self.skip(key.end())
            if self.body[pos:pos + 1] != b":":
                raise _Malformed
            pos = self.skip(self.value(self.skip(pos + 1), [t for tp in types_here for t in _step(tp, name)],
                                       (*loc, name)))
            if self.body[pos:pos + 1] == b"}":
                return pos + 1
            if self.body[pos:pos + 1] != b",":
                raise _Malformed
            pos = self.skip(pos + 1)

    def array(self, pos: int, types_here: list[Any], loc: tuple) -> int:
        self.count()
        field = loc[-1] if loc and isinstance(loc[-1], str) else None
        limit = self.limits.of(field) if field is not None and _models(
            [t for tp in types_here for t in _step(tp, 0)]) else None
        most, setting = limit if limit is not None else (MAX_ITEMS, "")
        pos, n = self.skip(pos + 1), 0
        if self.body[pos:pos + 1] == b"]":
            return self._counted(loc, 0, pos + 1)
        counted = 0   # items that are objects, arrays or strings: a number among numbers is data
        while True:
            n += 1
            counted += self.body[pos:pos + 1] in (b"{", b"[", b'"')
            if counted > most:
                where = f" ({setting})" if setting else ""
                raise ShapeError("limit", loc, f"more than {most} items, the limit is {most}{where}; "
                                 "split the body into several")
            pos = self.skip(self.value(pos, [t for tp in types_here for t in _step(tp, n - 1)], (*loc, n - 1)))
            if self.body[pos:pos + 1] == b"]":
                return self._counted(loc, n, pos + 1)
            if self.body[pos:pos + 1] != b",":
                raise _Malformed
            pos = self.skip(pos + 1)

    def _counted(self, loc: tuple, n: int, end: int) -> int:
        if loc == ("requests",):
            self.requests = n
        return end
