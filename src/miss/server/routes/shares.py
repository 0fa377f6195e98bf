"""Share links: ``/api/shares`` for their owners, and ``/s/{token}`` -- the page, its
model description and the model's files -- for whoever holds the link.

A link authenticates only the ``/s/{token}`` routes and the room of its model; it is no
session, so it opens no ``/api`` route: no listing, no other model, no upload.
"""

from __future__ import annotations

import html
from datetime import UTC
from string import Template
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import HTMLResponse, JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from miss import __version__
from miss.errors import BadParameter
from miss.export import WRITERS
from miss.server import audit, openings, shares
from miss.server.accounts import User
from miss.server.core import assets
from miss.server.core.auth import page_user
from miss.server.core.deps import (
    ModelFiles,
    ModelFilesDep,
    RoomsDep,
    StoreDep,
    UserDep,
    visible_model,
    visible_volume,
)
from miss.server.core.errors import Forbidden, Gone, MissError, NotFound, NotReady, status_of
from miss.server.core.schemas import (
    JSONRoute,
    SharedWithMeOut,
    lod_url,
    params_of,
    slice_gap,
)
from miss.server.routes.models import lod_response, model_file
from miss.server.routes.pages import WEB
from miss.server.storage.db import DONE, FAILED, ModelRow, ShareRow, VolumeRow
from miss.server.storage.store import Store
from miss.server.volumes.plain import plain_notes

router = APIRouter(tags=["shares"], route_class=JSONRoute)
#: Share pages must not leak their URL (the token) to anything they link to, nor be kept
#: by a shared cache.
PRIVATE = {"Referrer-Policy": "no-referrer", "Cache-Control": "no-store"}
GUEST_ERROR = "this model could not be made; the person who shared it can see why."


class ShareRequest(BaseModel):
    """A share link to make: of one model or of a volume's models, what it allows, and for
    how long."""

    model_config = ConfigDict(extra="forbid")

    model: str | None = Field(None, description="model id to share")
    volume: str | None = Field(None, description="or a volume id: the volume's models")
    expires_in: int = Field(shares.DEFAULT_SECONDS, description="seconds until the link expires")
    can_download: bool = Field(False, description="model files may be downloaded")
    can_annotate: bool = Field(False, description="may join the room: pins, chat, measure")
    can_view_volume: bool = Field(
        False, description="may show the scan itself (its de-identified voxels) in 3-D"
    )
    burned_in_confirmed: bool = Field(
        False,
        description="the owner looked at a scan flagged for burned-in text and offers it anyway",
    )
    label: str = Field(
        "", max_length=200, description="a note for yourself (who it is for); guests never see it"
    )
    message: str = Field(
        "", max_length=1000, description="a message for the link's guests, shown on its page"
    )


@router.post("/api/shares", status_code=201)
def create_share(body: ShareRequest, store: StoreDep, user: UserDep, request: Request) -> Any:
    """Make a link; the answer's ``url`` (``/s/{token}``) is shown this once: only a hash
    of the token is kept."""
    if (body.model is None) == (body.volume is None):  # before any look-up: say this first
        raise BadParameter('name exactly one of "model" or "volume" to share.')
    if body.model is not None:
        model = visible_model(store, user, body.model)
        volume = store.get_volume(model.volume_id)
    if body.volume is not None:
        volume = visible_volume(store, user, body.volume)
    if body.can_view_volume:
        shares.volume_offer(volume, body.burned_in_confirmed)
    row, token = shares.create(
        store,
        user,
        model_id=body.model,
        volume_id=body.volume,
        expires_in=body.expires_in,
        can_download=body.can_download,
        can_annotate=body.can_annotate,
        can_view_volume=body.can_view_volume,
        label=body.label,
        message=body.message,
    )
    target = body.model or body.volume or ""
    audit.record(store, "share", user.name, target, audit.address(request), share=row.id)
    out = shares.as_dict(row, store) | {"url": f"/s/{token}"}
    return JSONResponse(out, status_code=201, headers={"Location": f"/api/shares/{row.id}"})


@router.get("/api/shares")
def list_shares(
    store: StoreDep,
    user: UserDep,
    model: Annotated[str | None, Query(description="only links to this model")] = None,
    volume: Annotated[str | None, Query(description="only links to this volume")] = None,
) -> list[dict[str, Any]]:
    """Your links (an administrator sees all), newest first; never their tokens."""
    return [shares.as_dict(r, store) for r in shares.list_for(store, user, model, volume)]


@router.get("/api/shared-with-me", response_model=list[SharedWithMeOut])
def shared_with_me(store: StoreDep, user: UserDep) -> list[dict[str, Any]]:
    """Links others made that you opened while signed in and that still open, the latest
    opened first; who made each by name only."""
    return openings.opened_by(store, user)


def _own_share(store: Store, user: User, share_id: str) -> ShareRow:
    row = shares.get(store, share_id)
    if not (user.is_admin or row.owner_id == user.id):
        raise NotFound(f"no share {share_id!r}; GET /api/shares lists yours.")
    return row


@router.delete("/api/shares/{share_id}", status_code=204)
async def revoke_share(
    share_id: str, store: StoreDep, user: UserDep, request: Request, rooms: RoomsDep
) -> Response:
    """Revoke a link: its page, files and room close to it at once."""
    row = await run_in_threadpool(_own_share, store, user, share_id)
    await run_in_threadpool(shares.revoke, store, row.id)
    await rooms.revoke_share(row.id)
    where = audit.address(request)
    await run_in_threadpool(audit.record, store, "revoke", user.name, row.id, where)
    return Response(status_code=204)


# -- what a link opens ---------------------------------------------------------------------


def gone_page(exc: MissError) -> HTMLResponse:
    """A plain page for a link that is unknown (404), expired or revoked (410)."""
    code = status_of(exc)
    title = "This link is no longer valid" if code == 410 else "This link does not exist"
    page = Template((WEB / "share-gone.html").read_text(encoding="utf-8"))
    body = page.substitute(title=html.escape(title), message=html.escape(str(exc)))
    return HTMLResponse(body, status_code=code, headers=PRIVATE)


@router.get("/s/{token}", include_in_schema=False)
def share_page(token: str, store: StoreDep, request: Request) -> Response:
    """The viewer for what the link shares, without an account."""
    try:
        share = shares.resolve(store, token)
    except (NotFound, Gone) as exc:
        return gone_page(exc)
    target = share.model_id or share.volume_id or ""
    audit.record(store, "view", f"link:{share.id}", target, audit.address(request))
    openings.record(store, share, page_user(request, store))
    return assets.page("model.html", headers=PRIVATE)


def provenance(model: ModelRow, volume: VolumeRow) -> dict[str, Any]:
    """How the model was made, without identity: the worker's record, or (for models made
    before it kept one) what the database still knows."""
    kept = (model.stats or {}).get("provenance")
    if kept:
        return dict(kept)
    return {
        "software": f"MISS {__version__}",
        "parameters": params_of(model),
        "source": volume.slug,
        "source_sha256": volume.info.get("source_sha256", ""),
        "modality": volume.info.get("modality", ""),
    }


def model_entry(model: ModelRow, volume: VolumeRow, share: ShareRow, token: str) -> dict[str, Any]:
    """One shared model as the share page needs it; files limited to what the link allows."""
    files = {}
    if model.status == DONE and model.files:
        for fmt, meta in model.files.items():
            if fmt == "glb" or share.can_download:
                url = f"/s/{token}/models/{model.id}/model.{fmt}"
                files[fmt] = {"url": url, "bytes": meta["bytes"], "mime": meta["mime"],
                              "description": WRITERS[fmt].description,
                              "label": WRITERS[fmt].label or f".{fmt}"}  # fmt: skip
    stats = {k: v for k, v in (model.stats or {}).items() if k != "provenance"}
    return {
        "id": model.id,
        "status": model.status,
        "progress": model.progress,
        "stage": model.stage,
        # The reason is the owner's to read (it may name the server's folders or the
        # scan's problems); a link's guests learn only that the model could not be made.
        "error": GUEST_ERROR if model.error else None,
        "params": params_of(model),
        "stats": stats,
        "provenance": provenance(model, volume),
        "files": files,
        "lod": lod_url(model, f"/s/{token}/models/{model.id}"),
        "created": model.created_at.replace(tzinfo=UTC).isoformat(),
    }


@router.get("/s/{token}/info")
def share_info(token: str, store: StoreDep, request: Request) -> JSONResponse:
    """Who shared what until when, the volume (de-identified) and its model(s). A
    signed-in holder's opening is noted (their "Shared with me")."""
    share = shares.resolve(store, token)
    openings.record(store, share, page_user(request, store))
    found = shares.models(store, share)
    volume = store.get_volume(share.volume_id or found[0].volume_id)
    info = volume.info
    body = {
        "share": shares.as_dict(share, store, guest=True),
        "volume": {
            "name": volume.name,
            "modality": info.get("modality", ""),
            "dims": info.get("dims"),
            "spacing": info.get("spacing"),
            "slice_gap": slice_gap(info),
            "notes": info.get("notes", []),
            "notes_plain": plain_notes(info.get("notes", [])),
            "burned_in_annotation": bool(info.get("burned_in_annotation", False)),
            "source_sha256": info.get("source_sha256", ""),
        },
        "models": [model_entry(m, volume, share, token) for m in found],
    }
    return JSONResponse(body, headers=PRIVATE)


@router.head("/s/{token}/model.{fmt}", include_in_schema=False)
@router.get("/s/{token}/model.{fmt}")
def share_default_file(token: str, fmt: str, request: Request, files: ModelFilesDep) -> Response:
    """The shared model's file (a volume link: its newest finished model)."""
    return _share_file(files, request, token, fmt, None)


@router.head("/s/{token}/models/{model_id}/model.{fmt}", include_in_schema=False)
@router.get("/s/{token}/models/{model_id}/model.{fmt}")
def share_file(
    token: str, model_id: str, fmt: str, request: Request, files: ModelFilesDep
) -> Response:
    """One file of a model the link covers: the GLB always (the viewer draws it), every
    other format only when the link allows downloads."""
    return _share_file(files, request, token, fmt, model_id)


@router.get("/s/{token}/models/{model_id}/lod/{name:path}")
def share_lod_file(
    token: str, model_id: str, name: str, request: Request, store: StoreDep
) -> Response:
    """A file of the levels of detail of a model the link covers (a view-only link too:
    the viewer draws them)."""
    share = shares.resolve(store, token)
    model = shares.granted_model(store, share, model_id)
    response = lod_response(model, name, request, store)
    response.headers.update(PRIVATE)
    return response


def _share_file(
    files: ModelFiles, request: Request, token: str, fmt: str, model_id: str | None
) -> Response:
    store = files.store
    share = shares.resolve(store, token)
    model = shares.granted_model(store, share, model_id)
    if fmt != "glb" and fmt in WRITERS and not share.can_download:
        raise Forbidden(
            f"this link allows viewing only, not downloading .{fmt}; ask for a link with downloads."
        )
    if model.status == FAILED:  # the reason is the owner's (``model_entry``)
        raise NotReady(f"{GUEST_ERROR} ({model.id})")
    response = model_file(model, fmt, request, files)
    response.headers.update(PRIVATE)  # revoked means gone: no copy kept by a cache
    if response.status_code == 200 and request.method == "GET":
        actor = f"link:{share.id}"
        audit.record(store, "download", actor, model.id, audit.address(request), format=fmt)
    return response
