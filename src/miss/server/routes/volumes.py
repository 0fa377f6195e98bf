"""``/api/volumes``: upload a scan, list and delete volumes, slice images, histogram, and
the owner-only identity record."""

from __future__ import annotations

import shutil
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import FileResponse, JSONResponse
from starlette.concurrency import run_in_threadpool

from miss.errors import MissError
from miss.server import audit, quota
from miss.server.accounts import User, get_user
from miss.server.core.deps import (
    BytesDep,
    QueueDep,
    ReadingDep,
    RoomsDep,
    SettingsDep,
    StoreDep,
    UploadSlotsDep,
    UserDep,
    VolumeDep,
    rendering,
)
from miss.server.core.errors import Forbidden, NotFound
from miss.server.core.schemas import IdentityOut, VolumeOut, volume_out
from miss.server.core.settings import Settings
from miss.server.storage.db import VolumeRow
from miss.server.storage.store import Store
from miss.server.volumes import imaging, labelmaps
from miss.server.volumes.ingest import ingest
from miss.server.volumes.plain import explained
from miss.server.volumes.uploads import Pace, Upload, UploadSlots, receive

router = APIRouter(prefix="/api/volumes", tags=["volumes"])


def _multipart_body(file_description: str, **fields: str) -> dict[str, Any]:
    """OpenAPI for a streamed multipart upload (read by hand, so FastAPI can't infer it):
    a required ``file`` plus optional string ``fields`` (name -> description)."""
    properties: dict[str, Any] = {
        "file": {"type": "string", "format": "binary", "description": file_description},
        **{name: {"type": "string", "description": text} for name, text in fields.items()},
    }
    schema = {"type": "object", "required": ["file"], "properties": properties}
    return {
        "requestBody": {"required": True, "content": {"multipart/form-data": {"schema": schema}}}
    }


_UPLOAD_BODY = _multipart_body(
    "a .zip of a DICOM series (or folder tree); one .dcm or .nii/.nii.gz/.nrrd/.mha file; "
    "or several files in this field, read as one folder (the slices of a series, an "
    ".mhd with its .raw/.zraw)",
    name="name to list (default: modality, body part and series description; never the file name)",
    series="DICOM SeriesInstanceUID to read",
)


#: Window, level and threshold beyond this (volume units) are no image setting, only a way
#: to overflow the grey-value arithmetic.
VALUE_LIMIT = 1e12
_VALUE: dict[str, Any] = {"ge": -VALUE_LIMIT, "le": VALUE_LIMIT, "allow_inf_nan": False}


class Axis(StrEnum):
    """The plane of a slice: axial (z), coronal (y) or sagittal (x)."""

    axial = "axial"
    coronal = "coronal"
    sagittal = "sagittal"


def _declared(request: Request) -> int:
    """The body's declared size, bytes (0 when it declares none, or nonsense)."""
    try:
        return max(int(request.headers.get("content-length", "0")), 0)
    except ValueError:
        return 0


def upload_pace(settings: Settings) -> Pace:
    """What an upload's body must keep up (``MISS_UPLOAD_MIN_KBPS`` ...), bytes/s and s."""
    return Pace(
        settings.upload_min_kbps * 1000,
        settings.upload_rate_seconds,
        settings.upload_idle_seconds,
    )


@asynccontextmanager
async def received(
    request: Request,
    store: Store,
    settings: Settings,
    user: User,
    slots: UploadSlots,
    many: bool = False,
) -> AsyncIterator[tuple[Upload, Path]]:
    """An upload received into a fresh folder under ``tmp/`` (as one of the account's
    uploads at once, else 429; with free space, else 507), and that folder removed
    afterwards whatever happened: a stored volume was moved out of it before. ``many``:
    several files in the field ``file`` are one upload (the slices of a series)."""
    await run_in_threadpool(store.check_free_space, settings.min_free_bytes)
    await run_in_threadpool(quota.check, store, user, settings.quota_bytes, _declared(request))
    with slots.slot(user.id):
        work = await run_in_threadpool(store.tmp_dir)
        try:
            with store.disk_full_as_507():
                limit, free = settings.max_upload_bytes, settings.min_free_bytes
                pace = upload_pace(settings)
                yield await receive(request, work, limit, free, pace, many), work
        finally:
            await run_in_threadpool(shutil.rmtree, work, True)


@router.post(
    "",
    status_code=201,
    response_model=VolumeOut,
    openapi_extra=_UPLOAD_BODY,
    responses={
        413: {"description": "over the size limit, or larger than the account's quota"},
        408: {"description": "the body arrived too slowly, or stalled"},
        409: {"description": "the files hold several DICOM series: pick one of `series`"},
        415: {"description": "not a scan"},
        422: {
            "description": "a file that cannot be read: `detail` says it plainly, "
            "`technical` (when there is more) what the reader found"
        },
        507: {"description": "the server's disk, or the account's quota, is full"},
    },
)
async def upload_volume(
    request: Request,
    store: StoreDep,
    settings: SettingsDep,
    user: UserDep,
    slots: UploadSlotsDep,
    reading: ReadingDep,
) -> JSONResponse:
    """Upload a scan; it is read once (in a confined process), de-identified and stored
    for slicing and jobs."""
    async with received(request, store, settings, user, slots, many=True) as (upload, work):
        try:
            row = await run_in_threadpool(ingest, store, upload, work, reading, user.id, None, True)
        except MissError as exc:  # a reader's diagnosis, said plainly; its detail behind
            raise explained(exc, upload.filename or "the upload") from None
    await run_in_threadpool(_within_quota, store, user, settings.quota_bytes, row)
    await run_in_threadpool(
        audit.record, store, "upload", user.name, row.id, audit.address(request), name=row.name
    )
    body = volume_out(row, user.name).model_dump(mode="json")
    return JSONResponse(body, status_code=201, headers={"Location": f"/api/volumes/{row.id}"})


def _within_quota(store: Store, user: User, limit: int, row: VolumeRow) -> None:
    """Keep the new volume only if the account's use with it stays within its quota;
    otherwise remove it (it was never acknowledged) and refuse (507)."""
    used = quota.used_by(store, user) if limit > 0 else 0
    if used > limit > 0:
        store.delete_volume(row.id)
        raise quota.refusal(used, limit, "this volume would take it over")


def owner_name(store: Store, row: VolumeRow, cache: dict[str, str] | None = None) -> str:
    """The owner's user name ("" for none); ``cache`` saves look-ups over a list."""
    if row.owner_id is None:
        return ""
    cache = {} if cache is None else cache
    if row.owner_id not in cache:
        found = get_user(store, row.owner_id)
        cache[row.owner_id] = found.name if found else ""
    return cache[row.owner_id]


@router.get("", response_model=list[VolumeOut])
def list_volumes(store: StoreDep, user: UserDep) -> list[VolumeOut]:
    """Your volumes (an administrator's list holds everyone's), the newest first."""
    rows = store.list_volumes(None if user.is_admin else user.id, newest_first=True)
    names: dict[str, str] = {}
    return [volume_out(row, owner_name(store, row, names)) for row in rows]


@router.get("/{volume_id}", response_model=VolumeOut)
def get_volume(volume: VolumeDep, store: StoreDep) -> VolumeOut:
    """A volume: its size in voxels, spacing in mm, value range, source, presets and
    label map. 404 when there is none you may see."""
    out = volume_out(volume, owner_name(store, volume))
    out.labelmap = labelmaps.public(labelmaps.info(store, volume.id))
    return out


_LABELMAP_BODY = _multipart_body(
    "a label map of this volume (.nii/.nii.gz/.nrrd/.mha, whole numbers, 0 = background), "
    "e.g. TotalSegmentator output"
)


def _check_owner(volume: VolumeRow, user: User) -> None:
    """Only the owner changes a volume (an administrator, a volume nobody owns)."""
    if volume.owner_id != user.id and not (volume.owner_id is None and user.is_admin):
        raise Forbidden(f"volume {volume.id!r} is not yours; only its owner may change it.")


@router.post(
    "/{volume_id}/labelmap",
    response_model=VolumeOut,
    openapi_extra=_LABELMAP_BODY,
    responses={
        403: {"description": "not your volume"},
        422: {"description": "not a label map, or it does not overlap the volume"},
    },
)
async def upload_labelmap(
    volume: VolumeDep,
    request: Request,
    store: StoreDep,
    settings: SettingsDep,
    user: UserDep,
    slots: UploadSlotsDep,
    reading: ReadingDep,
) -> VolumeOut:
    """Lay a label map over the volume (replacing any earlier one); jobs with ``labels``
    then build its labels, resampled onto the volume's grid in patient mm."""
    _check_owner(volume, user)
    async with received(request, store, settings, user, slots) as (upload, work):
        assert upload.path is not None
        scan = await run_in_threadpool(store.open_volume, volume.id)
        labels, meta = await run_in_threadpool(
            labelmaps.read_labelmap, upload.path, scan, work, reading
        )
        await run_in_threadpool(labelmaps.save, store, volume.id, labels, meta)
    out = volume_out(volume, owner_name(store, volume))
    out.labelmap = labelmaps.public(meta)
    return out


@router.delete(
    "/{volume_id}/labelmap",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={403: {"description": "not your volume"}, 404: {"description": "no label map"}},
)
def delete_labelmap(volume: VolumeDep, store: StoreDep, user: UserDep) -> Response:
    """Remove the volume's label map (models built from it stay)."""
    _check_owner(volume, user)
    if not labelmaps.remove(store, volume.id):
        raise NotFound(f"volume {volume.id!r} has no label map.")
    return Response(status_code=204)


@router.delete("/{volume_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_volume(
    volume: VolumeDep,
    store: StoreDep,
    queue: QueueDep,
    user: UserDep,
    request: Request,
    rooms: RoomsDep,
) -> Response:
    """Delete a volume with all its models (running jobs are stopped), its identity
    record and its share links."""
    for model in store.list_models(volume.id):
        queue.cancel(model.id)
    store.delete_volume(volume.id)
    rooms.end("volume", volume.id)  # its models' rooms close
    audit.record(store, "delete", user.name, volume.id, audit.address(request), name=volume.name)
    return Response(status_code=204)


@router.get(
    "/{volume_id}/identity",
    response_model=IdentityOut,
    responses={404: {"description": "not your volume, or no identity was kept"}},
)
def identity(volume: VolumeDep, store: StoreDep, user: UserDep, request: Request) -> IdentityOut:
    """The original patient identity and UID mapping, for the volume's owner only (not
    even administrators: they run the server, they are not the patient's physician)."""
    record = store.get_identity(volume.id) if volume.owner_id == user.id else None
    if record is None or not record.data:
        raise NotFound(f"volume {volume.id!r} has no identity record of yours.")
    audit.record(store, "identity", user.name, volume.id, audit.address(request))
    return IdentityOut(volume=volume.id, **record.data)


@router.get("/{volume_id}/thumbnail.png", response_class=FileResponse)
def thumbnail(volume: VolumeDep, store: StoreDep) -> FileResponse:
    """A small preview image of the volume (PNG); 404 when there is none you may see."""
    path = store.volume_dir(volume.id) / "thumbnail.png"
    return FileResponse(
        path, media_type="image/png", headers={"Cache-Control": "private, max-age=86400"}
    )


@router.get("/{volume_id}/histogram")
def histogram(volume: VolumeDep, store: StoreDep) -> dict[str, Any]:
    """Counts per value bin (``edges`` has one more entry than ``counts``) and presets."""
    hist = store.read_json(volume.id, "histogram.json")
    edges = np.asarray(hist["edges"])
    return {
        **hist,
        "bins": ((edges[:-1] + edges[1:]) / 2).tolist(),
        "units": volume.info["units"],
        "presets": volume.info["presets"],
        "window": volume.info["window"],
    }


@router.get(
    "/{volume_id}/slices/{axis}/{index}.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}, 404: {"description": "no such slice"}},
)
async def slice_png(
    request: Request,
    volume: VolumeDep,
    store: StoreDep,
    caches: BytesDep,
    axis: Axis,
    index: int,
    window: Annotated[
        float | None,
        Query(ge=1e-6, le=VALUE_LIMIT, allow_inf_nan=False, description="width, volume units"),
    ] = None,
    level: Annotated[float | None, Query(**_VALUE, description="centre, volume units")] = None,
    threshold: Annotated[float | None, Query(**_VALUE, description="tint voxels above")] = None,
    labels: Annotated[bool, Query(description="the label map's colours laid over")] = False,
    size: Annotated[
        int, Query(ge=16, le=4096, description="longest side, pixels")
    ] = imaging.MAX_SIDE,
) -> Response:
    """One slice (0-based ``index``) with window/level, square millimetres, radiological
    orientation (see the volume's ``views``); voxels above ``threshold`` are tinted and, with
    ``labels``, each label of the volume's label map takes its colour (the one its part
    gets in a model)."""
    view = volume.info["views"][axis.value]
    if not 0 <= index < view["count"]:
        raise NotFound(f"{axis.value} slice {index} is outside 0..{view['count'] - 1} (0-based).")
    default = volume.info["window"]
    window = window or default["window"]
    level = default["level"] if level is None else level

    # the map's hash in the key: a new label map is a new picture
    sha = (labelmaps.info(store, volume.id) or {}).get("sha256") if labels else None

    def make() -> bytes:
        # lazy: only the chunks the plane crosses are read and decompressed
        scan = store.open_volume(volume.id, lazy=True)
        plane = imaging.slice_plane(scan.data, view, index)
        size_px = imaging.display_size(view, plane.shape, size)
        overlay = None
        if sha is not None:
            overlay = labelmaps.slice_overlay(
                store, volume.id, scan.affine, scan.data.shape, view, index
            )
        return imaging.render(plane, size_px, window, level, threshold, overlay)

    key = (volume.id, axis.value, index, window, level, threshold, size, sha)
    png = caches.slices.peek(key) or await rendering(request, caches.slices.get, key, make)
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})
