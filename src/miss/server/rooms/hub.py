"""All open rooms of one server process (:class:`Hub`): joining, leaving, the watcher
that closes connections whose grant ended, and the same room on other processes
(``storage.bus``)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
import time
import weakref
from collections.abc import Callable
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocket, WebSocketDisconnect

from miss.server.rooms import record as roomlog
from miss.server.rooms.messages import HANDLERS
from miss.server.rooms.people import (
    MAX_MESSAGE_BYTES,
    Close,
    Invalid,
    Participant,
    Refused,
    Visitor,
)
from miss.server.rooms.room import Room, unlisted
from miss.server.storage.db import utcnow
from miss.server.storage.store import Store

log = logging.getLogger("miss.server.rooms")

#: Connections one room takes at once (a consultation, not a broadcast): a leaked link
#: opened thousands of times must not hold thousands of sockets and queues. Counted over
#: every server process (the others' people as the bus has told them: a room opened
#: here learns of them within a moment of its first person). ``MISS_ROOM_MAX_PEOPLE``.
MAX_PEOPLE = 50
#: Places of ``MAX_PEOPLE`` no guest may take (kept for the owner and administrators),
#: and guests one link lets in at once: ``MISS_ROOM_RESERVED``, ``MISS_ROOM_GUESTS_PER_LINK``.
RESERVED, GUESTS_PER_LINK = 5, 20
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
        """Room connections open in this process."""
        return sum(len(room.people) for room in self.rooms.values())

    def end(self, kind: str, value: str) -> None:
        """A grant ended (a session, a user's access, a link, a model, a volume): every
        connection standing on it is closed within ``WATCH_EVERY`` seconds, in this
        server process and the others of the same database. Safe to call from any thread
        (the routes that end grants run in the threadpool)."""
        self.end_here(kind, value)
        self.store.bus.publish_soon("ended", [kind, value])

    def end_here(self, kind: str, value: str) -> None:
        """Record in this process that a grant ended (``end`` tells the other processes too)."""
        with self._ended_lock:
            self._ended[(kind, value)] = time.monotonic()

    def start(self) -> None:
        """Start watching for ended grants and expired guests (on the running event loop)."""
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
            message = message | {"participant": unlisted(message["participant"])}
        elif kind == "left":
            room.remote.pop(message["id"], None)
            room.remote_on.pop(message["id"], None)
        elif kind == "presenter":
            room.presenter, room.view = message["id"], None
        elif kind == "camera":
            room.view = {k: message[k] for k in ("position", "target", "up")}
        elif kind == "renamed" and message["participant"]["id"] in room.remote:
            room.remote[message["participant"]["id"]]["name"] = message["participant"]["name"]
        room.broadcast(message)

    async def stop(self) -> None:
        """Stop the watcher started by ``start``."""
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
        except json.JSONDecodeError as exc:
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


def _log_failure(task: asyncio.Future[Any]) -> None:
    if not task.cancelled() and task.exception() is not None:
        # The model was deleted meanwhile: nothing left to record the event on.
        log.info("room event not recorded: %s", task.exception())
