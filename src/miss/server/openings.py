"""Who opened which share link: a signed-in colleague who opens a link sent to them finds
it again under "Shared with me" in their library, for as long as the link is valid.

Only accounts leave a trace here, and only on links they do not own: a guest without an
account stays the anonymous holder of a token (the audit log's ``link:<id>``). The
token itself is not kept (``shares`` stores its hash), so the list names links by id;
the browser that opened one remembers its address.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.dialects import postgresql, sqlite

from miss.server import shares
from miss.server.accounts import User
from miss.server.core.errors import NotFound
from miss.server.storage.db import ShareOpeningRow, ShareRow, utcnow
from miss.server.storage.store import Store


def record(store: Store, share: ShareRow, user: User | None) -> None:
    """Note that ``user`` opened ``share`` now (again: only the time changes). Nothing for
    a guest without an account (``None``) or for the link's owner."""
    if user is None or user.id == share.owner_id:
        return
    now = utcnow()
    dialect = postgresql if store.engine.dialect.name == "postgresql" else sqlite
    # One statement, so two tabs opening the same link at once cannot collide.
    upsert = (
        dialect.insert(ShareOpeningRow)
        .values(share_id=share.id, user_id=user.id, opened_at=now)
        .on_conflict_do_update(index_elements=["share_id", "user_id"], set_={"opened_at": now})
    )
    with store.session.begin() as s:
        s.execute(upsert)


def opened_by(store: Store, user: User) -> list[dict[str, Any]]:
    """The links ``user`` opened that still open (not revoked, not expired, what they
    share still there), the latest opened first; never the owner's id nor the token."""
    now = utcnow()
    query = (
        select(ShareOpeningRow.opened_at, ShareRow)
        .join(ShareRow, ShareRow.id == ShareOpeningRow.share_id)
        .where(
            ShareOpeningRow.user_id == user.id,
            ShareRow.revoked_at.is_(None),
            ShareRow.expires_at > now,
        )
        .order_by(ShareOpeningRow.opened_at.desc(), ShareOpeningRow.share_id.desc())
    )
    with store.session() as s:
        found = [(opened, share) for opened, share in s.execute(query)]
    out = []
    for opened, share in found:
        entry = _entry(store, share, opened)
        if entry is not None:
            out.append(entry)
    return out


def _entry(store: Store, share: ShareRow, opened: datetime) -> dict[str, Any] | None:
    """One line of the list, or None when what the link shares is gone."""
    try:
        if share.model_id is not None:
            model = store.get_model(share.model_id)
            volume = store.get_volume(model.volume_id)
            name = model.name or volume.name
        else:
            volume = store.get_volume(share.volume_id or "")
            name = volume.name
    except NotFound:
        return None
    return {
        "id": share.id,
        "kind": "model" if share.model_id is not None else "volume",
        "name": name,
        "volume_name": volume.name,
        "modality": str(volume.info.get("modality") or ""),
        "shared_by": shares.shared_by(store, share),
        "message": share.message,
        "opened": opened.replace(tzinfo=UTC),
        "expires": share.expires_at.replace(tzinfo=UTC),
        "allows": allows(share),
    }


def allows(share: ShareRow) -> list[str]:
    """What the link lets its holder do, in words: ``view`` always, then ``annotate``
    (the room: pins, chat, measure), ``download`` (model files), ``scan`` (the voxels)."""
    granted = [
        ("annotate", share.can_annotate),
        ("download", share.can_download),
        ("scan", share.can_view_volume),
    ]
    return ["view"] + [word for word, given in granted if given]
