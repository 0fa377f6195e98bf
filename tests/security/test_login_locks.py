"""A locked account stays locked however many other names and addresses are tried
after it. The finding: the per-account lock lived in an LRU of 10,000 keys, so 10,000
logins under other names pushed it out and gave the guesser 10 fresh tries."""

from __future__ import annotations

import pytest

from miss.server.core.ratelimit import KeyedBuckets, LoginLimits, OverLimit


def test_a_locked_account_cannot_be_pushed_out() -> None:
    limits = LoginLimits()
    for n in range(10):  # ten wrong guesses at the victim, each from an address of its own
        limits.attempt(f"10.0.0.{n}", "victim")
    with pytest.raises(OverLimit):
        limits.attempt("10.0.1.1", "victim")
    # The flood: one guess each at 2 x 10,000 other names, from as many addresses.
    for n in range(20_000):
        limits.attempt(f"10.1.{n // 250}.{n % 250}", f"name{n}")
    with pytest.raises(OverLimit, match="locked"):
        limits.attempt("10.0.1.2", "victim")


def test_buckets_that_refilled_are_still_forgotten() -> None:
    """Memory stays bounded: keys whose buckets are full again (a right password gives
    its token back) are forgotten beyond ``max_keys``."""
    buckets = KeyedBuckets(capacity=10, rate=1 / 60, max_keys=100)
    assert buckets.take("locked")
    for n in range(5_000):
        buckets.take(f"k{n}")
        buckets.give_back(f"k{n}")
    assert len(buckets._buckets) <= 2 * 100
    assert buckets._buckets["locked"].tokens < 10  # still holding its spent token
