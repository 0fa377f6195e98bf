"""Request and response bodies of the REST API, and how rows become them."""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from dataclasses import fields
from datetime import UTC, datetime
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import Request, Response
from fastapi.routing import APIRoute
from pydantic import BaseModel, ConfigDict, Field
from starlette.requests import ClientDisconnect

from miss.errors import BadParameter
from miss.export import FORMATS, WRITERS
from miss.pipeline import JobSpec
from miss.server.db import DONE, ModelRow, VolumeRow
from miss.server.errors import BodyTooLarge
from miss.structures import parse_labels

_DEFAULTS = {f.name: f.default for f in fields(JobSpec)}
#: Largest JSON request body: the biggest real one (a job with many labels) is under 2 KB.
MAX_JSON_BYTES = 64 * 1024
#: Most thresholds one model may have (skin, soft tissue, bone ... each is a full surface).
MAX_LEVELS = 16
_Finite = Annotated[float, Field(allow_inf_nan=False)]


class JSONRoute(APIRoute):
    """A route whose JSON body is read with a cap: over :data:`MAX_JSON_BYTES` it is a
    413 that says so, before more is read (FastAPI would hold any size in memory)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
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


class ModelRequest(BaseModel):
    """The 1998 form: which volume, which density, how coarse, how much decimation."""

    model_config = ConfigDict(extra="forbid")

    volume: str = Field(description="volume id (GET /api/volumes)")
    level: float | None = Field(
        None,
        allow_inf_nan=False,
        description="threshold in the volume's units (HU for CT); or give 'levels'",
    )
    sample_rate: int | list[int] = Field(
        _DEFAULTS["sample_rate"], description="voxels per cube: n or [x, y, z]"
    )
    start_slice: int | None = Field(None, description="first slice, 1-based, inclusive")
    end_slice: int | None = Field(None, description="last slice, 1-based, inclusive")
    decimate: str = Field(_DEFAULTS["decimate"], description='"none", "schroeder" or "quadric"')
    error_bound: float = Field(
        _DEFAULTS["error_bound"],
        allow_inf_nan=False,
        description="local error bound, fraction of the bounding-box diagonal",
    )
    reduce: float = Field(
        _DEFAULTS["reduce"],
        allow_inf_nan=False,
        description="target fraction of triangles removed, 0 <= reduce < 1",
    )

    levels: list[_Finite] | None = Field(
        None,
        description=f"several thresholds, one structure each (a scene), e.g. [-500, 300]; "
        f"at most {MAX_LEVELS}",
    )
    components: str = Field(
        _DEFAULTS["components"], description='"all", "largest" or "split" (one part per piece)'
    )
    min_size_mm3: float = Field(
        _DEFAULTS["min_size_mm3"],
        allow_inf_nan=False,
        description="pieces smaller than this (mm³) are dropped",
    )
    smooth: int | None = Field(
        _DEFAULTS["smooth"], description="windowed-sinc smoothing iterations (keeps volume)"
    )
    passband: float = Field(
        _DEFAULTS["passband"], allow_inf_nan=False, description="smoothing passband, 0..2"
    )
    labels: str | list[int] | None = Field(
        None,
        description='label-map labels to build, one part each: "all" or ids such as [1, 4] '
        "(from the volume's uploaded label map, or the volume itself when it is one)",
    )

    def spec(self) -> JobSpec:
        """The engine's validated spec (raises BadParameter); every format is produced."""
        values = self.model_dump(exclude={"volume"})
        if values["levels"] is not None and len(values["levels"]) > MAX_LEVELS:
            raise BadParameter(
                f"{len(values['levels'])} levels is too many; a model takes at most "
                f"{MAX_LEVELS} (each is a whole surface): make several models."
            )
        if values["level"] is None:
            del values["level"]
        values["labels"] = parse_labels(values["labels"])
        return JobSpec.from_dict({**values, "formats": list(FORMATS)})


class VolumeOut(BaseModel):
    id: str
    name: str
    created: datetime
    dims: list[int] = Field(description="voxels (x, y, z) = (columns, rows, slices)")
    spacing: list[float] = Field(description="mm per voxel along x, y, z")
    range: list[float] = Field(description="min and max value, in the volume's units")
    modality: str
    units: str = Field(description='"HU" for CT, "" when unknown')
    series: list[dict[str, Any]]
    source_format: str
    notes: list[str]
    window: dict[str, float] = Field(description="default window/level for slice images")
    presets: list[dict[str, Any]] = Field(description="suggested levels: bone, skin")
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
    patient: dict[str, str] = Field(description="DICOM keyword -> original value")
    uids: dict[str, str] = Field(description="original UID -> the UID MISS uses")
    upload_filename: str = ""


class ModelOut(BaseModel):
    id: str
    volume: str
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
        description="per format: url, bytes, mime, filename"
    )


def _utc(value: datetime | None) -> datetime | None:
    """The database keeps naive UTC; say so, or browsers read it as local time."""
    return value.replace(tzinfo=UTC) if value is not None else None


def volume_out(row: VolumeRow, owner: str = "") -> VolumeOut:
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
        **{k: info[k] for k in keys},
    )


def params_of(row: ModelRow) -> dict[str, Any]:
    return {k: v for k, v in row.spec.items() if k not in ("formats", "roi", "max_error")}


def model_out(row: ModelRow, volume: VolumeRow | None = None) -> ModelOut:
    files = None
    if row.status == DONE and row.files:
        files = {
            fmt: {
                **meta,
                "url": f"/api/models/{row.id}/model.{fmt}",
                "filename": download_name(volume, row, fmt) if volume else f"model.{fmt}",
            }
            for fmt, meta in row.files.items()
        }
    return ModelOut(
        id=row.id,
        volume=row.volume_id,
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
    )


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
    levels = spec.get("levels") or ([spec["level"]] if spec.get("level") is not None else [])
    parts = [volume.slug, "levels" + "_".join(_number(v) for v in levels)]
    if len(levels) == 1:
        parts[1] = f"level{_number(levels[0])}"
    if spec.get("labels") is not None:
        labels = spec["labels"]
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
