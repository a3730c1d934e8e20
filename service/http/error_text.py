"""Validation errors in words a person can act on: one location syntax, no pydantic internals,
"did you mean" for a misspelt field.

Shared by the HTTP answers (service.http.problems) and the command line, so that both say
`experiments[0].time` for the same place. Standard library and pydantic only: the command line
imports it without the web stack.
"""
from __future__ import annotations

import difflib
import re
import types
from typing import Annotated, Any, Iterable, Mapping, Optional, Union, get_args, get_origin

from pydantic import BaseModel, Discriminator, Tag, ValidationError

# pydantic's labels for a member of a union in a location: `function-after[check(), FitRequest]`,
# `tagged-union[...]`, `list[float]`; the last name inside the brackets is the member
_MEMBER_LABEL = re.compile(r"^[a-z-]+\[(?:.*,\s*)?([A-Za-z_][\w]*)\]$")
# prefixes pydantic puts before the message of a ValueError or assert raised in a validator
_PREFIXES = ("Value error, ", "Assertion failed, ")
# what a strict type error means in JSON terms, and the fix
_TYPE_HINTS = {
    "float_type": "a JSON number is expected, not a string or true/false (write 500, not \"500\")",
    "int_type": "a JSON integer is expected, not a string, true/false or 2.0 (write 3, not \"3\")",
    "bool_type": "true or false is expected (not a string, not 0/1)",
    "string_type": "a JSON string is expected: put the value in double quotes",
    "finite_number": "NaN and Infinity are refused on every path (the library, the command line, each route, "
                     "the client); write null for a missing output sample, or trim the record",
}


def member_name(label: str) -> str:
    """`FitRequest` for pydantic's `function-after[_check(), FitRequest]`; other labels unchanged."""
    match = _MEMBER_LABEL.match(label)
    return match.group(1) if match else label


def location(loc: Iterable[Any], model: Optional[type[BaseModel]] = None) -> str:
    """`experiments[0].outputs.x` for pydantic's ('body', 'experiments', 0, 'outputs', 'x').

    A member of a plain union appears by its name in angle brackets (`result<FitResult>.parameters`),
    so that two members' errors about one place can be told apart without pydantic's validator
    labels; the tag of a discriminated union is left out (`model.numerator`, not
    `model.transfer_function.numerator`): the body chose the member, whose errors alone are reported.
    With the body's `model` the members are recognised by its types; without, by the brackets of
    pydantic's labels."""
    parts = list(loc)
    if parts and parts[0] == "body":
        parts = parts[1:]
    types_here: Optional[list[Any]] = [model] if model is not None else None
    out = ""
    for p in parts:
        text = str(p)
        label = _member_label(types_here, p) if types_here is not None else None
        if types_here is not None:
            types_here = [t for tp in types_here for t in _step(tp, p)]
        if label is None and ("[" in text or "(" in text):
            label = member_name(text)
        if label == "":               # a discriminated union's tag: the body chose it, so it says nothing
            continue
        if label is not None:
            out += f"<{label}>"
        elif isinstance(p, int) or text.isdigit():
            out += f"[{text}]"
        else:
            out += f".{text}" if out else text
    return out or "body"


def _member_label(types_here: list[Any], part: Any) -> Optional[str]:
    """The member's name when `part` selects a member of a union found here ("" for the tag of a
    discriminated union), else None."""
    text = str(part)
    for tp in types_here:
        if text in _tags(tp):
            return ""
        members = _members(tp)
        if len(members) > 1 and any(getattr(m, "__name__", None) == member_name(text) for m in members):
            return member_name(text)
    return None


def message(error: Mapping[str, Any], model: Optional[type[BaseModel]] = None) -> str:
    """The error's message without pydantic's prefixes, with the fix where one is known."""
    msg = error.get("msg", "invalid")
    for prefix in _PREFIXES:
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    kind = error.get("type", "")
    if kind in _TYPE_HINTS:
        return f"{msg}: {_TYPE_HINTS[kind]}"
    if kind == "extra_forbidden" and model is not None:
        loc = [p for p in error.get("loc", ()) if p != "body"]
        return unknown_field(model, loc)
    return msg


def unknown_field(model: type[BaseModel], loc: list) -> str:
    """'unknown field 'metod': did you mean 'method'?' (or the fields there, when none is close)."""
    if not loc:
        return "unknown field"
    name = str(loc[-1])
    names = sorted(known_fields(model, loc[:-1]))
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.6)
    if close:
        return f"unknown field '{name}': did you mean '{close[0]}'?"
    if names:
        return f"unknown field '{name}'; the fields here are: {', '.join(names)}"
    return f"unknown field '{name}'"


def known_fields(model: type[BaseModel], loc: list) -> set[str]:
    """The field names (and aliases) a body may have at `loc` inside `model` (all members' fields
    where the place is a union)."""
    types_here: list[Any] = [model]
    for part in loc:
        types_here = [t for tp in types_here for t in _step(tp, part)]
    names: set[str] = set()
    for tp in types_here:
        for member in _members(tp):
            if isinstance(member, type) and issubclass(member, BaseModel):
                for field_name, info in member.model_fields.items():
                    names.add(info.alias or field_name)
                    if member.model_config.get("populate_by_name"):
                        names.add(field_name)
    return names


def _members(tp: Any) -> list[Any]:
    """The concrete types behind Annotated, Optional and Union."""
    origin = get_origin(tp)
    if origin is Annotated:
        return _members(get_args(tp)[0])
    if origin is Union or origin is types.UnionType:
        return [m for arg in get_args(tp) if arg is not type(None) for m in _members(arg)]
    return [tp]


def _tags(tp: Any) -> dict[str, Any]:
    """Discriminator tags of a tagged union's members: {tag: member type}."""
    out: dict[str, Any] = {}
    origin = get_origin(tp)
    if origin is Annotated:
        inner, *meta = get_args(tp)
        tags = [m.tag for m in meta if isinstance(m, Tag)]
        for tag in tags:
            out[tag] = inner
        if not tags or any(isinstance(m, Discriminator) for m in meta):
            out.update(_tags(inner))
    elif origin is Union or origin is types.UnionType:
        for arg in get_args(tp):
            out.update(_tags(arg))
    return out


def _step(tp: Any, part: Any) -> list[Any]:
    """The types found one location part further inside `tp`."""
    text = str(part)
    tagged = _tags(tp)
    if text in tagged:
        return [tagged[text]]
    members = _members(tp)
    named = [m for m in members if getattr(m, "__name__", None) == member_name(text)]
    if named and len(members) > 1:
        return named
    out: list[Any] = []
    for member in members:
        origin, args = get_origin(member), get_args(member)
        if isinstance(member, type) and issubclass(member, BaseModel):
            for field_name, info in member.model_fields.items():
                if text in (field_name, info.alias):
                    out.append(info.annotation)
        elif origin in (list, tuple, set, frozenset) and args and isinstance(part, int):
            out.append(args[0])
        elif origin is dict and len(args) == 2:
            out.append(args[1])
    return out


def describe(errors: Iterable[Mapping[str, Any]], model: Optional[type[BaseModel]] = None) -> list[dict]:
    """[{"loc": "experiments[0].time[3]", "msg": ...}] for pydantic's errors (or FastAPI's, whose
    locations start with "body")."""
    return [{"loc": location(e.get("loc", ()), model), "msg": message(e, model)} for e in errors]


def request_model(title: str) -> Optional[type[BaseModel]]:
    """The request schema (or job body schema) of a task kind whose name is `title`: pydantic names
    a ValidationError after its model, and the task kinds' table knows them all."""
    from greyfit.service.task_kinds import KINDS
    for kind in KINDS.values():
        if kind.request.rpartition(":")[2] == title:
            return kind.request_schema()
        if kind.job_body is not None and kind.job_body.rpartition(":")[2] == title:
            return kind.job_schema()
    return None


def error_lines(exc: ValidationError) -> str:
    """A ValidationError as the HTTP answer words it, one `location: message` a line (for the CLI)."""
    errors = exc.errors(include_url=False, include_input=False, include_context=False)
    return "\n".join(f"{e['loc']}: {e['msg']}" for e in describe(errors, request_model(exc.title)))
