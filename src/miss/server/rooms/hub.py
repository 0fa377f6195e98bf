"""Live consultation rooms: one per model, joined over a WebSocket by its owner (or an
administrator) or by a share link that allows annotation.

The server relays and checks; the browsers draw. Positions travel in patient LPS
millimetres, so a participant in VRML mode and one in GLB mode point at the same anatomy.
Every message is JSON text of at most ``MAX_MESSAGE_BYTES``; each connection has a token
bucket (``BURST`` at once, ``RATE`` per second). Bad input gets an ``error`` frame naming
the problem and the connection stays; a client that keeps flooding, whose link expires or
is revoked, or that reads too slowly is closed with a code saying why. Nobody else in the
room notices any of it.

Each participant has an outgoing queue drained by its own task, so one slow browser
never holds up a broadcast to the others.

Places: guests fill at most ``max_people - reserved`` of a room, and at most
``per_link`` through one link, so the guests of one leaked link cannot lock out the
owner, the administrators or the guests of the owner's other links. What people see of
each other is display names, colours and a per-room pseudonym (:func:`public_key`): never
an account's id or another link's id.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import math
import secrets
import threading
import time
import weakref
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocket, WebSocketDisconnect

from miss.server.core.ratelimit import TokenBucket
from miss.server.rooms import record as roomlog
from miss.server.storage.db import utcnow
from miss.server.storage.store import Store

log = logging.getLogger("miss.server.rooms")

MAX_MESSAGE_BYTES = 16 * 1024
RATE, BURST = 30.0, 60
#: Dropped messages within ``FLOOD_WINDOW`` seconds after which a client is cut off.
FLOOD_LIMIT, FLOOD_WINDOW = 200, 10.0
OUTBOX = 512
#: Connections one room takes at once (a consultation, not a broadcast): a leaked link
#: opened thousands of times must not hold thousands of sockets and queues. Counted over
#: every server process (the others' people as the bus has told them: a room opened
#: here learns of them within a moment of its first person). ``MISS_ROOM_MAX_PEOPLE``.
MAX_PEOPLE = 50
#: Places of ``MAX_PEOPLE`` no guest may take (kept for the owner and administrators),
#: and guests one link lets in at once: ``MISS_ROOM_RESERVED``, ``MISS_ROOM_GUESTS_PER_LINK``.
RESERVED, GUESTS_PER_LINK = 5, 20
MAX_NOTE, MAX_CHAT, MAX_NAME = 500, 2000, 40
#: The presenter's camera goes to the replay at most this often (seconds).
VIEW_EVERY = 1.0
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


#: Why a connection closes when a grant ends, by kind.
ENDED = {
    "session": "you logged out, or your password was changed",
    "user": "your account was disabled or its password reset",
    "share": "the share link was revoked",
    "model": "the model was deleted",
    "volume": "the volume was deleted",
}
#: Which ended grant a closed connection is told of when several ended at once (disabling
#: an account also ends its logins: "disabled" says more than "logged out").
REASONS = ("user", "share", "model", "volume", "session")
#: Seconds between checks for ended grants and expired access (the promise: closed within
#: a second), and how long an ended grant is remembered (a connection admitted just
#: before the grant ended still finds it).
WATCH_EVERY = 0.25
REMEMBER_ENDED = 30.0
#: Every this many checks, the connected users' logins are looked up in the database, and
#: the server processes of the people listed from other processes checked alive.
RECHECK_TICKS = 8


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


# -- checking what clients send ------------------------------------------------------------


def point(value: Any, name: str) -> list[float]:
    """Three finite numbers (patient mm)."""
    numbers = (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    )
    if numbers and all(math.isfinite(v) and abs(v) < 1e6 for v in value):
        return [float(v) for v in value]
    raise Invalid("invalid", f"{name} must be [x, y, z]: three finite numbers in millimetres.")


def text(value: Any, name: str, limit: int, required: bool = True) -> str:
    if value is None and not required:
        return ""
    if not isinstance(value, str) or (required and not value.strip()):
        raise Invalid("invalid", f"{name} must be a non-empty string.")
    if len(value) > limit:
        raise Invalid("invalid", f"{name} is {len(value)} characters long; at most {limit}.")
    return value.strip()


def event_id(value: Any, known: dict[int, Any], what: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value not in known:
        raise Invalid("invalid", f"no {what} with id {value!r} in this room.")
    return value


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
        used = {p.colour for p in self.people.values()}
        free = [c for c in COLOURS if c not in used]
        return free[0] if free else COLOURS[len(self.people) % len(COLOURS)]

    def broadcast(self, message: dict[str, Any], skip: Participant | None = None) -> None:
        for person in list(self.people.values()):
            if person is skip:
                continue
            if person.expired():
                person.error("expired", "your access to this room has expired.")
                person.close(Close.GONE, "access expired")
            else:
                person.send(message)

    def welcome(self, you: Participant) -> dict[str, Any]:
        return {
            "type": "welcome",
            "model": self.model_id,
            "session": self.session,
            "you": you.public(),
            "participants": [p.public() for p in self.people.values()]
            + [_unlisted(p) for p in self.remote.values()],
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


Handler = Callable[["Hub", Room, Participant, dict[str, Any]], Awaitable[None]]


class Hub:
    """All open rooms of the server (in memory; their lasting content is in the database)."""

    def __init__(
        self,
        store: Store,
        max_people: int = MAX_PEOPLE,
        reserved: int = RESERVED,
        per_link: int = GUESTS_PER_LINK,
    ) -> None:
        self.store, self.max_people = store, max_people
        self.reserved, self.per_link = reserved, per_link
        self.rooms: dict[str, Room] = {}
        self._lock = asyncio.Lock()
        #: One lock a model while anything holds it: a session's last leave may still be
        #: being written when the next session of the room starts.
        self._writing: weakref.WeakValueDictionary[str, asyncio.Lock] = (
            weakref.WeakValueDictionary()
        )
        self._ended: dict[tuple[str, str], float] = {}  # written from any thread
        self._ended_lock = threading.Lock()
        self._watcher: asyncio.Task[None] | None = None
        store.bus.subscribe("ended", lambda grant: self.end_here(*grant))
        store.bus.subscribe("room", self._heard)
        self._loop: asyncio.AbstractEventLoop | None = None
        #: Told the number of this process's room connections at each join and leave
        #: (the metrics: other processes read it from a file, not by asking this one).
        self.on_people: Callable[[int], None] = lambda n: None

    def connections(self) -> int:
        return sum(len(room.people) for room in self.rooms.values())

    def end(self, kind: str, value: str) -> None:
        """A grant ended (a session, a user's access, a link, a model, a volume): every
        connection standing on it is closed within ``WATCH_EVERY`` seconds, in this
        server process and the others of the same database. Safe to call from any thread
        (the routes that end grants run in the threadpool)."""
        self.end_here(kind, value)
        self.store.bus.publish_soon("ended", [kind, value])

    def end_here(self, kind: str, value: str) -> None:
        with self._ended_lock:
            self._ended[(kind, value)] = time.monotonic()

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._watcher = self._loop.create_task(self._watch())

    # -- the same room on other server processes (``storage.bus``) -------------------------

    def broadcast(
        self,
        room: Room,
        message: dict[str, Any],
        skip: Participant | None = None,
        event: tuple[int, str, str, str, dict[str, Any]] | None = None,
    ) -> None:
        """Send to the room's people here and, through the bus, on the other processes;
        ``event`` (id, at, kind, author, data), when stored, is folded into their state."""
        room.broadcast(message, skip)
        self._publish(room.model_id, message, event)

    def _publish(self, model_id: str, message: dict[str, Any], event: Any = None) -> None:
        bus = self.store.bus
        bus.publish_soon("room", {"m": model_id, "msg": message, "event": event, "on": bus.origin})

    def _heard(self, data: dict[str, Any]) -> None:
        """A room message from another process (the bus's thread): handled on the loop."""
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._relay, data)

    def _relay(self, data: dict[str, Any]) -> None:
        room = self.rooms.get(data["m"])
        if room is None:  # nobody here; a room opened later loads the stored state
            return
        message = data["msg"]
        kind = message.get("type")
        if kind == "hello":  # a room just opened there: say who is here
            for person in room.people.values():
                self._publish(room.model_id, {"type": "joined", "participant": person.listed()})
            return
        if data.get("event"):
            room.state.apply(*data["event"])
        if kind == "joined":
            if message["participant"]["id"] in room.remote:
                return  # already known (an answer to a hello)
            room.remote[message["participant"]["id"]] = message["participant"]
            room.remote_on[message["participant"]["id"]] = str(data.get("on", ""))
            message = message | {"participant": _unlisted(message["participant"])}
        elif kind == "left":
            room.remote.pop(message["id"], None)
            room.remote_on.pop(message["id"], None)
        elif kind == "presenter":
            room.presenter, room.view = message["id"], None
        elif kind == "camera":
            room.view = {k: message[k] for k in ("position", "target", "up")}
        room.broadcast(message)

    async def stop(self) -> None:
        if self._watcher is not None:
            self._watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watcher

    async def _watch(self) -> None:
        ticks = 0
        while True:
            await asyncio.sleep(WATCH_EVERY)
            ticks += 1
            try:
                if ticks % RECHECK_TICKS == 0:  # ended elsewhere: `miss user disable`
                    await self._recheck_sessions()
                    await self._drop_the_dead()
                self.close_ended()
            except Exception:  # keep watching whatever one pass met
                log.exception("room watcher")

    async def _drop_the_dead(self) -> None:
        """People listed here from a server process that died (it could not say they
        left): gone from the rooms, and their leaving told to the people here."""
        origins = {o for room in self.rooms.values() for o in room.remote_on.values() if o}
        for origin in origins:
            if await run_in_threadpool(self.store.bus.is_alive, origin):
                continue
            for room in list(self.rooms.values()):
                for pid in [p for p, o in room.remote_on.items() if o == origin]:
                    room.remote.pop(pid, None)
                    room.remote_on.pop(pid, None)
                    if room.presenter == pid:
                        room.presenter, room.view = None, None
                        room.broadcast({"type": "presenter", "id": None, "name": None})
                    room.broadcast({"type": "left", "id": pid})

    async def _recheck_sessions(self) -> None:
        """Logins of connected users that the database no longer holds (ended by the
        command line or another process) end here too."""
        sessions = {
            person.visitor.session
            for room in self.rooms.values()
            for person in room.people.values()
            if person.visitor.session
        }
        if sessions:
            live = await run_in_threadpool(roomlog.live_sessions, self.store, sessions)
            for session in sessions - live:
                self.end("session", session)

    def close_ended(self) -> None:
        """Close connections whose grant ended or whose access expired (on the loop)."""
        now = time.monotonic()
        with self._ended_lock:
            ended = dict(self._ended)
            for key, at in ended.items():
                if now - at > REMEMBER_ENDED:
                    del self._ended[key]
        for room in list(self.rooms.values()):
            for person in list(room.people.values()):
                if person.closing:
                    continue
                grants = person.visitor.grants(room.model_id)
                gone = [kind for kind, value in grants if (kind, value) in ended]
                if gone:
                    kind = min(gone, key=REASONS.index)  # the most telling of those that ended
                    code = "revoked" if kind == "share" else "ended"
                    person.error(code, f"{ENDED[kind]}; this connection is closed.")
                    person.close(Close.GONE, ENDED[kind])
                elif person.expired():
                    person.error("expired", "your access to this room has expired.")
                    person.close(Close.GONE, "access expired")

    async def run(self, ws: WebSocket, model_id: str, visitor: Visitor, bounds: Any) -> None:
        """Serve one accepted connection until it closes."""
        try:
            room, person = await self._enter(ws, model_id, visitor, bounds)
        except Refused as refused:
            await ws.send_json({"type": "error", "code": "full", "error": refused.reason})
            await ws.close(code=refused.code, reason=refused.reason[:120])
            return
        sender = asyncio.create_task(self._send_loop(person))
        receiver = asyncio.create_task(self._receive_loop(room, person))
        try:
            await asyncio.wait({sender, receiver}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (sender, receiver):
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            await self._leave(room, person)

    async def _enter(
        self, ws: WebSocket, model_id: str, visitor: Visitor, bounds: Any
    ) -> tuple[Room, Participant]:
        async with self._lock:
            room = self.rooms.get(model_id)
            if room is not None:
                self._check_place(room, visitor)
            if room is None:
                state = await run_in_threadpool(roomlog.load_state, self.store, model_id)
                session = await run_in_threadpool(roomlog.next_session, self.store, model_id)
                writing = self._writing.setdefault(model_id, asyncio.Lock())
                room = Room(model_id, session, state, bounds, writing)
                self.rooms[model_id] = room
                self._publish(model_id, {"type": "hello"})
            person = Participant(ws, visitor, room.colour(), model_id)
            room.people[person.id] = person
            self.on_people(self.connections())
        person.send(room.welcome(person))
        room.broadcast({"type": "joined", "participant": person.public()}, skip=person)
        self._publish(model_id, {"type": "joined", "participant": person.listed()})
        await self.store_event(room, person, "join", {"colour": person.colour})
        return room, person

    def _check_place(self, room: Room, visitor: Visitor) -> None:
        """Refuse one more when the room is full, when the guests have taken all but the
        reserved places, or when this guest's link has ``per_link`` guests in already."""
        if len(room.people) + len(room.remote) >= self.max_people:
            raise Refused(
                Close.FULL, f"this room is full ({self.max_people} people); try again later."
            )
        if not visitor.guest:
            return
        places = self.max_people - self.reserved
        if room.guests() >= places:
            raise Refused(
                Close.FULL,
                f"all {places} places for guests in this room are taken (the other "
                f"{self.reserved} are kept for the owner); try again later.",
            )
        if room.guests(visitor.share_id) >= self.per_link:
            raise Refused(
                Close.FULL,
                f"this link already has {self.per_link} guests in the room, the most one "
                "link may let in; ask the owner for a link of your own.",
            )

    async def _leave(self, room: Room, person: Participant) -> None:
        # No await before the room is left: a connection cancelled mid-way (the server
        # stopping, a test client closing) still leaves no ghost behind.
        room.people.pop(person.id, None)
        if not room.people and self.rooms.get(room.model_id) is room:
            del self.rooms[room.model_id]
        self.on_people(self.connections())
        if room.presenter == person.id:
            room.presenter = None
            self.broadcast(room, {"type": "presenter", "id": None, "name": None})
        self.broadcast(room, {"type": "left", "id": person.id})
        # Shielded: the record of the leave is written even if this task is cancelled.
        record = asyncio.ensure_future(self.store_event(room, person, "leave", {}))
        record.add_done_callback(_log_failure)
        await asyncio.shield(record)

    async def store_event(
        self, room: Room, person: Participant, kind: str, data: dict[str, Any]
    ) -> tuple[int, str]:
        """Write one event; one at a time per model, so ids and times rise together, also
        across the room's sessions."""
        async with room.writing:
            return await run_in_threadpool(
                roomlog.append,
                self.store,
                room.model_id,
                room.session,
                kind,
                person.visitor.name,
                data,
                utcnow(),
            )

    @staticmethod
    async def _send_loop(person: Participant) -> None:
        while True:
            kind, payload = await person.outbox.get()
            if kind == "close":
                code, reason = payload
                await person.ws.close(code=code, reason=reason[:120])
                return
            await person.ws.send_text(payload)

    async def _receive_loop(self, room: Room, person: Participant) -> None:
        while True:
            try:
                frame = await person.ws.receive()
            except (WebSocketDisconnect, RuntimeError):
                return
            if frame["type"] == "websocket.disconnect":
                return
            if person.closing or not person.admit():
                continue
            if person.expired():
                person.error("expired", "your access to this room has expired.")
                person.close(Close.GONE, "access expired")
                continue
            try:
                await self._handle(room, person, frame.get("text"))
            except Invalid as exc:
                person.error(exc.code, exc.text)
            except Exception:  # a database hiccup (the model just deleted ...): say so, go on
                log.exception("room %s: message from %s failed", room.model_id, person.id)
                person.error("server", "the server could not handle that message; try again.")

    async def _handle(self, room: Room, person: Participant, raw: str | None) -> None:
        if raw is None:
            raise Invalid("malformed", "send JSON text frames, not binary ones.")
        size = len(raw.encode("utf-8", "replace"))
        if size > MAX_MESSAGE_BYTES:
            raise Invalid(
                "too_large", f"message of {size} bytes refused; at most {MAX_MESSAGE_BYTES}."
            )
        try:
            message = json.loads(raw)
        except ValueError as exc:
            raise Invalid("malformed", f"not valid JSON ({exc.msg} at {exc.pos}).") from None
        except RecursionError:  # "[[[[..." thousands deep: the parser's own limit
            raise Invalid(
                "malformed", "JSON nested too deeply; messages are objects a few levels deep."
            ) from None
        if not isinstance(message, dict) or not isinstance(message.get("type"), str):
            raise Invalid("malformed", 'send a JSON object with a "type", e.g. {"type": "ping"}.')
        handler = HANDLERS.get(message["type"])
        if handler is None:
            known = ", ".join(sorted(HANDLERS))
            raise Invalid("unknown_type", f"unknown message type {message['type']!r}; use {known}.")
        await handler(self, room, person, message)

    async def revoke_share(self, share_id: str) -> None:
        """Close every connection that came in through a revoked link, at once."""
        self.end("share", share_id)
        self.close_ended()


def _unlisted(entry: dict[str, Any]) -> dict[str, Any]:
    """A person listed by another process as the people here see them (no link digest)."""
    return {k: v for k, v in entry.items() if k != "link"}


def _log_failure(task: asyncio.Future[Any]) -> None:
    if not task.cancelled() and task.exception() is not None:
        # The model was deleted meanwhile: nothing left to record the event on.
        log.info("room event not recorded: %s", task.exception())


# -- message handlers ---------------------------------------------------------------------


def _check_model(room: Room, message: dict[str, Any]) -> None:
    target = message.get("model")
    if target is not None and target != room.model_id:
        raise Invalid(
            "wrong_model",
            f"this room is model {room.model_id!r}; refused an item for model {target!r} "
            "(open that model's room to annotate it).",
        )


async def on_ping(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    person.send({"type": "pong"})


async def on_presenter(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    on = message.get("on")
    if not isinstance(on, bool):
        raise Invalid("invalid", '"on" must be true (present) or false (stop presenting).')
    if on:
        room.presenter, room.view = person.id, None
    elif room.presenter == person.id:
        room.presenter, room.view = None, None
    else:
        return
    name = person.visitor.name if on else None
    hub.broadcast(room, {"type": "presenter", "id": room.presenter, "name": name})
    await hub.store_event(room, person, "presenter", {"on": on})


async def on_camera(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    if room.presenter != person.id:
        raise Invalid("not_presenter", "only the presenter's view is shared; press Present first.")
    view = {k: point(message.get(k), k) for k in ("position", "target", "up")}
    room.view = view
    hub.broadcast(room, {"type": "camera", "from": person.id, **view}, skip=person)
    now = time.monotonic()
    if now - room.last_view >= VIEW_EVERY:  # the replay gets a view a second, not sixty
        room.last_view = now
        await hub.store_event(room, person, "view", view)


async def on_laser(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    _check_model(room, message)
    at = message.get("point")
    at = None if at is None else room.on_model(point(at, "point"), "the laser point")
    frame = {"type": "laser", "from": person.id, "colour": person.colour, "point": at}
    hub.broadcast(room, frame, skip=person)


async def on_pin(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    _check_model(room, message)
    data = {
        "point": room.on_model(point(message.get("point"), "point"), "the pin"),
        "note": text(message.get("note"), "note", MAX_NOTE, required=False),
        "colour": person.colour,
        "by": person.visitor.key,
    }
    await _keep(hub, room, person, "pin", data)


async def on_measure(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    _check_model(room, message)
    a = room.on_model(point(message.get("a"), "a"), "the first point")
    b = room.on_model(point(message.get("b"), "b"), "the second point")
    data = {"a": a, "b": b, "mm": round(math.dist(a, b), 2), "colour": person.colour}
    await _keep(hub, room, person, "measure", data | {"by": person.visitor.key})


async def on_chat(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    data = {"text": text(message.get("text"), "text", MAX_CHAT), "colour": person.colour}
    await _keep(hub, room, person, "chat", data)


async def _keep(hub: Hub, room: Room, person: Participant, kind: str, data: dict[str, Any]) -> None:
    """Store an event, fold it into the room and send it to everyone (the sender too:
    it learns the id)."""
    stored_id, at = await hub.store_event(room, person, kind, data)
    room.state.apply(stored_id, at, kind, person.visitor.name, data)
    item = {"id": stored_id, "author": person.visitor.name, "at": at, **data}
    item = public_item(room.model_id, item)
    event = (stored_id, at, kind, person.visitor.name, data)
    hub.broadcast(room, {"type": kind, "item": item}, event=event)


async def on_remove(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """``unpin`` / ``unmeasure``: by their author or the model's owner."""
    kind = message["type"]
    items = room.state.pins if kind == "unpin" else room.state.measurements
    target = event_id(message.get("id"), items, "pin" if kind == "unpin" else "measurement")
    if items[target].get("by") != person.visitor.key and not person.visitor.owner:
        raise Invalid("forbidden", "only its author or the model's owner may remove it.")
    stored_id, at = await hub.store_event(room, person, kind, {"id": target})
    room.state.apply(stored_id, at, kind, person.visitor.name, {"id": target})
    event = (stored_id, at, kind, person.visitor.name, {"id": target})
    hub.broadcast(room, {"type": kind, "id": target}, event=event)


HANDLERS: dict[str, Handler] = {
    "ping": on_ping,
    "presenter": on_presenter,
    "camera": on_camera,
    "laser": on_laser,
    "pin": on_pin,
    "unpin": on_remove,
    "measure": on_measure,
    "unmeasure": on_remove,
    "chat": on_chat,
}
