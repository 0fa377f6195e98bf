"""Request and response bodies of the REST API, and how rows become them."""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from dataclasses import fields as dataclass_fields
from datetime import UTC, datetime
from types import UnionType
from typing import (
    TYPE_CHECKING,
    Annotated,
    Any,
    Union,
    get_args,
    get_origin,
    get_type_hints,
    overload,
)
from urllib.parse import quote

import numpy as np
from fastapi import Request, Response
from fastapi.routing import APIRoute
from pydantic import BaseModel, ConfigDict, Field, create_model
from starlette.requests import ClientDisconnect

from miss.errors import BadParameter
from miss.export import FORMATS, WRITERS
from miss.server.core.errors import BodyTooLarge
from miss.server.storage.db import DONE, RUNNING, ModelRow, VolumeRow
from miss.server.volumes.plain import plain_notes
from miss.spec import GROUPS, JobSpec, Structure, declared, default_of, form_name

#: Largest JSON request body: the biggest real one (a job with many labels) is under 2 KB.
MAX_JSON_BYTES = 64 * 1024
_Finite = Annotated[float, Field(allow_inf_nan=False)]


class JSONRoute(APIRoute):
    """A route whose JSON body is read with a cap: over :data:`MAX_JSON_BYTES` it is a
    413 that says so, before more is read (FastAPI would hold any size in memory)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        """FastAPI's handler, wrapped to refuse a body over ``MAX_JSON_BYTES`` with 413."""
        handler = super().get_route_handler()
        if self.body_field is None:
            return handler

        async def capped(request: Request) -> Response:
            length = request.headers.get("content-length", "")
            if length.isdigit() and int(length) > MAX_JSON_BYTES:
                raise BodyTooLarge(_body_too_large(int(length)))
            body = bytearray()
            try:
                async for chunk in request.stream():
                    body += chunk
                    if len(body) > MAX_JSON_BYTES:
                        raise BodyTooLarge(_body_too_large(None))
            except ClientDisconnect:
                raise BadParameter("the request was interrupted before its end.") from None
            request._body = bytes(body)  # what request.body() returns from now on
            return await handler(request)

        return capped


def _body_too_large(size: int | None) -> str:
    sent = f" ({size} bytes)" if size is not None else ""
    return (
        f"the request body{sent} is larger than the {MAX_JSON_BYTES // 1024} KB a JSON request "
        "may have; send only the documented fields (see /docs)."
    )


def _json_type(tp: Any) -> Any:
    """The REST type of a spec field's type: tuples are JSON lists, floats finite, a
    part a nested object."""
    origin, args = get_origin(tp), get_args(tp)
    if tp is float:
        return _Finite
    if tp is Structure:
        return PartRequest
    if origin is tuple:
        return list[_json_type(args[0])]  # type: ignore[misc]
    if origin in (Union, UnionType):
        return Union[tuple(_json_type(a) for a in args)]  # noqa: UP007
    return tp


def _fields_of(cls: type) -> dict[str, Any]:
    """pydantic field definitions of a spec class: name -> (type, Field)."""
    hints = get_type_hints(cls)
    out: dict[str, Any] = {}
    for f in dataclass_fields(cls):
        about = declared(f)
        if not about.api:
            continue
        tp = _json_type(hints[f.name]) if about.json is None else about.json | None
        # the page's range, for the page (GET /openapi.json): documented, not a check
        extra: dict[str, Any] | None = {"x-form": about.form} if about.form else None
        field = Field(default_of(f), description=about.help, json_schema_extra=extra)
        out[form_name(f)] = (tp, field)
    return out


PartRequest = create_model(
    "PartRequest",
    __config__=ConfigDict(extra="forbid"),
    __doc__="One part: a threshold (level) or labels, with its name, colour and cleanup.",
    **_fields_of(Structure),
)


class _ModelForm(BaseModel):
    """The 1998 form: which volume, which density, how coarse, how much decimation.
    Its fields are generated from :mod:`miss.spec` (the same names, defaults and
    checks as ``miss convert``'s options)."""

    model_config = ConfigDict(extra="forbid")

    volume: str = Field(description="volume id (GET /api/volumes)")

    def spec(self) -> JobSpec:
        """The engine's validated spec (raises BadParameter); every format is produced."""
        values = self.model_dump(exclude={"volume"}, exclude_unset=True)
        return JobSpec.from_dict({**values, "formats": list(FORMATS)})


_ModelRequest = create_model(
    "ModelRequest",
    __base__=_ModelForm,
    **{
        name: definition
        for attr, cls in GROUPS
        if attr != "outputs"
        for name, definition in _fields_of(cls).items()
    },
)
if TYPE_CHECKING:  # to mypy, the generated form is its base (pydantic checks its fields)
    ModelRequest = _ModelForm
else:
    ModelRequest = _ModelRequest


class VolumeOut(BaseModel):
    """A stored volume: its size, spacing and value range, where it came from, and how to
    show it."""

    id: str
    name: str
    created: datetime
    dims: list[int] = Field(description="voxels (x, y, z) = (columns, rows, slices)")
    spacing: list[float] = Field(description="mm per voxel along x, y, z")
    slice_gap: float | None = Field(
        None,
        description="mm between slice planes along their normal, as MISS used them: "
        "less than spacing z when the slices are sheared (gantry tilt)",
    )
    range: list[float] = Field(description="min and max value, in the volume's units")
    modality: str
    units: str = Field(description='"HU" for CT, "" when unknown')
    series: list[dict[str, Any]]
    source_format: str
    notes: list[str]
    notes_plain: list[str] = Field(
        default_factory=list,
        description="the notes said for a person, as the volume and model pages show them",
    )
    window: dict[str, float] = Field(description="default window/level for slice images")
    presets: list[dict[str, Any]] = Field(
        description="suggested levels, the default first: bone and skin for CT, skin and "
        "tissue for MR (never bone)"
    )
    scale: dict[str, str] = Field(
        default_factory=dict,
        description='what a level measures: {"label": "Density (HU)" or "Intensity" ..., '
        '"kind": "CT" or "MR", "reason": how that was decided}',
    )
    views: dict[str, Any] = Field(description="per view: voxel axes across/down, flips, mm size")
    thumbnail: str
    owner: str = Field("", description="user name of the owner")
    burned_in_annotation: bool = Field(
        False, description="the scanner flagged text burned into the pixels (may show identity)"
    )
    deidentification: dict[str, Any] = Field(
        default_factory=dict,
        description="what was removed (attribute names only), UIDs remapped, private tags dropped",
    )
    labelmap: dict[str, Any] | None = Field(
        None,
        description="the uploaded label map: {labels: [{label, name, voxels, color}], table}; "
        "shown by GET /api/volumes/{id}, null when there is none",
    )


class IdentityOut(BaseModel):
    """The original identity of a volume, for its owner."""

    volume: str
    patient: dict[str, str] = Field(
        default_factory=dict, description="DICOM keyword -> original value"
    )
    uids: dict[str, str] = Field(
        default_factory=dict, description="original UID -> the UID MISS uses"
    )
    upload_filename: str = Field("", description="the uploaded file's name, as sent")


class ModelOut(BaseModel):
    """A surface model of a volume: the job's state and parameters, and its files once made."""

    id: str
    volume: str
    name: str | None = Field(None, description="the display name its owner gave it, if any")
    status: str = Field(description="queued | running | done | failed")
    progress: float = Field(description="0..1")
    stage: str
    params: dict[str, Any]
    stats: dict[str, Any] | None
    error: str | None
    attempts: int
    created: datetime
    started: datetime | None
    finished: datetime | None
    files: dict[str, dict[str, Any]] | None = Field(
        description="per format: url, bytes, mime, filename, description; while the job "
        "runs, the files written so far (the GLB first)"
    )
    preview: str | None = Field(
        None,
        description="while the job runs: the URL of a coarse GLB of the model, to draw until "
        "the model's own GLB is in ``files``",
    )
    lod: str | None = Field(
        None,
        description="a large model's levels of detail: the URL of its 3D Tiles 1.1 tileset "
        "(tiles are meshopt-compressed GLBs beside it), for a viewer to draw a coarse level "
        "first and refine what is in view; null for models within the budget",
    )


class SharedWithMeOut(BaseModel):
    """A share link someone else made that you opened while signed in, still valid.
    Its token is not kept, so no URL: the browser that opened it remembers it."""

    id: str = Field(description="the share link's id")
    kind: str = Field(description='"model": one model; "volume": a volume\'s models')
    name: str = Field(description="the model's name (else its volume's)")
    volume_name: str
    modality: str = Field(description='the scan\'s modality, "" when the file does not say')
    shared_by: str = Field(description="user name of who made the link")
    message: str = Field(description="what they wrote for the link's holders")
    opened: datetime = Field(description="when you last opened it")
    expires: datetime
    allows: list[str] = Field(
        description='"view", then any of "annotate", "download", "scan" (the voxels in 3-D)'
    )


@overload
def _utc(value: datetime) -> datetime: ...
@overload
def _utc(value: None) -> None: ...
def _utc(value: datetime | None) -> datetime | None:
    """The database keeps naive UTC; say so, or browsers read it as local time."""
    return value.replace(tzinfo=UTC) if value is not None else None


def volume_out(row: VolumeRow, owner: str = "") -> VolumeOut:
    """The API's view of a volume row; ``owner`` is its owner's name."""
    info = row.info
    keys = (
        "dims",
        "spacing",
        "range",
        "modality",
        "units",
        "series",
        "source_format",
        "notes",
        "window",
        "presets",
        "views",
    )
    return VolumeOut(
        id=row.id,
        name=row.name,
        created=_utc(row.created_at),
        thumbnail=f"/api/volumes/{row.id}/thumbnail.png",
        owner=owner,
        burned_in_annotation=bool(info.get("burned_in_annotation", False)),
        deidentification=info.get("deidentification", {}),
        scale=info.get("scale") or _scale_of_old(info),
        slice_gap=slice_gap(info),
        notes_plain=plain_notes(info["notes"]),
        **{k: info[k] for k in keys},
    )


def slice_gap(info: dict[str, Any]) -> float | None:
    """The distance between slice planes along their normal (mm) of a volume's ``info``:
    the volume of a voxel over the area of its in-plane face (None without an affine)."""
    affine = info.get("affine")
    if not affine:
        return None
    m = np.asarray(affine, dtype=float)[:3, :3]
    face = float(np.linalg.norm(np.cross(m[:, 0], m[:, 1])))
    return abs(float(np.linalg.det(m))) / face if face > 0 else None


def _scale_of_old(info: dict[str, Any]) -> dict[str, str]:
    """A volume stored before volumes had a ``scale``: its units and modality say it."""
    ct = info.get("units") == "HU" or str(info.get("modality", "")).upper() == "CT"
    label = "Density (HU)" if info.get("units") == "HU" else "Density" if ct else "Intensity"
    return {"label": label, "kind": "CT" if ct else "MR", "reason": "units and modality"}


def params_of(row: ModelRow) -> dict[str, Any]:
    """The job's parameters as shown to users (not its formats, region or error bound)."""
    return {k: v for k, v in row.spec.items() if k not in ("formats", "roi", "max_error")}


def model_out(row: ModelRow, volume: VolumeRow | None = None) -> ModelOut:
    """The API's view of a model row, with its files' URLs and download names (named after
    ``volume`` when given)."""
    files = None
    if row.status in (DONE, RUNNING) and row.files:
        files = {
            fmt: {
                **meta,
                "url": f"/api/models/{row.id}/model.{fmt}",
                "description": WRITERS[fmt].description,
                "label": WRITERS[fmt].label or f".{fmt}",
                "filename": download_name(volume, row, fmt) if volume else f"model.{fmt}",
            }
            for fmt, meta in row.files.items()
        }
    return ModelOut(
        id=row.id,
        volume=row.volume_id,
        name=row.name,
        status=row.status,
        progress=row.progress,
        stage=row.stage,
        params=params_of(row),
        stats=row.stats,
        error=row.error,
        attempts=row.attempts,
        created=_utc(row.created_at),
        started=_utc(row.started_at),
        finished=_utc(row.finished_at),
        files=files,
        preview=preview_url(row),
        lod=lod_url(row, f"/api/models/{row.id}"),
    )


def lod_url(row: ModelRow, base: str) -> str | None:
    """A model's tileset (written before its GLB) under ``base`` (its API or share-link path), its ETag in
    the query; None without levels of detail."""
    lod = (row.stats or {}).get("lod") if row.status in (DONE, RUNNING) else None
    return f"{base}/lod/tileset.json?v={lod['etag']}" if lod else None


def preview_url(row: ModelRow) -> str | None:
    """The running job's preview GLB, with its ETag in the query (a new one, a new URL)."""
    preview = (row.stats or {}).get("preview") if row.status == RUNNING else None
    return f"/api/models/{row.id}/preview.glb?v={preview['etag']}" if preview else None


def _number(value: float) -> str:
    return f"{value:g}".replace("+", "")


def attachment(filename: str) -> dict[str, str]:
    """The Content-Disposition header of a download, as Starlette's FileResponse writes it
    (RFC 6266: ``filename*`` when the name is not plain ASCII)."""
    quoted = quote(filename)
    if quoted != filename:
        return {"Content-Disposition": f"attachment; filename*=utf-8''{quoted}"}
    return {"Content-Disposition": f'attachment; filename="{filename}"'}


def download_name(volume: VolumeRow, row: ModelRow, fmt: str) -> str:
    """A readable file name without identity: ``demo-head_level300_bone.wrl``."""
    spec = row.spec
    structures = JobSpec.from_dict(spec).structures
    levels = structures.levels_used
    parts = [volume.slug, "levels" + "_".join(_number(v) for v in levels)]
    if len(levels) == 1:
        parts[1] = f"level{_number(levels[0])}"
    labels = structures.labels_used
    if labels is not None:
        named = "labels" + ("all" if labels == "all" else "_".join(str(n) for n in labels))
        parts[1:2] = [parts[1], named] if levels else [named]
    preset = next(
        (
            p["name"]
            for p in volume.info.get("presets", [])
            if len(levels) == 1 and p["level"] == levels[0]
        ),
        None,
    )
    if spec.get("components", "all") != "all":
        parts.append(spec["components"])
    if preset:
        parts.append(preset)
    steps = spec["sample_rate"] if isinstance(spec["sample_rate"], list) else [spec["sample_rate"]]
    if any(s != 1 for s in steps):
        parts.append("sr" + "x".join(str(s) for s in steps))
    if spec.get("start_slice") or spec.get("end_slice"):
        parts.append(f"slices{spec.get('start_slice') or 1}-{spec.get('end_slice') or 'end'}")
    if spec.get("decimate") == "none":
        parts.append("nodecimation")
    return "_".join(parts) + f".{fmt}"


def mime_for(fmt: str, accept: str) -> str:
    """The writer's type; a client asking for the 1998 VRML type by name gets that one."""
    writer = WRITERS[fmt]
    if writer.legacy_mime and writer.legacy_mime in accept:
        return writer.legacy_mime
    return writer.mime
