"""Who is in a room: a visitor's grants, a participant's connection (its outgoing queue,
colour and rate limit), the pseudonyms others see, and the close codes and refusals."""

from __future__ import annotations

import asyncio
import hashlib
import json
import secrets
import time
from collections import deque
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from starlette.websockets import WebSocket

from miss.server.core.ratelimit import TokenBucket
from miss.server.storage.db import utcnow

MAX_MESSAGE_BYTES = 16 * 1024
RATE, BURST = 30.0, 60
#: Dropped messages within ``FLOOD_WINDOW`` seconds after which a client is cut off.
FLOOD_LIMIT, FLOOD_WINDOW = 200, 10.0
OUTBOX = 512
MAX_NAME = 40


class Close:
    """WebSocket close codes MISS uses (4000-4999 are the application's own)."""

    POLICY = 1008  # kept flooding
    TOO_BIG = 1009
    SLOW = 1013  # could not keep up with the room
    UNAUTHORIZED = 4401
    FORBIDDEN = 4403
    NOT_FOUND = 4404
    GONE = 4410
    FULL = 4429  # the room, its places for guests or the link's are taken
    TOO_MANY = 4429  # the address opened too many connections


class Refused(Exception):
    """A connection that may not join (or stay): close ``code`` with ``reason``."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code, self.reason = code, reason


class Invalid(Exception):
    """A message refused; the sender gets ``{"type": "error", "code", "error"}``."""

    def __init__(self, code: str, text: str) -> None:
        super().__init__(text)
        self.code, self.text = code, text


@dataclass(frozen=True)
class Visitor:
    """Who joins: a user (``key`` "u:<id>") or a share link's guest ("s:<share id>:<n>",
    one per connection, so guests of one link cannot remove each other's pins), and the
    grants that let them in: when any of those ends, the connection closes."""

    key: str
    name: str
    guest: bool
    owner: bool  # may remove anyone's pins
    expires: datetime | None = None  # naive UTC, like the database
    share_id: str | None = None
    user_id: str | None = None
    session: str | None = None  # the login session's token hash
    volume_id: str | None = None

    def grants(self, model_id: str) -> set[tuple[str, str]]:
        """What this connection stands on: ("session", hash), ("user", id), ("share", id),
        ("model", id), ("volume", id)."""
        found = {("model", model_id)}
        for kind, value in (
            ("session", self.session),
            ("user", self.user_id),
            ("share", self.share_id),
            ("volume", self.volume_id),
        ):
            if value:
                found.add((kind, value))
        return found


def public_key(model_id: str, key: str) -> str:
    """A participant's key (``Visitor.key``) as the others in the room see it: the same
    for the same author in this room, so a browser knows its own pins, but a digest that
    does not give away the account's id or the link's id it came from."""
    if not key.startswith(("u:", "s:")):
        return key
    digest = hashlib.sha256(f"{model_id}\0{key}".encode()).hexdigest()
    return f"p:{digest[:16]}"


def public_item(model_id: str, item: dict[str, Any]) -> dict[str, Any]:
    """A pin or measurement as sent to the room: its author's key as :func:`public_key`."""
    if isinstance(item.get("by"), str):
        return item | {"by": public_key(model_id, item["by"])}
    return item


def guest_name(raw: str) -> str:
    """A display name a guest chose, printable and short, marked as a guest's."""
    clean = "".join(ch for ch in raw if ch.isprintable()).strip()[:MAX_NAME] or "Guest"
    return f"{clean} (guest)"


class Participant:
    """One connection: its socket, outgoing queue, colour and rate limit."""

    def __init__(self, ws: WebSocket, visitor: Visitor, colour: str, model_id: str) -> None:
        self.id = secrets.token_hex(4)
        self.ws, self.visitor, self.colour = ws, visitor, colour
        self.model_id = model_id
        self.outbox: asyncio.Queue[tuple[str, Any]] = asyncio.Queue(OUTBOX)
        self.bucket = TokenBucket(BURST, RATE)
        self.dropped: deque[float] = deque()
        self.last_limit_notice = 0.0
        self.closing = False

    def public(self) -> dict[str, Any]:
        """What everyone in the room may know of this person: no account or link id."""
        v = self.visitor
        return {
            "id": self.id,
            "name": v.name,
            "colour": self.colour,
            "guest": v.guest,
            "owner": v.owner,
            "key": public_key(self.model_id, v.key),
        }

    def listed(self) -> dict[str, Any]:
        """:meth:`public` and, for the other server processes only (they count a link's
        guests too), a digest of the link it came through."""
        link = self.visitor.share_id
        return self.public() | ({"link": public_key(self.model_id, f"s:{link}")} if link else {})

    def send(self, message: dict[str, Any]) -> None:
        """Queue a frame; a reader too slow to take its frames is closed, not waited for."""
        if self.closing:
            return
        try:
            self.outbox.put_nowait(("text", json.dumps(message, separators=(",", ":"))))
        except asyncio.QueueFull:
            self.close(Close.SLOW, "your connection could not keep up with the room; reconnect.")

    def error(self, code: str, text: str) -> None:
        """Send an error frame: ``code`` for the client, ``text`` for the person."""
        self.send({"type": "error", "code": code, "error": text})

    def close(self, code: int, reason: str) -> None:
        """Send what is queued, then close with ``code``; a full queue is dropped first."""
        if self.closing:
            return
        self.closing = True
        while self.outbox.full():
            self.outbox.get_nowait()
        self.outbox.put_nowait(("close", (code, reason)))

    def expired(self) -> bool:
        """Whether this visitor's access (a share link's) has expired."""
        return self.visitor.expires is not None and self.visitor.expires <= utcnow()

    def admit(self) -> bool:
        """Rate limit: False (and a notice at most once a second) when over; a sustained
        flood closes the connection."""
        if self.bucket.take():
            return True
        now = time.monotonic()
        self.dropped.append(now)
        while self.dropped and self.dropped[0] < now - FLOOD_WINDOW:
            self.dropped.popleft()
        if len(self.dropped) > FLOOD_LIMIT:
            self.error("flood", "too many messages; the connection is closed.")
            self.close(Close.POLICY, "flooding: too many messages")
        elif now - self.last_limit_notice > 1.0:
            self.last_limit_notice = now
            self.error(
                "rate_limited",
                f"too many messages: at most {RATE:g} per second (bursts of {BURST}); "
                "messages beyond that are dropped.",
            )
        return False
