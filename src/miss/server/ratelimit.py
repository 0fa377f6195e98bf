"""Limits that keep one client from starving the others.

- :class:`TokenBucket` and :class:`KeyedBuckets`: a burst of ``capacity`` at once, then
  ``rate`` per second; per WebSocket connection (room messages), per client address
  (failed logins).
- :class:`ApiLimits` and :class:`RateLimitMiddleware`: the REST API's bucket per account,
  or per client address for requests without a known session (share-link viewers).
- :class:`JobLimit`: how many surface jobs one account may have queued or running.

Over a limit the answer is 429 with a JSON ``detail`` and a ``Retry-After`` header.
"""

from __future__ import annotations

import hashlib
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import select
from starlette.requests import HTTPConnection
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from miss.server.auth import presented_token
from miss.server.errors import TooManyRequests
from miss.server.storage.db import FAILED, QUEUED, RUNNING, ModelRow
from miss.server.storage.store import Store


class TokenBucket:
    """``take()`` is True while tokens remain; they refill continuously at ``rate``/s."""

    def __init__(self, capacity: float, rate: float) -> None:
        self.capacity, self.rate = float(capacity), float(rate)
        self.tokens = float(capacity)
        self.stamp = time.monotonic()

    def take(self, cost: float = 1.0) -> bool:
        now = time.monotonic()
        self.tokens = min(self.capacity, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= cost:
            self.tokens -= cost
            return True
        return False

    def seconds_until(self, cost: float = 1.0) -> float:
        """How long until ``take(cost)`` would succeed."""
        return max(0.0, (cost - self.tokens) / self.rate) if self.rate > 0 else float("inf")


class KeyedBuckets:
    """One bucket per key (a client address), the oldest forgotten beyond ``max_keys``
    so a scan from many addresses cannot grow memory without end. Thread-safe."""

    def __init__(self, capacity: float, rate: float, max_keys: int = 10_000) -> None:
        self.capacity, self.rate, self.max_keys = capacity, rate, max_keys
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()
        self._lock = threading.Lock()

    def take(self, key: str, cost: float = 1.0) -> bool:
        with self._lock:
            return self._bucket(key).take(cost)

    def take_or_wait(self, key: str, cost: float = 1.0) -> float:
        """Take ``cost`` tokens: 0.0 when they were there, else the seconds until they
        will be (and nothing is taken)."""
        with self._lock:
            bucket = self._bucket(key)
            return 0.0 if bucket.take(cost) else max(bucket.seconds_until(cost), 1e-3)

    def give_back(self, key: str, cost: float = 1.0) -> None:
        """Return ``cost`` tokens taken for an attempt that turned out fine."""
        with self._lock:
            bucket = self._bucket(key)
            bucket.tokens = min(bucket.capacity, bucket.tokens + cost)

    def allowed(self, key: str) -> tuple[bool, float]:
        """(a token is there now, seconds until one is) without taking it."""
        with self._lock:
            bucket = self._bucket(key)
            ok = bucket.take(0.0) and bucket.tokens >= 1.0
            return ok, bucket.seconds_until()

    def _bucket(self, key: str) -> TokenBucket:
        bucket = self._buckets.pop(key, None) or TokenBucket(self.capacity, self.rate)
        self._buckets[key] = bucket
        while len(self._buckets) > self.max_keys:
            self._buckets.popitem(last=False)
        return bucket


def too_many(detail: str, wait: float) -> JSONResponse:
    """The 429 answer: ``detail`` and ``Retry-After`` in whole seconds (at least 1)."""
    return JSONResponse(
        {"detail": detail}, status_code=429, headers={"Retry-After": str(retry_after(wait))}
    )


def retry_after(wait: float) -> int:
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
            "(DELETE /api/models/{id}), then submit again."
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
