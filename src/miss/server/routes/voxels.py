"""``/api/volumes/{id}/voxels``: the stored (de-identified) voxels for the browser's volume
renderer, one level at a time (``miss.server.volumes.voxels`` has the format); and a share
link's ``/s/{token}/voxels``, the same bytes for a link whose owner offered the scan
(``can_view_volume``; a scan flagged for burned-in text only once they confirmed it);
and ``/api/volumes/{id}/voxel``, one voxel's exact value and label (the slice views'
readout under the pointer).
"""

from __future__ import annotations

import gzip
import hashlib
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from miss.server import shares
from miss.server.core.deps import BytesDep, SettingsDep, StoreDep, VolumeDep, rendering
from miss.server.core.errors import NotFound
from miss.server.core.settings import Settings
from miss.server.storage.caches import ByteCaches
from miss.server.storage.db import VolumeRow
from miss.server.storage.store import Store
from miss.server.volumes import labelmaps, voxels

router = APIRouter(tags=["volumes"])

#: Stored volumes never change and the URL names the volume, the level and (in the ETag)
#: the format: a browser keeps the answer for a year without asking again.
KEEP = "private, max-age=31536000, immutable"
MIME = "application/vnd.miss.voxels"


def etag(volume: VolumeRow, level: int, budget_bytes: int) -> str:
    """The body's ETag: the volume, the level, the format's version and (level 1) the budget."""
    seed = f"{volume.id}/{level}/{voxels.VERSION}/{budget_bytes if level else 0}"
    return '"' + hashlib.sha256(seed.encode()).hexdigest()[:32] + '"'


def _make(store: Store, volume: VolumeRow, level: int, budget_bytes: int) -> bytes:
    scan = store.open_volume(volume.id, lazy=True)  # read a slab at a time
    hist = store.read_json(volume.id, "histogram.json")
    return voxels.encode(scan.data, scan.affine, volume.info, hist, level, budget_bytes)


LevelQuery = Annotated[
    int, Query(ge=0, le=max(voxels.LEVELS), description="0: at most 256 a side; 1: full")
]


@router.get(
    "/api/volumes/{volume_id}/voxels",
    response_class=Response,
    responses={
        200: {"content": {MIME: {}}, "description": "header length, JSON header, uint8 voxels"},
        304: {"description": "not modified (ETag)"},
        404: {"description": "no such volume, or not yours"},
    },
)
async def get_voxels(
    request: Request,
    volume: VolumeDep,
    store: StoreDep,
    caches: BytesDep,
    settings: SettingsDep,
    level: LevelQuery = 0,
) -> Response:
    """The volume's voxels at ``level``, 8-bit with the value mapping in the header
    (``real = scale * byte + offset``), the voxel-to-LPS affine of the sent grid, gzip."""
    return await _voxels(request, volume, store, caches, settings, level, KEEP)


@router.get("/s/{token}/voxels", include_in_schema=False)
async def share_voxels(
    token: str,
    request: Request,
    store: StoreDep,
    caches: BytesDep,
    settings: SettingsDep,
    level: LevelQuery = 0,
) -> Response:
    """The shared volume's voxels (a model link: its model's volume), as the owner gets
    them, only when the link's owner allowed the scan itself (else 404, as for a volume
    that is not there); never kept by a cache, as nothing of a link is."""
    share = await run_in_threadpool(shares.resolve, store, token)
    volume = await run_in_threadpool(shares.shared_volume, store, share)
    return await _voxels(request, volume, store, caches, settings, level, "no-store")


async def _voxels(
    request: Request,
    volume: VolumeRow,
    store: Store,
    caches: ByteCaches,
    settings: Settings,
    level: int,
    keep: str,
) -> Response:
    budget = settings.voxel_budget_bytes
    tag = etag(volume, level, budget)
    headers = {"ETag": tag, "Cache-Control": keep, "Vary": "Accept-Encoding"}
    if keep == "no-store":  # a link's page and files: its URL holds the token
        headers["Referrer-Policy"] = "no-referrer"
    held = request.headers.get("if-none-match", "")
    if tag in (t.strip().removeprefix("W/") for t in held.split(",")):
        return Response(status_code=304, headers=headers)
    key = ("voxels", volume.id, level, budget)

    def make() -> bytes:
        return _make(store, volume, level, budget)

    body = caches.slices.peek(key)
    if body is None:
        body = await rendering(request, caches.slices.get, key, make)
    if "gzip" not in request.headers.get("accept-encoding", ""):
        return Response(gzip.decompress(body), media_type=MIME, headers=headers)
    return Response(body, media_type=MIME, headers=headers | {"Content-Encoding": "gzip"})


Index = Annotated[int, Query(ge=0, description="0-based voxel index")]


@router.get("/api/volumes/{volume_id}/voxel")
def get_voxel(volume: VolumeDep, store: StoreDep, i: Index, j: Index, k: Index) -> dict[str, Any]:
    """One voxel's stored value (volume units: HU for CT) and, over a label map, its label
    and that label's name (``label`` 0 and ``name`` "" outside every label; both null
    without a map)."""
    scan = store.open_volume(volume.id, lazy=True)  # one chunk read
    dims = scan.data.shape
    if not (i < dims[0] and j < dims[1] and k < dims[2]):
        raise NotFound(
            f"voxel ({i}, {j}, {k}) is outside the volume's 0..{dims[0] - 1}, 0..{dims[1] - 1}, "
            f"0..{dims[2] - 1} (0-based i, j, k); pick one inside."
        )
    found = labelmaps.labels_at(store, volume.id, scan.affine, np.array([[i], [j], [k]]))
    label = None if found is None else int(found[0])
    names = {
        e["label"]: e["name"] for e in (labelmaps.info(store, volume.id) or {}).get("labels", [])
    }
    return {
        "index": [i, j, k],
        "value": float(scan.data[i, j, k]),
        "units": volume.info.get("units", ""),
        "label": label,
        "name": None if label is None else names.get(label, ""),
    }
