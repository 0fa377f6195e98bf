"""One model's room: the people in it here and on other server processes, the presenter
and the state its events fold to."""

from __future__ import annotations

import asyncio
import math
from typing import Any

from miss.server.rooms import record as roomlog
from miss.server.rooms.people import (
    BURST,
    MAX_MESSAGE_BYTES,
    RATE,
    Close,
    Invalid,
    Participant,
    public_item,
    public_key,
)

COLOURS = (
    "#e6194b",
    "#3cb44b",
    "#4363d8",
    "#f58231",
    "#911eb4",
    "#42d4f4",
    "#f032e6",
    "#9a6324",
    "#469990",
    "#808000",
)


class Room:
    """The people in one model's room and what they have left there."""

    def __init__(
        self,
        model_id: str,
        session: int,
        state: roomlog.RoomState,
        bounds: Any,
        writing: asyncio.Lock,
    ) -> None:
        self.model_id, self.session, self.state = model_id, session, state
        self.bounds = bounds  # [[min x, y, z], [max x, y, z]] in mm, or None when unknown
        self.people: dict[str, Participant] = {}
        #: People in this room on other server processes (``Participant.public()``), and
        #: the process (bus origin) each is on.
        self.remote: dict[str, dict[str, Any]] = {}
        self.remote_on: dict[str, str] = {}
        self.presenter: str | None = None
        self.view: dict[str, Any] | None = None  # the presenter's latest camera, for late joiners
        self.last_view = 0.0
        self.writing = writing  # the model's, shared with its other sessions (Hub.writing)

    def colour(self) -> str:
        """A colour for a newcomer: the first not in use, else one in turn."""
        used = {p.colour for p in self.people.values()}
        free = [c for c in COLOURS if c not in used]
        return free[0] if free else COLOURS[len(self.people) % len(COLOURS)]

    def broadcast(self, message: dict[str, Any], skip: Participant | None = None) -> None:
        """Send ``message`` to everyone here but ``skip``; those whose access has expired are
        told so and closed instead."""
        for person in list(self.people.values()):
            if person is skip:
                continue
            if person.expired():
                person.error("expired", "your access to this room has expired.")
                person.close(Close.GONE, "access expired")
            else:
                person.send(message)

    def welcome(self, you: Participant) -> dict[str, Any]:
        """The first frame a newcomer gets: the people, the presenter and view, the model's
        bounds, the room's limits and its items."""
        return {
            "type": "welcome",
            "model": self.model_id,
            "session": self.session,
            "you": you.public(),
            "participants": [p.public() for p in self.people.values()]
            + [unlisted(p) for p in self.remote.values()],
            "presenter": self.presenter,
            "view": self.view if self.presenter else None,
            "bounds": self.bounds,
            "limits": {"max_bytes": MAX_MESSAGE_BYTES, "rate": RATE, "burst": BURST},
            **self.state.snapshot(lambda item: public_item(self.model_id, item)),
        }

    def guests(self, link: str | None = None) -> int:
        """Guests here and on other processes; only those of ``link`` (a share id) if given."""
        tag = link and public_key(self.model_id, f"s:{link}")
        here = [p.visitor for p in self.people.values() if p.visitor.guest]
        there = [p for p in self.remote.values() if p.get("guest")]
        if link is None:
            return len(here) + len(there)
        return sum(v.share_id == link for v in here) + sum(p.get("link") == tag for p in there)

    def on_model(self, p: list[float], name: str) -> list[float]:
        """Refuse a point far from this model: most likely meant for another one."""
        if self.bounds is None:
            return p
        lo, hi = self.bounds
        margin = 0.05 * math.dist(lo, hi) + 1.0
        outside = max(max(lo[i] - p[i], p[i] - hi[i], 0.0) for i in range(3))
        if outside > margin:
            raise Invalid(
                "off_model",
                f"{name} lies {outside:.0f} mm outside this model; pins and measurements "
                "must be on its surface (is it meant for another model?).",
            )
        return p


def unlisted(entry: dict[str, Any]) -> dict[str, Any]:
    """A person listed by another process as the people here see them (no link digest)."""
    return {k: v for k, v in entry.items() if k != "link"}
