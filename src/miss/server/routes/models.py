"""``/api/models``: submit a job, follow it, download the model in every format (all but
the GLB made on their first download: :mod:`miss.server.storage.formats`)."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse, JSONResponse
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from miss.errors import BadParameter, EmptySurface
from miss.export import FORMATS, WRITERS
from miss.server import audit, quota
from miss.server.core.deps import (
    EventStreamDep,
    FollowersDep,
    JobLimitDep,
    ModelDep,
    ModelFiles,
    ModelFilesDep,
    QueueDep,
    RoomsDep,
    SettingsDep,
    StoreDep,
    UserDep,
    here_or_threadpool,
    visible_volume,
)
from miss.server.core.errors import NotFound, NotReady
from miss.server.core.ratelimit import would_queue
from miss.server.core.schemas import (
    JSONRoute,
    ModelOut,
    ModelRequest,
    attachment,
    download_name,
    mime_for,
    model_out,
)
from miss.server.jobs import follow, turn
from miss.server.storage import formats
from miss.server.storage.db import DONE, FAILED, RUNNING, ModelRow, VolumeRow
from miss.server.storage.store import LOD_DIR, PREVIEW_FILE, Store, remove_outputs
from miss.server.volumes import labelmaps
from miss.spec import JobSpec
from miss.structures.labelmap import label_counts

router = APIRouter(prefix="/api/models", tags=["models"], route_class=JSONRoute)


def check_against_volume(spec: JobSpec, volume: VolumeRow, store: Store) -> None:
    """Refuse at submit time what would only fail minutes later in the job: a level
    outside the values, slices beyond the stack, a region with no surface."""
    info = volume.info
    lo, hi = info["range"]
    units = f" {info['units']}" if info["units"] else ""
    for level in spec.structures.levels_used:
        if not lo < level < hi:
            raise EmptySurface(
                f"level {level:g} is outside this volume's values {lo:g}..{hi:g}{units}; "
                "pick a level inside that range (see the histogram's presets)."
            )
    box = spec.region.box(info["dims"])  # slices beyond the stack, too few voxels
    picked = tuple(slice(a, b + 1, s) for (a, b), s in zip(box, spec.region.steps, strict=True))
    block = store.open_volume(volume.id, lazy=True).data[picked]  # reads the region only
    bmin, bmax = float(block.min()), float(block.max())
    first, last = box[2][0] + 1, box[2][1] + 1
    for level in spec.structures.levels_used:
        if not bmin < level < bmax:
            raise EmptySurface(
                f"no surface at level {level:g} in slices {first}..{last}: they hold values "
                f"{bmin:g}..{bmax:g}{units}; pick a level inside that range or other slices."
            )


def _label_source(
    volume: VolumeRow, store: Store, wanted: str | tuple[int, ...] | None
) -> dict[str, Any] | None:
    """The stored label map a ``labels`` job reads; None when the volume is its own map.
    Refuses labels none of which the map holds (the job would only fail later)."""
    meta = labelmaps.info(store, volume.id)
    if meta is not None:
        present = sorted(int(e["label"]) for e in meta["labels"])
    else:
        counts = label_counts(store.open_volume(volume.id))
        if counts is None:
            raise BadParameter(
                "this volume has no label map: upload one (POST /api/volumes/{id}/labelmap) "
                "before asking for 'labels', or give a 'level'."
            )
        present = sorted(counts)
    if isinstance(wanted, tuple) and not set(wanted) & set(present):
        shown = ", ".join(map(str, present[:30])) + (" ..." if len(present) > 30 else "")
        raise BadParameter(
            f"none of the labels {list(wanted)[:10]} is in this volume's label map; "
            f"it holds {shown} (GET /api/volumes/{{id}} lists them with names)."
        )
    return meta


@router.post(
    "",
    status_code=202,
    response_model=ModelOut,
    responses={
        200: {"description": "the same parameters were done before: that model"},
        422: {"description": "bad parameters, or no surface at this level"},
        429: {"description": "this account already has its most jobs queued or running"},
        507: {"description": "the server's disk, or the account's quota, is full"},
    },
)
def create_model(
    body: ModelRequest,
    store: StoreDep,
    queue: QueueDep,
    user: UserDep,
    request: Request,
    jobs: JobLimitDep,
    settings: SettingsDep,
) -> JSONResponse:
    """Queue a surface job (202); identical parameters on the same volume return the
    existing model: 202 while it is queued or running, 200 once done."""
    volume = visible_volume(store, user, body.volume)
    spec = body.spec()
    check_against_volume(spec, volume, store)
    key = spec.key()
    labels = spec.structures.labels_used
    if labels is not None:
        key = labelmaps.cache_key(key, _label_source(volume, store, labels))
    store.check_free_space(settings.min_free_bytes)  # 507 while the disk is nearly full
    if would_queue(store, volume.id, key):  # a model made already costs no room
        quota.check(store, user, settings.quota_bytes)  # 507 once the account's is full
    with jobs.slot(store, user.name, volume.id, key):  # 429 when one job too many
        row, created = store.find_or_create_model(volume.id, key, spec.to_dict(), user.name)
        if created:
            where = audit.address(request)
            audit.record(store, "generate", user.name, row.id, where, volume=volume.id)
    if created:
        queue.submit()
    code = 200 if row.status == DONE else 202
    return JSONResponse(
        model_out(row, volume).model_dump(mode="json"),
        status_code=code,
        headers={"Location": f"/api/models/{row.id}"},
    )


@router.get("", response_model=list[ModelOut])
def list_models(
    store: StoreDep,
    user: UserDep,
    volume: Annotated[str | None, Query(description="only the models of this volume")] = None,
) -> list[ModelOut]:
    """Your models (an administrator's list holds everyone's)."""
    if volume is not None:
        visible_volume(store, user, volume)
    owner = None if user.is_admin else user.id
    volumes = {v.id: v for v in store.list_volumes(owner)}
    rows = store.list_models(volume, owner_id=owner)
    return [model_out(row, volumes.get(row.volume_id)) for row in rows]


@router.get("/{model_id}", response_model=ModelOut)
async def get_model(model: ModelDep, store: StoreDep) -> ModelOut:
    """A model: its job's status and progress, its parameters and statistics, and the URLs
    of its files once made. 404 when there is none you may see."""
    cached = store.cached_volume(model.volume_id) is not None
    volume = await here_or_threadpool(cached, store.get_volume, model.volume_id)
    return model_out(model, volume)


@router.delete("/{model_id}", status_code=204)
def delete_model(model: ModelDep, store: StoreDep, queue: QueueDep, rooms: RoomsDep) -> Response:
    """Delete a model (its running job is stopped); its room's connections close."""
    queue.cancel(model.id)
    store.delete_model(model.id)
    rooms.end("model", model.id)
    return Response(status_code=204)


class ModelChange(BaseModel):
    """What its owner may change of a model: its display name."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(
        max_length=200,
        description="the display name (blank: named after its parameters again)",
    )


@router.patch("/{model_id}", response_model=ModelOut)
def rename_model(model: ModelDep, body: ModelChange, store: StoreDep) -> ModelOut:
    """Give the model a display name (shown in the volume's list and on its page)."""
    name = " ".join(body.name.split()) or None  # no line breaks nor runs of spaces
    store.update_model(model.id, name=name)
    return model_out(store.get_model(model.id), store.get_volume(model.volume_id))


@router.post(
    "/{model_id}/cancel",
    response_model=ModelOut,
    responses={409: {"description": "the job has ended already"}},
)
def cancel_model(
    model: ModelDep, store: StoreDep, queue: QueueDep, user: UserDep, request: Request
) -> ModelOut:
    """Stop a queued or running job: its worker is killed, the files it wrote so far are
    removed (the account's quota and job slot are free again) and the model stays,
    failed as cancelled, to be submitted again."""
    if not queue.state.cancel(model.id, user.name):
        raise NotReady(
            f"model {model.id} is {store.get_model(model.id).status}: only a queued or running "
            "job can be cancelled; delete the model (DELETE /api/models/{id}) instead."
        )
    queue.cancel(model.id)  # here; a worker of another server process stops at its next report
    remove_outputs(store.model_dir(model.id))
    audit.record(store, "cancel", user.name, model.id, audit.address(request))
    return model_out(store.get_model(model.id), store.get_volume(model.volume_id))


@router.get("/{model_id}/events", response_class=EventSourceResponse)
async def model_events(
    model: ModelDep,
    store: StoreDep,
    _stream: EventStreamDep,
    followers: FollowersDep,
    draws: Annotated[bool, Query(description="the caller draws the model and says so")] = False,
) -> AsyncIterator[ServerSentEvent]:
    """Server-Sent Events: the model (as GET /api/models/{id}) each time its status,
    stage, progress, preview or files change, until it is done or failed; then the
    stream ends. ``draws=1`` (the model page): the caller draws the model once it can
    and posts ``/shown`` when it has; meanwhile, for a second at most, the job holds back
    its other formats and its error (:mod:`miss.server.jobs.turn`). An account holds at
    most ``MISS_SSE_PER_USER`` streams at once (429 beyond)."""
    volume = await run_in_threadpool(store.get_volume, model.volume_id)
    folder = store.model_dir(model.id)
    last = None
    async with followers.follow(store, model) as watch:  # one look for all its followers
        while True:
            version, row = watch.version, watch.row
            if row is None:
                yield ServerSentEvent(
                    data={"id": model.id, "status": FAILED, "error": "model deleted"}
                )
                return
            state = follow.shown_state(row)
            if state != last:
                last = state
                yield ServerSentEvent(data=model_out(row, volume).model_dump(mode="json"))
            if row.status in (DONE, FAILED):
                if draws:  # (it may have touched .watched as the job ended)
                    turn.done(folder)
                return
            if draws:  # a viewer follows the job: the job waits for its word
                turn.watching(folder)
            await watch.changed(version, follow.EVENT_POLL)


@router.post("/{model_id}/shown", status_code=204)
def model_shown(model: ModelDep, store: StoreDep) -> Response:
    """The viewer has drawn the running job's model (its GLB or levels of detail): the
    job goes on with its other formats and the error, which it held back meanwhile
    (:mod:`miss.server.jobs.turn`). Nothing for a model that is not running."""
    if model.status == RUNNING:
        turn.shown(store.model_dir(model.id))
    return Response(status_code=204)


@router.get(
    "/{model_id}/preview.glb",
    response_class=FileResponse,
    responses={404: {"description": "this job made no preview (a small region)"}},
)
def preview(model: ModelDep, store: StoreDep) -> FileResponse:
    """A running job's coarse GLB (every n-th voxel, decimated hard), drawn until the
    model's own GLB is written; the model's ``preview`` field links it while it runs."""
    path = store.model_dir(model.id) / PREVIEW_FILE
    if not path.is_file():
        raise NotFound(
            f"model {model.id} has no preview (small regions get none); "
            "load its model.glb once it is listed in the model's files."
        )
    # Its URL carries its ETag (``?v=``): a job run again writes a new one under a new URL.
    headers = {"Cache-Control": "private, max-age=3600"}
    return FileResponse(path, media_type=WRITERS["glb"].mime, headers=headers)


def _etag_matches(header: str | None, etag: str) -> bool:
    if not header:
        return False
    tags = [t.strip().removeprefix("W/") for t in header.split(",")]
    return "*" in tags or etag in tags


@router.head("/{model_id}/model.{fmt}", include_in_schema=False)
@router.get(
    "/{model_id}/model.{fmt}",
    response_class=FileResponse,
    responses={304: {"description": "not modified (ETag)"}, 409: {"description": "not done yet"}},
)
async def download(
    model: ModelDep, fmt: str, request: Request, files: ModelFilesDep, user: UserDep
) -> Response:
    """The model file, as an attachment with a readable name; ``Accept: x-world/x-vrml``
    gets VRML under its 1998 type."""
    store = files.store
    cached = file_in_memory(model, fmt, request, files)
    response = await here_or_threadpool(cached, model_file, model, fmt, request, files)
    if response.status_code == 200 and request.method == "GET":
        where, queued = audit.address(request), store.appender.running
        args = (store, "download", user.name, model.id, where)
        await here_or_threadpool(queued, audit.record, *args, format=fmt)
    return response


def file_in_memory(model: ModelRow, fmt: str, request: Request, files: ModelFiles) -> bool:
    """True when ``model_file`` will answer from this process's memory: the volume's row
    and the whole file (not a range of it) are cached."""
    entry = (model.files or {}).get(fmt) or {}
    etag = entry.get("etag")
    store, caches = files.store, files.caches
    return (
        etag is not None
        and not entry.get("on_request")  # made on request: its use is recorded on disk
        and "range" not in request.headers
        and store.cached_volume(model.volume_id) is not None
        and caches.model_files.peek((model.id, fmt, etag)) is not None
    )


def model_file(model: ModelRow, fmt: str, request: Request, files: ModelFiles) -> Response:
    """A model's file with type, name, ETag (304 when unchanged): for owners and links."""
    store, caches = files.store, files.caches
    if fmt not in WRITERS:
        raise NotFound(f"no format {fmt!r}; choose one of {', '.join(FORMATS)}.")
    # A running job's files are listed as soon as each is in place (the GLB first).
    if model.status not in (DONE, RUNNING) or not model.files or fmt not in model.files:
        reason = f": {model.error}" if model.status == FAILED else f" ({model.progress:.0%})"
        raise NotReady(
            f"model {model.id} is {model.status}{reason}; download it once its status is done."
        )
    tag = model.files[fmt]["etag"]
    if model.files[fmt].get("on_request"):  # made on its first download, then read
        tag = made_on_request(model, fmt, files)
    mime = mime_for(fmt, request.headers.get("accept", ""))
    etag = f'"{tag}{"-legacy" if mime != WRITERS[fmt].mime else ""}"'
    headers = {"ETag": etag, "Cache-Control": "private, max-age=86400", "Vary": "Accept"}
    if _etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    name = download_name(store.get_volume(model.volume_id), model, fmt)
    key, ranged = (model.id, fmt, tag), "range" in request.headers
    on_request = bool(model.files[fmt].get("on_request"))
    data = None if ranged or on_request else caches.model_files.peek(key)
    if data is None:
        path = store.model_dir(model.id) / f"model.{fmt}"
        if not path.is_file():
            raise NotFound(
                f"the {fmt} file of model {model.id} is missing; delete the model and submit again."
            )
        if ranged or path.stat().st_size > caches.max_file:
            return FileResponse(path, media_type=mime, filename=name, headers=headers)
        data = path.read_bytes()
        if not on_request:
            caches.model_files.put(key, data)
    return Response(data, media_type=mime, headers=headers | attachment(name))


def made_on_request(model: ModelRow, fmt: str, files: ModelFiles) -> str:
    """Make ``fmt`` of a finished model unless it is in its folder (waiting while another
    download makes it: :func:`formats.ensure`), record its size and ETag in the model's
    ``files`` the first time; its ETag."""
    store, settings = files.store, files.settings
    folder = store.model_dir(model.id)
    path, made = formats.ensure(folder, fmt, settings.format_cache_bytes)
    known = (model.files or {}).get(fmt, {}).get("etag")
    if made is None and known is None:  # made by another process; this row is older
        made = formats.describe(path.read_bytes())
    if made is not None and made["etag"] != known:
        formats.record(store, model.id, fmt, made)
    return made["etag"] if made is not None else known


#: The files of a tileset (``miss.export.tiles``): nothing else is served from lod/.
LOD_NAME = re.compile(r"tileset\.json|tiles/r[0-7]{0,12}\.glb")


@router.get(
    "/{model_id}/lod/{name:path}",
    response_class=FileResponse,
    responses={304: {"description": "not modified (ETag)"}, 404: {"description": "no such tile"}},
)
def lod_file(model: ModelDep, name: str, request: Request, store: StoreDep) -> Response:
    """A file of a large model's levels of detail: ``tileset.json`` (3D Tiles 1.1) or a
    tile it names (``tiles/r….glb``, meshopt-compressed glTF); the model's ``lod`` links it."""
    return lod_response(model, name, request, store)


def lod_response(model: ModelRow, name: str, request: Request, store: Store) -> Response:
    """One tileset file with its ETag (304 when unchanged), for owners and links alike."""
    lod = (model.stats or {}).get("lod") if model.status in (DONE, RUNNING) else None
    if lod is None:
        raise NotFound(
            f"model {model.id} has no levels of detail (only models over the server's "
            "triangle budget get them); load its model.glb."
        )
    path = store.model_dir(model.id) / LOD_DIR / name
    if not LOD_NAME.fullmatch(name) or not path.is_file():
        raise NotFound(f"model {model.id} has no tile {name!r}; its tileset.json lists them.")
    etag = f'"{lod["etag"]}-{name.replace("/", "-")}"'
    headers = {"ETag": etag, "Cache-Control": "private, max-age=86400"}
    if _etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    mime = "application/json" if name == "tileset.json" else WRITERS["glb"].mime
    return FileResponse(path, media_type=mime, headers=headers)
