"""What the server process keeps in memory so that a viewer's requests seldom reach the
database or the disk: row snapshots, rendered slices and model files.

Each is safe because of what it holds. Stored volumes and finished model files never
change; rows go in only when they change through this process alone (a volume, a
finished model, a login session), and the code that changes them drops them. A TTL
bounds what a change made by another program on the same database could leave behind.

``cache_only()`` turns a cache miss into :class:`NotCached` for the code run inside it:
a route's sync helper is tried on the event loop first (everything it needs in memory:
microseconds, no thread) and goes to the threadpool only when it would wait for the
database or the disk (see ``deps.on_loop``).
"""

from __future__ import annotations

import contextvars
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

_CACHE_ONLY: contextvars.ContextVar[bool] = contextvars.ContextVar("cache_only", default=False)


class NotCached(Exception):
    """Raised under ``cache_only()`` where the answer needs the database or the disk."""


@contextmanager
def cache_only() -> Iterator[None]:
    """Within this block, misses raise :class:`NotCached` instead of blocking."""
    token = _CACHE_ONLY.set(True)
    try:
        yield
    finally:
        _CACHE_ONLY.reset(token)


def need_io() -> None:
    """Call before blocking on the database or the disk: raises under ``cache_only()``."""
    if _CACHE_ONLY.get():
        raise NotCached


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
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def get(self, key: Hashable, make: Callable[[], bytes]) -> bytes:
        """The value of ``key``, made (under ``cache_only()``: NotCached) when missing."""
        value = self.peek(key)
        if value is not None:
            return value
        need_io()
        value = make()  # outside the lock: two first requests may both make it, both right
        self.put(key, value)
        return value

    def put(self, key: Hashable, value: bytes) -> None:
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

    def get(self, key: Hashable) -> Any | None:
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
        with self._lock:
            if generation != self.generation:
                return
            self._items[key] = (time.monotonic(), value)
            self._items.move_to_end(key)
            while len(self._items) > self.max_items:
                self._items.popitem(last=False)

    def drop(self, *keys: Hashable) -> None:
        with self._lock:
            self.generation += 1
            for key in keys:
                self._items.pop(key, None)

    def clear(self) -> None:
        with self._lock:
            self.generation += 1
            self._items.clear()

    def cached(self, key: Hashable, load: Callable[[], Any], keep: Callable[[Any], bool]) -> Any:
        """The snapshot of ``key``, else ``load()`` (kept when ``keep(value)``); under
        ``cache_only()`` a miss raises NotCached."""
        value = self.get(key)
        if value is not None:
            return value
        need_io()
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
