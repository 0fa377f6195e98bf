"""What a consultation room keeps: its events in the database, and the state they fold to.

Every event (join, leave, presenter, view, display, pin, unpin, measure, unmeasure, chat)
is one row. Pins, measurements and chat are not stored separately: a room opened again folds
its rows into the current state, and a replay reads the same rows in order, so the two
can never disagree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import func, select

from miss.server.storage.db import RoomEventRow, SessionRow, UserRow, utcnow
from miss.server.storage.store import Store

#: Chat messages a late joiner receives (older ones stay in the replay).
CHAT_BACKLOG = 200


def iso(value: datetime) -> str:
    """A naive UTC time from the database as ISO 8601 with milliseconds and ``+00:00``."""
    return value.replace(tzinfo=UTC).isoformat(timespec="milliseconds")


def append(
    store: Store,
    model_id: str,
    session: int,
    kind: str,
    author: str,
    data: dict[str, Any],
    at: datetime | None = None,
) -> tuple[int, str]:
    """Store one event; returns (id, time as ISO 8601)."""
    row = RoomEventRow(
        model_id=model_id, session=session, kind=kind, author=author, data=data, at=at or utcnow()
    )
    with store.session.begin() as s:
        s.add(row)
        s.flush()
        return row.id, iso(row.at)


def next_session(store: Store, model_id: str) -> int:
    """The number of the session that starts now (one more than the last)."""
    with store.session() as s:
        last = s.scalar(
            select(func.max(RoomEventRow.session)).where(RoomEventRow.model_id == model_id)
        )
    return int(last or 0) + 1


@dataclass
class RoomState:
    """Pins and measurements by id, and the latest chat, as the room shows them."""

    pins: dict[int, dict[str, Any]] = field(default_factory=dict)
    measurements: dict[int, dict[str, Any]] = field(default_factory=dict)
    chat: list[dict[str, Any]] = field(default_factory=list)
    #: The latest ``display`` (parts shown, their opacity, the clipping), or None.
    display: dict[str, Any] | None = None

    def apply(self, event_id: int, at: str, kind: str, author: str, data: dict[str, Any]) -> None:
        """Fold one event in (the live room calls this too, after storing it)."""
        item = {"id": event_id, "author": author, "at": at, **data}
        if kind == "pin":
            self.pins[event_id] = item
        elif kind == "unpin":
            self.pins.pop(int(data.get("id", -1)), None)
        elif kind == "measure":
            self.measurements[event_id] = item
        elif kind == "unmeasure":
            self.measurements.pop(int(data.get("id", -1)), None)
        elif kind == "display":
            self.display = item
        elif kind == "chat":
            self.chat.append(item)
            del self.chat[:-CHAT_BACKLOG]

    def snapshot(
        self, shown: Callable[[dict[str, Any]], dict[str, Any]] = lambda item: item
    ) -> dict[str, Any]:
        """Pins, measurements and chat, each pin and measurement as ``shown`` makes it."""
        return {
            "pins": [shown(item) for item in self.pins.values()],
            "measurements": [shown(item) for item in self.measurements.values()],
            "chat": list(self.chat),
            "display": self.display,
        }


def load_state(store: Store, model_id: str) -> RoomState:
    """The room's state from all its stored events."""
    state = RoomState()
    kinds = ("pin", "unpin", "measure", "unmeasure", "chat", "display")
    query = (
        select(RoomEventRow)
        .where(RoomEventRow.model_id == model_id, RoomEventRow.kind.in_(kinds))
        .order_by(RoomEventRow.id)
    )
    with store.session() as s:
        for row in s.scalars(query):
            state.apply(row.id, iso(row.at), row.kind, row.author, row.data)
    return state


def events(store: Store, model_id: str, session: int | None = None) -> list[dict[str, Any]]:
    """Events in order, with times; one session's or all."""
    query = select(RoomEventRow).where(RoomEventRow.model_id == model_id)
    if session is not None:
        query = query.where(RoomEventRow.session == session)
    with store.session() as s:
        rows = list(s.scalars(query.order_by(RoomEventRow.id)))
    return [
        {
            "id": r.id,
            "session": r.session,
            "at": iso(r.at),
            "kind": r.kind,
            "author": r.author,
            "data": r.data,
        }
        for r in rows
    ]


#: Events that only say who came and went: a session of nothing else was a page visit.
PRESENCE = ("join", "leave")


def sessions(store: Store, model_id: str) -> list[dict[str, Any]]:
    """One line per past (or current) session that had a conversation (anything but
    people coming and going: every page visit opens a session): start, end, how many
    events, who."""
    out: dict[int, dict[str, Any]] = {}
    talked: set[int] = set()
    for event in events(store, model_id):
        if event["kind"] not in PRESENCE:
            talked.add(event["session"])
        entry = out.setdefault(
            event["session"],
            {"session": event["session"], "start": event["at"], "events": 0, "people": []},
        )
        entry["end"] = event["at"]
        entry["events"] += 1
        if event["author"] and event["author"] not in entry["people"]:
            entry["people"].append(event["author"])
    return [entry for n, entry in out.items() if n in talked]


def live_sessions(store: Store, sessions: set[str]) -> set[str]:
    """Those of ``sessions`` (token hashes) that are live logins of enabled accounts."""
    with store.session() as s:
        rows = s.scalars(
            select(SessionRow.id)
            .join(UserRow, UserRow.id == SessionRow.user_id)
            .where(SessionRow.id.in_(sessions), SessionRow.expires_at > utcnow())
            .where(UserRow.disabled.is_(False))
        )
        return set(rows)
