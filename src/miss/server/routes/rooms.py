"""The consultation rooms: the WebSocket ``/ws/rooms/{model}`` and, for the owner, the
record of past sessions (``/api/models/{id}/room/...``) to replay."""

from __future__ import annotations

import secrets
from typing import Annotated, Any

from fastapi import APIRouter, Query, WebSocket
from starlette.concurrency import run_in_threadpool

from miss.server import audit, shares
from miss.server.core.auth import authenticate, same_origin
from miss.server.core.deps import ModelDep, RoomsDep, StoreDep, WsConnectsDep, visible_model
from miss.server.core.errors import Gone, NotFound, Unauthorized
from miss.server.core.ratelimit import KeyedBuckets, retry_after
from miss.server.rooms import Close, Refused, Visitor, guest_name
from miss.server.rooms import record as roomlog
from miss.server.storage.store import Store

router = APIRouter(tags=["rooms"])


def admit_guest(store: Store, model_id: str, token: str, name: str) -> tuple[Visitor, Any]:
    """A share link's guest: the link must be live, cover the model and allow annotating."""
    try:
        share = shares.resolve(store, token)
    except NotFound:
        raise Refused(Close.UNAUTHORIZED, "unknown share link; check the URL.") from None
    except Gone as exc:
        raise Refused(Close.GONE, str(exc)) from None
    try:
        model = shares.granted_model(store, share, model_id)
    except NotFound:
        raise Refused(Close.NOT_FOUND, f"this link does not cover model {model_id!r}.") from None
    if not share.can_annotate:
        raise Refused(
            Close.FORBIDDEN, "this link allows viewing only; ask for one that allows annotating."
        )
    visitor = Visitor(
        key=f"s:{share.id}:{secrets.token_hex(8)}",  # this connection's own: pins are its own
        name=guest_name(name),
        guest=True,
        owner=False,
        expires=share.expires_at,
        share_id=share.id,
        volume_id=model.volume_id,
    )
    return visitor, (model.stats or {}).get("bounds_mm")


def admit_user(store: Store, ws: WebSocket, model_id: str) -> tuple[Visitor, Any]:
    """A logged-in user: the model's owner or an administrator."""
    try:
        user, session, by_cookie = authenticate(ws, store)
    except Unauthorized as exc:
        raise Refused(Close.UNAUTHORIZED, str(exc)) from None
    # Browsers send cookies with a WebSocket opened by any site: check who opened it.
    if by_cookie and not same_origin(ws):
        raise Refused(Close.FORBIDDEN, "cross-site connection refused.")
    try:
        model = visible_model(store, user, model_id)
    except NotFound:
        raise Refused(Close.NOT_FOUND, f"no model {model_id!r}.") from None
    owner = store.get_volume(model.volume_id).owner_id
    visitor = Visitor(
        key=f"u:{user.id}",
        name=user.name,
        guest=False,
        owner=user.is_admin or user.id == owner,
        expires=session.expires_at,
        user_id=user.id,
        session=session.id,
        volume_id=model.volume_id,
    )
    return visitor, (model.stats or {}).get("bounds_mm")


def admit(store: Store, ws: WebSocket, model_id: str, token: str, name: str) -> tuple[Visitor, Any]:
    """Let a guest (share-link ``token``) or a signed-in user into the model's room and log
    it in the audit log; the visitor and the model's bounds (mm). Raises Refused otherwise."""
    if token:
        visitor, bounds = admit_guest(store, model_id, token, name)
        actor = f"link:{visitor.share_id}"
    else:
        visitor, bounds = admit_user(store, ws, model_id)
        actor = visitor.name
    where = audit.address(ws)
    audit.record(store, "join_room", actor, model_id, where, name=visitor.name)
    return visitor, bounds


def too_often(ws: WebSocket, connects: KeyedBuckets) -> None:
    """Refuse a connection over its address's allowance (``MISS_WS_CONNECTS_PER_MINUTE``),
    before any database look-up: a loop reconnecting as fast as it can costs little."""
    address = ws.client.host if ws.client else ""
    wait = connects.take_or_wait(f"addr:{address}")
    if wait > 0.0:
        per_minute = connects.capacity
        raise Refused(
            Close.TOO_MANY,
            f"too many connections from your address (at most {per_minute:g} a minute); "
            f"retry in {retry_after(wait)} s.",
        )


@router.websocket("/ws/rooms/{model_id}")
async def room_socket(
    ws: WebSocket,
    model_id: str,
    store: StoreDep,
    rooms: RoomsDep,
    connects: WsConnectsDep,
    share: Annotated[str, Query(max_length=200)] = "",
    name: Annotated[str, Query(max_length=200)] = "",
) -> None:
    """Join a model's room: logged in (cookie or bearer) as its owner, or ``?share=TOKEN``
    of a link with ``can_annotate`` (``&name=`` the guest's display name). A refusal is an
    ``error`` frame, then a close: 4401 unknown credentials, 4403 not allowed, 4404 no
    such model, 4410 expired or revoked link, 4429 the room (or its places for guests,
    or the link's) full, or too many connections from the address."""
    # Accept first, so a refusal reaches the browser as words and a code, not a bare 403.
    await ws.accept()
    try:
        too_often(ws, connects)
        visitor, bounds = await run_in_threadpool(admit, store, ws, model_id, share, name)
    except Refused as refused:
        await ws.send_json({"type": "error", "code": "refused", "error": refused.reason})
        await ws.close(code=refused.code, reason=refused.reason[:120])
        return
    await rooms.run(ws, model_id, visitor, bounds)


@router.get("/api/models/{model_id}/room/sessions")
def room_sessions(model: ModelDep, store: StoreDep) -> list[dict[str, Any]]:
    """The room's sessions (periods with someone in it): start, end, events, who."""
    return roomlog.sessions(store, model.id)


@router.get("/api/models/{model_id}/room/events")
def room_events(
    model: ModelDep,
    store: StoreDep,
    session: Annotated[
        int | None, Query(ge=1, le=2**31 - 1, description="one session; default all")
    ] = None,
) -> list[dict[str, Any]]:
    """The room's events in order, with times, to replay a consultation: join, leave,
    presenter, view (the presenter's camera, once a second), pin, unpin, measure,
    unmeasure, chat."""
    return roomlog.events(store, model.id, session)
