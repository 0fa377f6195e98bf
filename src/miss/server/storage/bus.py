"""What one server process tells the others on the same PostgreSQL database, through
``LISTEN``/``NOTIFY`` (no broker): rows dropped from the caches, grants that ended (a
logout, a revoked link, a deleted model: their room connections close), jobs queued,
room messages.

On SQLite there is one server process per data folder (``Store.lock``): the bus is off
and ``publish`` does nothing. What ``miss`` commands beside it must tell it at once (an
account disabled, a password or a permission changed) goes through ``announce``: on
SQLite a line appended to a file beside the database (``<database>-bus``), which the
server reads every ``POLL`` seconds.

Each process listens on one connection of its own, in a thread; a message carries its
sender's ``origin``, so a process ignores its own. PostgreSQL delivers notifications of
a committed transaction in commit order, after the commit: a process that hears "drop
model X" and reads X again reads what the sender committed. A listener that lost its
connection may have missed some: on reconnecting it tells each channel's ``on_gap`` (the
row cache empties itself).
"""

from __future__ import annotations

import json
import logging
import os
import queue
import secrets
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, make_url, text

log = logging.getLogger("miss.server.storage.bus")

#: NOTIFY's payload must be shorter than 8000 bytes; longer messages are split by callers
#: (``RowCache`` keys) or dropped with a log line.
MAX_PAYLOAD = 7900
PREFIX = "miss_"
#: Seconds between two looks at the SQLite bus file (``announce``).
POLL = 0.2


class Bus:
    """Publish to and hear from the other server processes of one database."""

    def __init__(self, engine: Engine, url: str) -> None:
        self.engine, self.url = engine, url
        self.enabled = make_url(url).get_backend_name() == "postgresql"
        self.origin = secrets.token_hex(6)
        self._handlers: dict[str, Callable[[Any], None]] = {}
        self._gaps: dict[str, Callable[[], None]] = {}
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._outbox: queue.SimpleQueue[tuple[str, Any] | None] = queue.SimpleQueue()
        self._sender: threading.Thread | None = None
        self._sender_lock = threading.Lock()
        self.heard = 0  # messages from others handled (tests, metrics)
        self._alive: Any = None  # the connection holding this process's liveness lock
        #: On SQLite: where ``announce`` appends (None for a database in memory).
        self.file = None if self.enabled else _bus_file(url)

    def subscribe(
        self, channel: str, handler: Callable[[Any], None], on_gap: Callable[[], None] | None = None
    ) -> None:
        """``handler(data)`` for each message of another process (in the bus's thread)."""
        self._handlers[channel] = handler
        if on_gap is not None:
            self._gaps[channel] = on_gap

    def publish(self, channel: str, data: Any) -> None:
        """Tell the other processes before returning (a row dropped: the caller answers
        only after the others were told); never raises (a lost message costs a TTL)."""
        if self.enabled:
            self._send([(channel, data)])

    def announce(self, channel: str, data: Any) -> None:
        """``publish``, and on SQLite append to the bus file the server process reads
        within ``POLL`` seconds: for ``miss`` commands, which run beside a server."""
        if self.enabled:
            self.publish(channel, data)
        elif self.file is not None:
            line = json.dumps({"o": self.origin, "c": channel, "d": data}) + "\n"
            # One write of one short line with O_APPEND: lines of several commands never mix.
            fd = os.open(self.file, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
            try:
                os.write(fd, line.encode())
            finally:
                os.close(fd)

    def publish_soon(self, channel: str, data: Any) -> None:
        """Tell the other processes without waiting (from the event loop: room messages),
        in the order asked, by a thread of the bus."""
        if not self.enabled:
            return
        with self._sender_lock:
            if self._sender is None:
                self._sender = threading.Thread(target=self._send_loop, daemon=True)
                self._sender.start()
        self._outbox.put((channel, data))

    def _send(self, messages: list[tuple[str, Any]]) -> None:
        notes = []
        for channel, data in messages:
            payload = json.dumps({"o": self.origin, "d": data}, separators=(",", ":"))
            if len(payload.encode()) > MAX_PAYLOAD:
                log.warning(
                    "bus message on %s too long (%d bytes): not sent", channel, len(payload)
                )
                continue
            notes.append({"c": PREFIX + channel, "p": payload})
        if not notes:
            return
        try:
            with self.engine.begin() as conn:
                conn.execute(text("SELECT pg_notify(:c, :p)"), notes)
        except Exception:
            log.exception("could not publish %d bus message(s)", len(notes))

    def _send_loop(self) -> None:
        while True:
            batch = [self._outbox.get()]
            while len(batch) < 200 and not self._outbox.empty():
                batch.append(self._outbox.get())
            messages = [m for m in batch if m is not None]
            self._send(messages)
            if len(messages) < len(batch):
                return

    # -- liveness: whose running jobs are orphans -----------------------------------------

    @staticmethod
    def key(origin: str) -> int:
        """The advisory lock key of a process (its 48-bit origin)."""
        return int(origin, 16)

    def hold_liveness(self) -> None:
        """Hold this process's liveness lock, on a connection of its own, for its life:
        while it is held (PostgreSQL frees it when the process or its connection dies),
        the jobs whose ``runner`` is this process are this process's."""
        if not self.enabled:
            return
        if self._alive is not None and not self._alive.closed and not self._alive.broken:
            return
        if self._alive is not None:
            log.warning("liveness connection lost; taking the lock again")
        self._alive = self._connect()
        self._alive.execute("SELECT pg_advisory_lock(%s)", (self.key(self.origin),))

    def is_alive(self, origin: str) -> bool:
        """True while the process ``origin`` holds its liveness lock (always on SQLite)."""
        if not self.enabled or origin == self.origin:
            return True
        key = {"k": self.key(origin)}
        with self.engine.connect() as conn:
            free = conn.execute(text("SELECT pg_try_advisory_lock(:k)"), key).scalar()
            if free:
                conn.execute(text("SELECT pg_advisory_unlock(:k)"), key)
            conn.commit()
        return not free

    def start(self) -> None:
        """Start listening: on PostgreSQL, from a thread of its own; on SQLite, to the bus file."""
        if self._thread is not None:
            return
        if self.enabled:
            self._thread = threading.Thread(target=self._run, name="miss-bus", daemon=True)
        elif self.file is not None:
            self._thread = threading.Thread(
                target=self._read_file, args=(self.file,), name="miss-bus", daemon=True
            )
        if self._thread is not None:
            self._thread.start()

    def _read_file(self, path: Path) -> None:
        """The SQLite bus: hear each line appended to ``path`` since this process started."""
        offset = path.stat().st_size if path.exists() else 0
        while not self._stopping.wait(POLL):
            try:
                size = path.stat().st_size
            except FileNotFoundError:
                offset = 0
                continue
            if size < offset:  # replaced by a shorter file: read it all
                offset = 0
            if size == offset:
                continue
            with open(path, "rb") as f:
                f.seek(offset)
                chunk = f.read(size - offset)
            end = chunk.rfind(b"\n") + 1  # a line still being written waits for its end
            offset += end
            for line in chunk[:end].splitlines():
                self._hear_line(line)

    def _hear_line(self, line: bytes) -> None:
        try:
            message = json.loads(line)
            channel = str(message["c"])
        except (ValueError, KeyError, TypeError):
            log.warning("unreadable line in the bus file: %r", line[:200])
            return
        self._deliver(channel, message)

    def stop(self) -> None:
        """Stop the threads (waiting up to 5 s each) and release the liveness lock."""
        self._stopping.set()
        if self._sender is not None:
            self._outbox.put(None)
            self._sender.join(timeout=5)
            self._sender = None
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self._alive is not None:
            self._alive.close()
            self._alive = None

    def _run(self) -> None:
        first = True
        while not self._stopping.is_set():
            try:
                with self._connect() as conn:
                    for channel in self._handlers:
                        conn.execute(f'LISTEN "{PREFIX}{channel}"')
                    if not first:  # messages may have been missed meanwhile
                        for on_gap in self._gaps.values():
                            on_gap()
                    first = False
                    while not self._stopping.is_set():
                        for note in conn.notifies(timeout=0.5):
                            self._hear(note.channel.removeprefix(PREFIX), note.payload)
            except Exception:
                if not self._stopping.is_set():
                    log.exception("bus listener lost its connection; reconnecting")
                    self._stopping.wait(1.0)

    def _connect(self) -> Any:
        import psycopg

        plain = make_url(self.url).set(drivername="postgresql")
        return psycopg.connect(plain.render_as_string(hide_password=False), autocommit=True)

    def _hear(self, channel: str, payload: str) -> None:
        self._deliver(channel, json.loads(payload))

    def _deliver(self, channel: str, message: dict[str, Any]) -> None:
        if message.get("o") == self.origin:
            return
        handler = self._handlers.get(channel)
        if handler is None:
            return
        try:
            handler(message.get("d"))
            self.heard += 1
        except Exception:
            log.exception("bus handler for %s", channel)


def _bus_file(url: str) -> Path | None:
    """The file beside an SQLite database through which ``announce`` speaks."""
    database = make_url(url).database
    if make_url(url).get_backend_name() != "sqlite" or not database or database == ":memory:":
        return None
    return Path(database + "-bus")
