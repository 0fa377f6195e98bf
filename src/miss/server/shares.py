"""Share links: a random token that opens one model (or one volume's models) without an
account, for a while, with exactly the permissions written on it.

The token is 256 random bits (``secrets.token_urlsafe(32)``) shown once, in the link; the
database stores its SHA-256 only, so neither a database copy nor the list of links can
open anything. Expiry and revocation are checked on every use, so both act at once.
"""

from __future__ import annotations

import secrets
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import select, update

from miss.errors import BadParameter
from miss.server.accounts import User, get_user, token_hash
from miss.server.core.errors import Conflict, Gone, NotFound
from miss.server.storage.db import DONE, ModelRow, ShareRow, VolumeRow, utcnow
from miss.server.storage.store import Store, new_id

TOKEN_BYTES = 32
MIN_SECONDS = 60
MAX_SECONDS = 90 * 24 * 3600
DEFAULT_SECONDS = 7 * 24 * 3600


def create(
    store: Store,
    owner: User,
    *,
    model_id: str | None,
    volume_id: str | None,
    expires_in: int,
    can_download: bool,
    can_annotate: bool,
    label: str,
    message: str = "",
    can_view_volume: bool = False,
) -> tuple[ShareRow, str]:
    """A new link for exactly one of ``model_id`` / ``volume_id``; returns (row, token).
    ``can_view_volume``: the scan itself in the guest's 3-D view (the caller has checked
    that its owner confirmed a scan flagged for burned-in text: :func:`volume_offer`)."""
    if (model_id is None) == (volume_id is None):
        raise BadParameter('name exactly one of "model" or "volume" to share.')
    if not MIN_SECONDS <= expires_in <= MAX_SECONDS:
        raise BadParameter(
            f"expires_in {expires_in} s is out of range; use {MIN_SECONDS} s to "
            f"{MAX_SECONDS // 86400} days ({MAX_SECONDS} s)."
        )
    token = secrets.token_urlsafe(TOKEN_BYTES)
    row = ShareRow(
        id=new_id(),
        token_hash=token_hash(token),
        owner_id=owner.id,
        model_id=model_id,
        volume_id=volume_id,
        label=label.strip()[:200],
        message=message.strip()[:1000],
        can_download=can_download,
        can_annotate=can_annotate,
        can_view_volume=can_view_volume,
        expires_at=utcnow() + timedelta(seconds=expires_in),
    )
    with store.session.begin() as s:
        s.add(row)
    return row, token


def status(row: ShareRow, now: datetime | None = None) -> str:
    """``"active"``, ``"expired"`` or ``"revoked"``."""
    if row.revoked_at is not None:
        return "revoked"
    return "expired" if row.expires_at <= (now or utcnow()) else "active"


def resolve(store: Store, token: str) -> ShareRow:
    """The live link of a token; NotFound for no such link, Gone once expired or revoked."""
    with store.session() as s:
        row = s.scalars(select(ShareRow).where(ShareRow.token_hash == token_hash(token))).first()
    if row is None:
        raise NotFound("this share link does not exist; check that it was copied whole.")
    state = status(row)
    if state == "revoked":
        raise Gone("this share link was revoked by the person who shared it.")
    if state == "expired":
        raise Gone(f"this share link expired on {_when(row.expires_at)}.")
    return row


def _when(value: datetime) -> str:
    return value.replace(tzinfo=UTC).strftime("%Y-%m-%d %H:%M UTC")


def get(store: Store, share_id: str) -> ShareRow:
    """The share with id ``share_id``; NotFound (404) when there is none."""
    with store.session() as s:
        row = s.get(ShareRow, share_id)
    if row is None:
        raise NotFound(f"no share {share_id!r}; GET /api/shares lists yours.")
    return row


def list_for(
    store: Store, user: User, model_id: str | None = None, volume_id: str | None = None
) -> list[ShareRow]:
    """The links ``user`` made (every link for an administrator), newest first."""
    query = select(ShareRow).order_by(ShareRow.created_at.desc())
    if not user.is_admin:
        query = query.where(ShareRow.owner_id == user.id)
    if model_id is not None:
        query = query.where(ShareRow.model_id == model_id)
    if volume_id is not None:
        query = query.where(ShareRow.volume_id == volume_id)
    with store.session() as s:
        return list(s.scalars(query))


def revoke(store: Store, share_id: str) -> None:
    """Revoke now (idempotent: a second revoke keeps the first time)."""
    with store.session.begin() as s:
        s.execute(
            update(ShareRow)
            .where(ShareRow.id == share_id, ShareRow.revoked_at.is_(None))
            .values(revoked_at=utcnow())
        )


def models(store: Store, share: ShareRow) -> list[ModelRow]:
    """The models a link shows: its model, or the finished models of its volume."""
    if share.model_id is not None:
        return [store.get_model(share.model_id)]
    assert share.volume_id is not None
    return [m for m in store.list_models(share.volume_id) if m.status == DONE]


def granted_model(store: Store, share: ShareRow, model_id: str | None) -> ModelRow:
    """The model a link may show: the one named (it must be covered), else its first."""
    if model_id is None:
        found = models(store, share)
        if not found:
            raise NotFound("the shared volume has no finished model yet; try again later.")
        return found[-1]
    row = store.get_model(model_id) if _covers(store, share, model_id) else None
    if row is None:
        raise NotFound(f"no model {model_id!r} in this share link.")
    return row


def _covers(store: Store, share: ShareRow, model_id: str) -> bool:
    if share.model_id is not None:
        return share.model_id == model_id
    try:
        return store.get_model(model_id).volume_id == share.volume_id
    except NotFound:
        return False


def shared_volume(store: Store, share: ShareRow) -> VolumeRow:
    """The volume whose voxels a link offers: NotFound unless its owner allowed it."""
    if not share.can_view_volume:
        raise NotFound("this link shows the surfaces only; ask its owner for a link with the scan.")
    volume_id = share.volume_id or store.get_model(share.model_id or "").volume_id
    return store.get_volume(volume_id)


def volume_offer(volume: VolumeRow, confirmed: bool) -> None:
    """Refuse (Conflict) to offer a scan flagged for burned-in text to guests unless its
    owner has looked and confirmed: such pixels may show a name or a date of birth that
    de-identifying the header cannot remove."""
    if (volume.info or {}).get("burned_in_annotation") and not confirmed:
        raise Conflict(
            "this scan is flagged for text burned into its pixels (it may show the patient's "
            "name or dates): look at its slices, then make the link again with "
            '"burned_in_confirmed": true, or share the surfaces only.'
        )


def shared_by(store: Store, share: ShareRow) -> str:
    """The name of the share's owner, or "a former user" when the account is gone."""
    owner = get_user(store, share.owner_id)
    return owner.name if owner else "a former user"


def as_dict(row: ShareRow, store: Store | None = None, guest: bool = False) -> dict[str, Any]:
    """A link as the API lists it: never its token (not kept) -- the URL is shown once.
    ``guest``: as the link's holder sees it, without the owner's ``label`` (a note for
    the owner: "for Dr X, re. Mrs Y"), with the ``message`` written for them."""
    out: dict[str, Any] = {
        "id": row.id,
        "model": row.model_id,
        "volume": row.volume_id,
        **({} if guest else {"label": row.label}),
        "message": row.message,
        "can_download": row.can_download,
        "can_annotate": row.can_annotate,
        "can_view_volume": row.can_view_volume,
        "created": row.created_at.replace(tzinfo=UTC).isoformat(),
        "expires": row.expires_at.replace(tzinfo=UTC).isoformat(),
        "revoked": row.revoked_at.replace(tzinfo=UTC).isoformat() if row.revoked_at else None,
        "status": status(row),
    }
    if store is not None:
        out["shared_by"] = shared_by(store, row)
    return out
