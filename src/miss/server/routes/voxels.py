"""``/api/volumes/{id}/voxels``: the stored (de-identified) voxels for the browser's volume
renderer, one level at a time (``miss.server.volumes.voxels`` has the format); and the share
link's answer, 404: no link offers the voxels yet.

Share links have no column for a volume right (``ShareRow`` holds booleans only and no
JSON to carry a new flag without a migration), so a guest gets 404 whatever the link.
"""

from __future__ import annotations

import gzip
import hashlib
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from miss.server.core.deps import BytesDep, SettingsDep, StoreDep, VolumeDep, rendering
from miss.server.core.errors import NotFound
from miss.server.storage.db import VolumeRow
from miss.server.storage.store import Store
from miss.server.volumes import voxels

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
    level: Annotated[
        int, Query(ge=0, le=max(voxels.LEVELS), description="0: at most 256 a side; 1: full")
    ] = 0,
) -> Response:
    """The volume's voxels at ``level``, 8-bit with the value mapping in the header
    (``real = scale * byte + offset``), the voxel-to-LPS affine of the sent grid, gzip."""
    budget = settings.voxel_budget_bytes
    tag = etag(volume, level, budget)
    headers = {"ETag": tag, "Cache-Control": KEEP, "Vary": "Accept-Encoding"}
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


@router.get("/s/{token}/voxels", include_in_schema=False)
def share_voxels(token: str) -> Response:
    """A share link never offers the voxels (yet): 404, as for a volume that is not there."""
    raise NotFound("this link shows the surfaces only; ask its owner for the scan itself.")
