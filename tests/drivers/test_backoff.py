"""Reconnect backoff: exponential, capped, jittered (a fleet must not retry in lockstep)."""

from __future__ import annotations

import random

from drivers.backoff import Backoff


def test_delays_grow_to_the_cap_with_full_jitter_and_reset_after_success() -> None:
    b = Backoff(initial_s=0.5, cap_s=30.0, rng=random.Random(1))
    delays = [b.next_delay() for _ in range(20)]
    ceilings = [min(30.0, 0.5 * 2**i) for i in range(20)]
    assert all(c / 2 <= d <= c for d, c in zip(delays, ceilings, strict=True))
    assert max(delays) <= 30.0 and min(delays[10:]) >= 15.0  # capped, and stays there
    b.reset()
    assert b.next_delay() <= 0.5


def test_two_boxes_after_the_same_outage_do_not_retry_in_lockstep() -> None:
    a = Backoff(initial_s=0.5, cap_s=30.0, rng=random.Random(1))
    b = Backoff(initial_s=0.5, cap_s=30.0, rng=random.Random(2))
    pairs = [(a.next_delay(), b.next_delay()) for _ in range(10)]
    assert all(abs(x - y) > 1e-6 for x, y in pairs)
