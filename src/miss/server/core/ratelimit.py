"""Limits that keep one client from starving the others.

- :class:`TokenBucket` and :class:`KeyedBuckets`: a burst of ``capacity`` at once, then
  ``rate`` per second; per WebSocket connection (room messages), per client address
  (failed logins, WebSocket connections opened: :func:`ws_connect_limits`).
- :class:`ApiLimits` and :class:`RateLimitMiddleware`: the REST API's bucket per account,
  or per client address for requests without a known session (share-link viewers).
- :class:`JobLimit`: how many surface jobs one account may have queued or running.
- :class:`PasswordChecks`: how many passwords one server process checks at once.
- :class:`OpenStreams`: how many event streams one account may hold open at once.
- :class:`SharedBuckets`: the keyed buckets of the server processes of one PostgreSQL
  database kept in step, so a client spread over N processes gets the limit once, not
  N times.

Over a limit the answer is 429 with a JSON ``detail`` and a ``Retry-After`` header.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from datetime import UTC, datetime, timedelta
from typing import ParamSpec, TypeVar

import anyio
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from miss.server.core.auth import presented_token
from miss.server.core.errors import TooManyRequests
from miss.server.storage.bus import Bus
from miss.server.storage.db import FAILED, QUEUED, RUNNING, ModelRow
from miss.server.storage.store import Store


class TokenBucket:
    """``take()`` is True while tokens remain; they refill continuously at ``rate``/s."""

    def __init__(self, capacity: float, rate: float) -> None:
        self.capacity, self.rate = float(capacity), float(rate)
        self.tokens = float(capacity)
        self.stamp = time.monotonic()

    def take(self, cost: float = 1.0) -> bool:
        """Take ``cost`` tokens if there are that many (True), else take none (False)."""
        now = time.monotonic()
        self.tokens = min(self.capacity, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= cost:
            self.tokens -= cost
            return True
        return False

    def deduct(self, spent: float) -> None:
        """Take what was spent elsewhere (negative: given back) whether or not it is there:
        a bucket in debt refuses until it has refilled past it, so N processes that
        each let a burst through in the same moment are paid back. The debt is bounded
        by one burst."""
        self.take(0.0)
        self.tokens = min(self.capacity, max(-self.capacity, self.tokens - spent))

    def seconds_until(self, cost: float = 1.0) -> float:
        """How long until ``take(cost)`` would succeed."""
        return max(0.0, (cost - self.tokens) / self.rate) if self.rate > 0 else float("inf")


#: A shared bucket below this share of its capacity is told to the other processes at
#: once (``SharedBuckets``), not at the next round: near the limit, what a client spends
#: on several processes at the same moment is what lets it past.
LOW = 0.25


class KeyedBuckets:
    """One bucket per key (a client address, an account), the oldest full ones forgotten
    beyond ``max_keys`` so a scan from many addresses cannot grow memory without end;
    one with tokens spent is kept until it has refilled (``_forget_full``). Thread-safe."""

    def __init__(self, capacity: float, rate: float, max_keys: int = 10_000) -> None:
        self.capacity, self.rate, self.max_keys = capacity, rate, max_keys
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()
        #: Keys beyond which full buckets are forgotten (``_forget_full``).
        self._high = max_keys
        self._lock = threading.Lock()
        #: Tokens taken (net of those given back) per key since ``drain``, while shared.
        self._spent: dict[str, float] | None = None
        #: Called when a take leaves a bucket below ``LOW`` of its capacity, while shared.
        self.on_low: Callable[[], None] = lambda: None

    def take(self, key: str, cost: float = 1.0) -> bool:
        """Take ``cost`` tokens from ``key``'s bucket if it has them (True), else none (False)."""
        with self._lock:
            bucket = self._bucket(key)
            taken = bucket.take(cost)
            if taken:
                self._note(key, cost, bucket)
            return taken

    def take_or_wait(self, key: str, cost: float = 1.0) -> float:
        """Take ``cost`` tokens: 0.0 when they were there, else the seconds until they
        will be (and nothing is taken)."""
        with self._lock:
            bucket = self._bucket(key)
            if bucket.take(cost):
                self._note(key, cost, bucket)
                return 0.0
            return max(bucket.seconds_until(cost), 1e-3)

    def give_back(self, key: str, cost: float = 1.0) -> None:
        """Return ``cost`` tokens taken for an attempt that turned out fine."""
        with self._lock:
            bucket = self._bucket(key)
            bucket.tokens = min(bucket.capacity, bucket.tokens + cost)
            self._note(key, -cost, bucket)

    # -- what the other processes spent (``SharedBuckets``) ---------------------------------

    def record(self) -> None:
        """From now on, count what is taken and given back, for ``drain``."""
        with self._lock:
            if self._spent is None:
                self._spent = {}

    def drain(self) -> dict[str, float]:
        """What was taken per key since the last call (net of what was given back)."""
        with self._lock:
            if not self._spent:
                return {}
            spent, self._spent = self._spent, {}
        return {key: n for key, n in spent.items() if n}

    def deduct(self, spent: dict[str, float]) -> None:
        """Take from each key's bucket what another process took for that key."""
        with self._lock:
            for key, n in spent.items():
                self._bucket(key).deduct(n)

    def _note(self, key: str, cost: float, bucket: TokenBucket) -> None:
        if self._spent is not None:
            self._spent[key] = self._spent.get(key, 0.0) + cost
            if bucket.tokens < LOW * bucket.capacity:
                self.on_low()

    def allowed(self, key: str) -> tuple[bool, float]:
        """(a token is there now, seconds until one is) without taking it."""
        with self._lock:
            bucket = self._bucket(key)
            ok = bucket.take(0.0) and bucket.tokens >= 1.0
            return ok, bucket.seconds_until()

    def _bucket(self, key: str) -> TokenBucket:
        bucket = self._buckets.pop(key, None) or TokenBucket(self.capacity, self.rate)
        self._buckets[key] = bucket
        if len(self._buckets) > self._high:
            self._forget_full()
        return bucket

    def _forget_full(self) -> None:
        """Forget the oldest full buckets, down to ``max_keys``: a full bucket is what a
        new key gets anyway. A bucket with tokens spent (a locked account) stays until it
        has refilled, however many keys come after it: forgetting it would hand out a
        fresh burst. Those are as many as the keys spent on within one refill, which the
        limits themselves bound; the next sweep waits until the keys have doubled, so
        sweeping costs O(1) a key."""
        full = [key for key, b in self._buckets.items() if b.take(0.0) and b.tokens >= b.capacity]
        for key in full[: max(0, len(self._buckets) - self.max_keys)]:
            del self._buckets[key]
        self._high = max(self.max_keys, 2 * len(self._buckets))


def ws_connect_limits(per_minute: float) -> KeyedBuckets:
    """WebSocket connections per client address: ``per_minute`` at once (a ward's guests
    behind one address joining together), then ``per_minute`` a minute. Rooms limit the
    messages of a connection themselves; this limits opening them."""
    return KeyedBuckets(per_minute, per_minute / 60.0)


def too_many(detail: str, wait: float) -> JSONResponse:
    """The 429 answer: ``detail`` and ``Retry-After`` in whole seconds (at least 1)."""
    return JSONResponse(
        {"detail": detail}, status_code=429, headers={"Retry-After": str(retry_after(wait))}
    )


def retry_after(wait: float) -> int:
    """Seconds to put in ``Retry-After``: ``wait`` rounded up, at least 1 (an hour if
    ``wait`` is infinite)."""
    return max(1, math.ceil(wait)) if math.isfinite(wait) else 3600


class OverLimit(TooManyRequests):
    """A client over one of these limits; ``wait`` seconds until it may try again."""

    def __init__(self, message: str, wait: float) -> None:
        super().__init__(message)
        self.wait = wait


# -- the REST API ------------------------------------------------------------------------

#: Paths the API limit covers: the REST API and what a share link opens. Not the pages,
#: not ``/web/`` assets, not WebSockets (rooms limit their messages themselves).
LIMITED_PREFIXES = ("/api/", "/s/")
#: Monitoring must see the server's state, not the limit's.
UNLIMITED_PATHS = frozenset({"/api/health"})
#: A tile of a model's levels of detail costs this share of a request: a viewer zooming
#: into a large model fetches dozens of them at once, each a small cached file.
TILE_COST = 0.125


def request_cost(path: str) -> float:
    """What a request to ``path`` takes from its bucket: ``TILE_COST`` for a level-of-detail
    tile, 1 otherwise."""
    return TILE_COST if "/lod/" in path else 1.0


class ApiLimits:
    """One bucket (``burst`` at once, then ``rate`` per second) per account; requests with
    no session known to belong to an account (anonymous share-link viewers, logins, a
    token never seen or made up) share their client address's bucket.

    Accounts are learnt from the sessions the routes authenticate (:meth:`remember`), so
    the limit itself never touches the database; only a digest of each token is kept."""

    def __init__(self, rate: float, burst: float, max_keys: int = 10_000) -> None:
        self.rate, self.burst = rate, burst
        self.buckets = KeyedBuckets(burst, rate, max_keys)
        self.max_keys = max_keys
        self._accounts: OrderedDict[bytes, str] = OrderedDict()
        self._lock = threading.Lock()

    def remember(self, token: str, user_id: str) -> None:
        """``token`` is a live session of account ``user_id``."""
        digest = _digest(token)
        with self._lock:
            if self._accounts.get(digest) == user_id:
                self._accounts.move_to_end(digest)
                return
            self._accounts[digest] = user_id
            while len(self._accounts) > self.max_keys:
                self._accounts.popitem(last=False)

    def key(self, token: str, address: str) -> str:
        """The bucket a request counts against: ``user:<id>`` for a session known to belong to
        an account, ``addr:<address>`` otherwise."""
        if token:
            with self._lock:
                user_id = self._accounts.get(_digest(token))
            if user_id is not None:
                return f"user:{user_id}"
        return f"addr:{address}"

    def check(self, token: str, address: str, cost: float = 1.0) -> tuple[str, float] | None:
        """None when the request may go on (``cost`` tokens taken); else the 429's detail
        and the seconds to wait (nothing taken)."""
        key = self.key(token, address)
        wait = self.buckets.take_or_wait(key, cost)
        if wait <= 0.0:
            return None
        who = "this account" if key.startswith("user:") else f"the address {address}"
        detail = (
            f"too many requests: {who} may make {self.rate:g} per second (bursts of "
            f"{self.burst:g}); retry in {retry_after(wait)} s."
        )
        return detail, wait


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8", "replace")).digest()


class RateLimitMiddleware:
    """ASGI middleware applying :class:`ApiLimits` to ``LIMITED_PREFIXES``; a refused
    request gets 429 before any route, database or body read."""

    def __init__(self, app: ASGIApp, limits: ApiLimits) -> None:
        self.app, self.limits = app, limits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Refuse with 429 a request under ``LIMITED_PREFIXES`` whose bucket is empty; pass
        everything else on."""
        path = scope.get("path", "")
        if (
            scope["type"] != "http"
            or not path.startswith(LIMITED_PREFIXES)
            or path in UNLIMITED_PATHS
        ):
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        token, _ = presented_token(conn.headers, conn.cookies)
        address = conn.client.host if conn.client else ""
        refused = self.limits.check(token, address, request_cost(path))
        if refused is not None:
            await too_many(*refused)(scope, receive, send)
            return
        await self.app(scope, receive, send)


# -- across server processes ----------------------------------------------------------------

#: Seconds between two messages of what a process's clients spent: how long a client
#: spread over several processes may spend more than its limit (one burst at most, paid
#: back as a debt).
SHARE_EVERY = 0.1
#: Bytes of one message's spending (``Bus.MAX_PAYLOAD`` less its envelope); more is split.
SHARE_BYTES = 7000


class SharedBuckets:
    """The keyed buckets of every server process of one PostgreSQL database in step.

    Each process decides alone, from its own buckets, in memory: no database round trip
    on a request's way. Every ``SHARE_EVERY`` seconds it publishes on the bus (one
    ``NOTIFY``) the tokens its clients spent per key, and at once when a bucket runs
    low; every other process takes them from its own bucket for the key. So the limit
    holds across processes within about ``SHARE_EVERY``: what a client sprays over N
    processes in that window is let through, and taken from it afterwards (the buckets
    may go into debt). On SQLite (one process) nothing is recorded or sent."""

    CHANNEL = "spent"

    def __init__(self, buckets: dict[str, KeyedBuckets], every: float = SHARE_EVERY) -> None:
        self.buckets, self.every = buckets, every
        self._bus: Bus | None = None
        self._stopping = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, bus: Bus) -> None:
        """Subscribe (before ``bus.start()``) and publish from a thread of its own."""
        if not bus.enabled or self._thread is not None:
            return
        self._bus = bus
        for buckets in self.buckets.values():
            buckets.record()
            buckets.on_low = self._wake.set
        bus.subscribe(self.CHANNEL, self.heard)
        self._thread = threading.Thread(target=self._run, name="miss-limits", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop publishing and wait for the thread (up to 5 s)."""
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def _run(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(self.every)
            self._wake.clear()
            self.publish()

    def publish(self) -> None:
        """Send what was spent since the last time, in messages of at most
        ``SHARE_BYTES`` (usually one)."""
        if self._bus is None:
            return
        for message in split(
            {name: buckets.drain() for name, buckets in self.buckets.items()}, SHARE_BYTES
        ):
            self._bus.publish(self.CHANNEL, message)

    def heard(self, message: dict[str, dict[str, float]]) -> None:
        """Deduct what the clients of another process spent (a message of ``publish``)."""
        for name, spent in message.items():
            buckets = self.buckets.get(name)
            if buckets is not None:
                buckets.deduct(spent)


def split(spent: dict[str, dict[str, float]], most: int) -> list[dict[str, dict[str, float]]]:
    """``{buckets: {key: tokens}}`` as messages whose JSON is at most about ``most``
    bytes; none when nothing was spent."""
    messages: list[dict[str, dict[str, float]]] = []
    message: dict[str, dict[str, float]] = {}
    size = 2
    for name, keys in spent.items():
        for key, n in keys.items():
            entry = len(json.dumps({name: {key: round(n, 4)}})) + 1
            if message and size + entry > most:
                messages.append(message)
                message, size = {}, 2
            message.setdefault(name, {})[key] = round(n, 4)
            size += entry
    if message:
        messages.append(message)
    return messages


# -- long-lived responses --------------------------------------------------------------------


class HeldCounts:
    """How many of something each key holds at once (open streams, uploads being
    received), under one lock; what may be held is the caller's ``check``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held: dict[str, int] = {}

    @contextmanager
    def hold(self, key: str, check: Callable[[int, int], None]) -> Iterator[None]:
        """Hold one more for ``key`` while the body runs. ``check(mine, total)`` runs under
        the lock first, with ``key``'s count and everyone's, and raises to refuse."""
        with self._lock:
            mine = self._held.get(key, 0)
            check(mine, sum(self._held.values()))
            self._held[key] = mine + 1
        try:
            yield
        finally:
            with self._lock:
                left = self._held[key] - 1
                if left:
                    self._held[key] = left
                else:
                    del self._held[key]


class OpenStreams:
    """At most ``limit`` responses that stay open (Server-Sent Events) per key (an
    account) at once: each holds a connection and a task that polls the job for as long
    as it runs, so one account opening thousands would take them from everyone."""

    #: Seconds a refused client is told to wait (its page falls back to polling anyway).
    RETRY_SECONDS = 5.0

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._open = HeldCounts()

    def slot(self, key: str) -> AbstractContextManager[None]:
        """Hold one of ``key``'s streams while the body runs; :class:`OverLimit` beyond."""
        return self._open.hold(key, self._check)

    def _check(self, mine: int, total: int) -> None:
        if mine >= self.limit:
            raise OverLimit(
                f"too many event streams open: this account already has {mine} (at most "
                f"{self.limit}); close a model page you no longer watch, or poll "
                "GET /api/models/{id} instead.",
                self.RETRY_SECONDS,
            )


# -- surface jobs --------------------------------------------------------------------------

#: Seconds a client told to wait for a job slot is asked to wait before asking again.
JOB_RETRY_SECONDS = 15.0


class JobLimit:
    """At most ``limit`` jobs queued or running per account.

    A job belongs to whoever last queued it (the model's ``submitted_by``), so the count
    survives a restart. A request that finds its model already made, queued or
    running queues nothing and is never refused. One lock makes the check and the
    queuing one step, so two requests at once cannot both take the last slot."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._lock = threading.Lock()

    @contextmanager
    def slot(self, store: Store, user_name: str, volume_id: str, key: str) -> Iterator[None]:
        """Hold the lock while the body queues the job (and records who queued it);
        raises :class:`OverLimit` when it would be one too many."""
        with self._lock:
            if would_queue(store, volume_id, key):
                active = active_jobs(store, user_name)
                if len(active) >= self.limit:
                    raise OverLimit(self._refusal(active), JOB_RETRY_SECONDS)
            yield

    def _refusal(self, active: list[str]) -> str:
        n = len(active)
        return (
            f"you already have {n} model{'s' if n != 1 else ''} being generated "
            f"({', '.join(active)}); wait for one to finish or cancel it "
            "(the Cancel button on its page, or POST /api/models/{id}/cancel), then submit again."
        )


def would_queue(store: Store, volume_id: str, key: str) -> bool:
    """True when no model with these parameters exists, or only a failed one (queued anew)."""
    model = store.find_model(volume_id, key)
    return model is None or model.status == FAILED


def active_jobs(store: Store, user_name: str) -> list[str]:
    """Ids of the models queued or running that ``user_name`` queued last."""
    query = select(ModelRow.id).where(
        ModelRow.status.in_((QUEUED, RUNNING)), ModelRow.submitted_by == user_name
    )
    with store.session() as s:
        return sorted(s.scalars(query))


# -- password checks -----------------------------------------------------------------------

#: Seconds a login waits for its turn at the password check before it is refused (429).
PASSWORD_WAIT = 5.0

P = ParamSpec("P")
T = TypeVar("T")


class PasswordChecks:
    """At most ``at_once`` password checks at a time in this process.

    Checking a password (argon2id: 64 MiB and tens of milliseconds of a core) is the
    dearest thing an anonymous client can ask for; 120 logins at once took both cores
    and every other user's requests waited seconds. The logins beyond ``at_once`` wait
    for a turn on the event loop, holding no thread, at most ``wait`` seconds; then 429
    with ``Retry-After``."""

    def __init__(self, at_once: int, wait: float = PASSWORD_WAIT) -> None:
        self.at_once, self.wait = at_once, wait
        self._turns: anyio.Semaphore | None = None  # made in the event loop, on first use

    async def run(self, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
        """``fn(...)`` in the threadpool once a turn is free; ``OverLimit`` after ``wait``."""
        if self._turns is None:
            self._turns = anyio.Semaphore(self.at_once)
        with anyio.move_on_after(self.wait) as waited:
            await self._turns.acquire()
        if waited.cancelled_caught:
            raise OverLimit(
                f"the server is busy checking other passwords ({self.at_once} at once, "
                f"MISS_PASSWORD_CHECKS); try again in {retry_after(self.wait)} s.",
                self.wait,
            )
        try:
            return await run_in_threadpool(fn, *args, **kwargs)
        finally:
            self._turns.release()


class LoginLimits:
    """Login attempts per client address (10 at once, then one every 30 s) and per
    account name (10, then one a minute, from anywhere): enough for a person who
    mistypes, far too few to guess a password, and a botnet gets no more tries at one
    account than a single client.

    An attempt is counted *before* the password is checked, in one locked step per
    bucket, and given back when the password was right: parallel requests cannot all
    pass a check that reads the count first and adds to it afterwards. Several server
    processes keep their counts in step (``ratelimit.SharedBuckets``)."""

    def __init__(self) -> None:
        self.addresses = KeyedBuckets(capacity=10, rate=1 / 30)
        self.accounts = KeyedBuckets(capacity=10, rate=1 / 60)

    def attempt(self, address: str, name: str) -> None:
        """Count one attempt; ``OverLimit`` (429) when the address or account is locked."""
        wait = self.addresses.take_or_wait(address)
        if wait > 0:
            raise OverLimit(
                f"too many failed logins from {address}; try again in {retry_after(wait)} s "
                f"({_at(wait)}).",
                wait,
            )
        wait = self.accounts.take_or_wait(name.lower())
        if wait > 0:
            self.addresses.give_back(address)
            raise OverLimit(
                f"too many failed logins for the account {name!r}: it is locked; try again "
                f"in {retry_after(wait)} s ({_at(wait)}), or ask an administrator.",
                wait,
            )

    def succeeded(self, address: str, name: str) -> None:
        """Give back the attempts of a login whose password was right."""
        self.addresses.give_back(address)
        self.accounts.give_back(name.lower())


def _at(wait: float) -> str:
    return f"at {(datetime.now(UTC) + timedelta(seconds=retry_after(wait))):%H:%M:%S} UTC"
