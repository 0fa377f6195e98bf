"""The audit log: who uploaded, viewed, downloaded, shared, revoked, logged in -- when and
from which address. Entries name things by id and de-identified name only; they never
carry patient identity or a token.
"""

from __future__ import annotations

from datetime import UTC
from typing import Any

from sqlalchemy import select
from starlette.requests import HTTPConnection

from miss.server.storage.db import AuditRow, utcnow
from miss.server.storage.store import Store

#: The actions recorded, for the API's filter and the docs.
ACTIONS = (
    "login",
    "login_failed",
    "logout",
    "upload",
    "delete",
    "generate",
    "cancel",
    "view",
    "download",
    "identity",
    "share",
    "revoke",
    "join_room",
    "user_add",
)


def address(conn: HTTPConnection) -> str:
    """The client's address as the server sees it (uvicorn applies trusted proxy headers)."""
    return conn.client.host if conn.client else ""


def record(
    store: Store,
    action: str,
    actor: str,
    target: str = "",
    where: str = "",
    **detail: Any,
) -> None:
    """Append one entry, timed now. In the server it is committed just after the response
    (``Store.appender``: a download never waits for the write lock); elsewhere at once.
    A failure to write is logged with the whole entry, never raised: an audit hiccup must
    not turn a download into an error."""
    row = AuditRow(
        at=utcnow(), action=action, actor=actor, target=target, address=where, detail=detail
    )
    store.appender.add(row)


def entries(
    store: Store, limit: int = 500, action: str | None = None, actor: str | None = None
) -> list[dict[str, Any]]:
    """The newest ``limit`` entries, oldest first, as JSON-ready dicts."""
    store.appender.flush()  # the entries of requests answered before this one
    query = select(AuditRow).order_by(AuditRow.id.desc()).limit(limit)
    if action:
        query = query.where(AuditRow.action == action)
    if actor:
        query = query.where(AuditRow.actor == actor)
    with store.session() as s:
        rows = list(s.scalars(query))
    return [as_dict(r) for r in reversed(rows)]


def as_dict(row: AuditRow) -> dict[str, Any]:
    """The audit row as JSON: ``at`` in ISO 8601 UTC, the other columns as stored."""
    return {
        "id": row.id,
        "at": row.at.replace(tzinfo=UTC).isoformat(),
        "actor": row.actor,
        "action": row.action,
        "target": row.target,
        "address": row.address,
        "detail": row.detail,
    }


def format_line(entry: dict[str, Any]) -> str:
    """One entry as a line of ``miss audit``."""
    detail = " ".join(f"{k}={v}" for k, v in entry["detail"].items())
    return (
        f"{entry['at'][:19].replace('T', ' ')}  {entry['address'] or '-':<15}  "
        f"{entry['actor']:<16}  {entry['action']:<12}  {entry['target']:<20}  {detail}".rstrip()
    )
