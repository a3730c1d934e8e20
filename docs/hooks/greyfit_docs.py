"""MkDocs hooks of the greyfit docs: the package namespace for mkdocstrings, and option tables.

1. `greyfit.schemas`, `greyfit.solvers` and `greyfit.service` live in the folders `schemas/`,
   `solvers/` and `service/` (pyproject's package-dir mapping), which griffe cannot follow from
   the source tree; `on_startup` lays the installed layout out as links under build/docs-namespace,
   the `paths` mkdocstrings reads.
2. A page line `<!-- fields: greyfit.schemas.fit.FitOptions -->` becomes a table of that pydantic
   model's fields (name, type, default, meaning and bounds), read from the model and its JSON schema
   at build time, never copied by hand; nested option models get their own table after it.
   `<!-- settings: greyfit.service.settings.Settings -->` does the same for environment variables.
"""
from __future__ import annotations

import importlib
import json
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[2]
NAMESPACE = ROOT / "build" / "docs-namespace"
LAYOUT = {"greyfit": "greyfit", "greyfit/schemas": "schemas", "greyfit/solvers": "solvers",
          "greyfit/service": "service"}
MARKER = re.compile(r"^<!-- (fields|fields-only|settings): ([\w.]+) -->$", re.M)
BOUNDS = (("minimum", "≥ {}"), ("exclusiveMinimum", "> {}"), ("maximum", "≤ {}"), ("exclusiveMaximum", "< {}"),
          ("minLength", "at least {} characters"), ("maxLength", "at most {} characters"),
          ("minItems", "at least {} items"), ("maxItems", "at most {} items"))


def on_startup(command: str, dirty: bool) -> None:
    """Lay out greyfit/ as installed: its own files linked, the three subpackages linked as folders."""
    package = NAMESPACE / "greyfit"
    package.mkdir(parents=True, exist_ok=True)
    sources = {path.name: path for path in (ROOT / "greyfit").glob("*.py")}
    for stale in package.glob("*.py"):
        if stale.name not in sources:   # a module removed since the last build
            stale.unlink()
    for name, path in sources.items():
        _link(package / name, path)
    for target, source in LAYOUT.items():
        if target != "greyfit":
            _link(NAMESPACE / target, ROOT / source)


def _link(link: Path, target: Path) -> None:
    if link.is_symlink() and link.resolve() == target.resolve():
        return
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(target, target_is_directory=target.is_dir())


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    def table(match: re.Match) -> str:
        kind, dotted = match.groups()
        model = _import(dotted)
        if kind == "settings":
            return settings_table(model)
        return fields_tables(model, nested=kind == "fields")

    return MARKER.sub(table, markdown)


def _import(dotted: str) -> type[BaseModel]:
    module, _, name = dotted.rpartition(".")
    return getattr(importlib.import_module(module), name)


def fields_tables(model: type[BaseModel], nested: bool = True) -> str:
    """The model's table, then (`nested`) one table per model it holds, each once."""
    out, queue, seen = [], [model], set()
    while queue:
        current = queue.pop(0)
        if current in seen:
            continue
        seen.add(current)
        rows, inner = _rows(current, link=nested)
        anchor = current.__name__.lower()
        title = "" if current is model else f"\n#### `{current.__name__}` {{#{anchor}}}\n\n{_summary(current)}\n"
        out.append(title + "\n| field | type | default | meaning |\n|---|---|---|---|\n" + "\n".join(rows) + "\n")
        queue += inner if nested else []
    return "\n".join(out)


def _summary(model: type[BaseModel]) -> str:
    return (model.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")


def _rows(model: type[BaseModel], link: bool) -> tuple[list[str], list[type[BaseModel]]]:
    schema = model.model_json_schema()
    rows, nested = [], []
    for name, field in model.model_fields.items():
        prop = schema.get("properties", {}).get(name, {})
        subs = _nested_models(field.annotation)
        nested += subs
        kind = _type(prop, schema)
        if subs and link:
            kind = " or ".join(f"[`{s.__name__}`](#{s.__name__.lower()})" for s in subs)
            kind = f"list of {kind}" if prop.get("type") == "array" else kind
        meaning = _cell(field.description or prop.get("description", ""))
        bounds = ", ".join(fmt.format(_number(prop[key])) for key, fmt in BOUNDS if key in prop)
        if bounds:
            meaning = f"{meaning} ({bounds})" if meaning else bounds
        rows.append(f"| `{name}` | {kind} | {_default(field)} | {meaning or '—'} |")
    return rows, nested


def _nested_models(annotation: Any) -> list[type[BaseModel]]:
    """The models a field holds (itself, or inside Optional/Union/list/dict), each with a table of its own."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    found: list[type[BaseModel]] = []
    for arg in getattr(annotation, "__args__", ()):
        found += [m for m in _nested_models(arg) if m not in found]
    return found


def _type(prop: dict, schema: dict) -> str:
    if "enum" in prop:
        return " \\| ".join(f"`{json.dumps(v)}`" for v in prop["enum"])
    if "const" in prop:
        return f"`{json.dumps(prop['const'])}`"
    if "anyOf" in prop:
        return " or ".join(_type(p, schema) for p in prop["anyOf"])
    if "$ref" in prop:
        return f"`{prop['$ref'].rsplit('/', 1)[1]}`"
    kind = prop.get("type", "any")
    if kind == "array":
        return f"list of {_type(prop.get('items', {}), schema)}"
    values = prop.get("additionalProperties") or next(iter(prop.get("patternProperties", {}).values()), None)
    if kind == "object" and isinstance(values, dict):
        return f"map of name → {_type(values, schema)}"
    return {"number": "number", "integer": "integer", "string": "string", "boolean": "boolean",
            "null": "null", "object": "object"}.get(kind, kind)


def _default(field: Any) -> str:
    if field.is_required():
        return "required"
    value = field.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        return "its defaults"
    if isinstance(value, Path):
        value = str(value)
    try:
        text = json.dumps(value, ensure_ascii=False)
    except TypeError:
        text = str(value)
    return f"`{text}`" if len(text) <= 60 else f"`{text[:57]}…`"


def _number(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _cell(text: str) -> str:
    """One table cell: one line, pipes escaped, and <placeholders> kept as text outside `code`."""
    parts = " ".join(text.split()).replace("|", "\\|").split("`")
    for i in range(0, len(parts), 2):   # the even parts are outside code spans
        parts[i] = parts[i].replace("<", "&lt;").replace(">", "&gt;")
    return "`".join(parts)


def settings_table(model: type[BaseModel]) -> str:
    prefix = model.model_config.get("env_prefix", "")
    rows = []
    for name, field in model.model_fields.items():
        default = "number of cores" if name == "workers" else _default(field)
        if field.default is None:
            default = "unset"
        rows.append(f"| `{prefix}{name.upper()}` | {default} | {_cell(field.description or '') or '—'} |")
    return "| variable | default | meaning |\n|---|---|---|\n" + "\n".join(rows) + "\n"
