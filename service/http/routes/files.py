"""POST /v1/fits/files and /v1/discover/files: a request without records, and its measurement files, as
one multipart form.

The files are read as `greyfit fit MODEL.json --data ...` reads them (solvers/data/files.py, in a
thread: pandas and scipy hold the event loop otherwise); the request they make is then checked and run
as POST /v1/fits (/v1/discover) runs its body, so the answer is the same result, or the same 422.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any, Optional

import anyio
from fastapi import APIRouter, File, Form, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError

from greyfit.schemas.files import FileColumns
from greyfit.schemas.model import Model
from greyfit.service.http.json_body import StrictJSONRoute
from greyfit.service.http.json_parsing import loads_strict, validate_strict
from greyfit.service.http.routes.sync import run_sync_request
from greyfit.service.task_kinds import KINDS, TaskKind

router = APIRouter(prefix="", route_class=StrictJSONRoute)
UPLOAD_CHUNK = 1 << 20
# the kinds whose requests take records: POST {sync_path}/files for each
FILE_KINDS = ("fit", "discover")


def _files_endpoint(kind: TaskKind):
    schema = kind.request_schema()

    async def endpoint(
            request: Request,
            fit_request: str = Form(alias="request", description=f"the {schema.__name__} as JSON, without "
                                                                 "`experiments`"),
            data: list[UploadFile] = File(description="the records to fit, one per file: .csv (with a header), "
                                                      ".parquet or MATLAB .mat (v5 or v7.3)"),
            validation: Optional[list[UploadFile]] = File(
                default=None, description="records kept for validation (not fitted)"),
            columns: str = Form(default="{}", description="FileColumns as JSON: the time column or sample rate, "
                                                          "names that differ, scales, a segment, decimation")):
        body = _parsed("request", fit_request)
        if not isinstance(body, dict):
            _refuse(("request",), f"the request must be a JSON object (a {schema.__name__} without experiments)")
        if "experiments" in body:
            _refuse(("request", "experiments"), "give the records as files (`data`), not in the request")
        spec = _validated(FileColumns, _parsed("columns", columns), "columns")
        model = _validated(Model, body.get("model"), "request", "model")
        with tempfile.TemporaryDirectory(prefix="greyfit-upload-") as folder:
            records = await _read_uploads(folder, "data", data, model, spec, True)
            if validation:
                body["validation"] = await _read_uploads(folder, "validation", validation, model, spec, False)
        body["experiments"] = records
        return await run_sync_request(request, kind.name, _validated(schema, body, "request"), check=kind.check(),
                                      count=kind.count(), elsewhere=kind.elsewhere)

    endpoint.__name__ = endpoint.__qualname__ = f"{kind.operation}_from_files"
    endpoint.__doc__ = (f"{kind.summary.split(';')[0].rstrip('.')}, from measurement files: a multipart form of "
                        "the request without experiments and one file per record.")
    return endpoint


for _kind in FILE_KINDS:
    router.add_api_route(f"{KINDS[_kind].sync_path}/files", _files_endpoint(KINDS[_kind]), methods=["POST"],
                         tags=[KINDS[_kind].tag], response_model=KINDS[_kind].result_schema(),
                         operation_id=f"{KINDS[_kind].operation}_from_files")


async def _read_uploads(folder: str, field: str, uploads: list[UploadFile], model: Model, spec: FileColumns,
                        require_outputs: bool) -> list[dict]:
    """The uploads saved under their own suffix, read as records named by their file names."""
    from greyfit.solvers.data.files import read_records
    paths, labels = [], []
    for i, upload in enumerate(uploads):
        label = Path(upload.filename or f"{field}{i}").name
        # stored under a name of ours: the user's (any characters) only names the file in messages
        path = Path(folder) / f"{field}{i}"
        with open(path, "wb") as out:
            while chunk := await upload.read(UPLOAD_CHUNK):
                out.write(chunk)
        paths.append(path)
        labels.append(label)
    records = await anyio.to_thread.run_sync(read_records, paths, model, spec, require_outputs, labels)
    return [json.loads(r.model_dump_json(exclude_unset=True)) for r in records]


def _parsed(field: str, text: str) -> Any:
    try:
        return loads_strict(text)
    except ValueError as exc:
        _refuse((field,), f"not valid JSON: {exc}")


def _validated(schema: type[BaseModel], value: Any, *where: str) -> Any:
    """`value` validated as `schema` as strictly as a JSON body; errors located under `where`."""
    try:
        return validate_strict(schema, value)
    except ValidationError as exc:
        raise RequestValidationError([{**e, "loc": (*where, *e["loc"])} for e in exc.errors()]) from None


def _refuse(loc: tuple, msg: str) -> None:
    raise RequestValidationError([{"type": "value_error", "loc": loc, "msg": msg}])
