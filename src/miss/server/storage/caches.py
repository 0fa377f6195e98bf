"""What the server process keeps in memory so that a viewer's requests seldom reach the
database or the disk: row snapshots, rendered slices and model files.

Each is safe because of what it holds. Stored volumes and finished model files never
change; rows go in only when they change through the server alone (a volume, a finished
model, a login session), and the code that changes them drops them: here, and, through
the bus (``storage.bus``, PostgreSQL's NOTIFY), in every other server process of the
same database. A TTL bounds what a change made by another program could leave behind.

Each has a ``peek``-like read that never waits (``BytesLRU.peek``, ``RowCache.get``,
``Store.cached_volume``): a route asks first, answers on the event loop when everything
is in memory (microseconds, no thread) and goes to the threadpool only when it must wait
for the database or the disk (``deps.here_or_threadpool``).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any


class BytesLRU:
    """Byte strings by key (rendered PNGs, model files), least recently used out first.

    Bounded by total bytes; a value larger than the whole budget is returned but not kept.
    Thread-safe: the threadpool fills it while the event loop reads it.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._items: OrderedDict[Hashable, bytes] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def peek(self, key: Hashable) -> bytes | None:
        """The value of ``key`` (now the most recently used), or None."""
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def get(self, key: Hashable, make: Callable[[], bytes]) -> bytes:
        """The value of ``key``, made when missing."""
        value = self.peek(key)
        if value is not None:
            return value
        value = make()  # outside the lock: two first requests may both make it, both right
        self.put(key, value)
        return value

    def put(self, key: Hashable, value: bytes) -> None:
        """Keep ``value`` under ``key``, dropping the least recently used to stay within
        ``max_bytes``; a value larger than the budget, or a key already kept, is ignored."""
        with self._lock:
            if key in self._items or len(value) > self.max_bytes:
                return
            self._items[key] = value
            self._bytes += len(value)
            while self._bytes > self.max_bytes:
                self._bytes -= len(self._items.popitem(last=False)[1])


class RowCache:
    """Snapshots of database rows by key, each for at most ``ttl`` seconds.

    ``generation`` guards a race: a thread that read a row before another dropped it must
    not put the stale copy back, so ``put`` takes the generation seen before the query
    and is ignored if anything was dropped since.
    """

    def __init__(self, max_items: int = 4096, ttl: float = 30.0) -> None:
        self.max_items, self.ttl = max_items, ttl
        self._items: OrderedDict[Hashable, tuple[float, Any]] = OrderedDict()
        self._lock = threading.Lock()
        self.generation = 0
        #: Told the keys dropped (None: all), after the drop: the store publishes them.
        self.on_change: Callable[[tuple[Hashable, ...] | None], None] = lambda keys: None

    def get(self, key: Hashable) -> Any | None:
        """The row kept under ``key`` if younger than ``ttl`` seconds, else None."""
        with self._lock:
            found = self._items.get(key)
            if found is None:
                return None
            if time.monotonic() - found[0] > self.ttl:
                del self._items[key]
                return None
            self._items.move_to_end(key)
            return found[1]

    def put(self, key: Hashable, value: Any, generation: int) -> None:
        """Keep ``value`` under ``key`` unless something was dropped since ``generation`` was
        read (then the value may be stale and is ignored)."""
        with self._lock:
            if generation != self.generation:
                return
            self._items[key] = (time.monotonic(), value)
            self._items.move_to_end(key)
            while len(self._items) > self.max_items:
                self._items.popitem(last=False)

    def drop(self, *keys: Hashable) -> None:
        """Drop ``keys`` here and in the other server processes."""
        self.drop_here(*keys)
        self.on_change(keys)

    def drop_here(self, *keys: Hashable) -> None:
        """Drop ``keys`` in this process only (``drop`` tells the other processes too)."""
        with self._lock:
            self.generation += 1
            for key in keys:
                self._items.pop(key, None)

    def clear(self) -> None:
        """Drop every row here and in the other processes."""
        self.clear_here()
        self.on_change(None)

    def clear_here(self) -> None:
        """Drop every row in this process only."""
        with self._lock:
            self.generation += 1
            self._items.clear()

    def cached(self, key: Hashable, load: Callable[[], Any], keep: Callable[[Any], bool]) -> Any:
        """The snapshot of ``key``, else ``load()`` (kept when ``keep(value)``)."""
        value = self.get(key)
        if value is not None:
            return value
        generation = self.generation
        value = load()
        if value is not None and keep(value):
            self.put(key, value, generation)
        return value


@dataclass(frozen=True)
class ByteCaches:
    """The bytes this server process answers viewers with (``app.state.bytes``): model
    files by (model, format, ETag), up to 32 MB each and 128 MB in all (a finished
    model's files never change); rendered slices, 64 MB (stored volumes never change)."""

    model_files: BytesLRU = field(default_factory=lambda: BytesLRU(128 * 2**20))
    slices: BytesLRU = field(default_factory=lambda: BytesLRU(64 * 2**20))
    max_file: int = 32 * 2**20
