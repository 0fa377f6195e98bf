"""Token buckets: a burst of ``capacity`` at once, then ``rate`` per second.

Used per WebSocket connection (room messages) and per client address (failed logins);
the hardening work reuses them for the REST API.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict


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
