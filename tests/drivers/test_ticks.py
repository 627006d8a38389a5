"""The shared tick grid: periodic tasks whose periods divide one another wake together."""

from __future__ import annotations

import asyncio

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.ticks import next_tick, sleep_to_next_tick


@given(
    now=st.floats(min_value=0.0, max_value=1e7, allow_nan=False),
    period=st.sampled_from([0.01, 0.05, 0.1, 0.2, 1 / 3, 1.0]),
)
def test_the_next_tick_is_a_multiple_of_the_period_at_most_one_period_ahead(
    now: float, period: float
) -> None:
    tick = next_tick(now, period)
    assert now < tick <= now + period * (1 + 1e-9)
    assert round(tick / period) * period == pytest.approx(tick, abs=1e-9 * max(1.0, tick))


def test_a_period_of_zero_is_refused() -> None:
    with pytest.raises(ValueError, match="period"):
        next_tick(1.0, 0.0)


async def test_tasks_on_the_grid_wake_in_the_same_loop_iteration() -> None:
    """A 50 ms task and a 200 ms task: every wake of the slow one coincides with one of the
    fast one's, in the same pass of the event loop (counted by a callback that re-arms itself
    once per pass)."""
    loop = asyncio.get_running_loop()
    passes = 0
    counting = True

    def count() -> None:
        nonlocal passes
        passes += 1
        if counting:
            loop.call_soon(count)

    loop.call_soon(count)
    fast: list[int] = []
    slow: list[int] = []

    async def ticker(period: float, seen: list[int], n: int) -> None:
        for _ in range(n):
            await sleep_to_next_tick(period)
            seen.append(passes)

    try:
        await asyncio.gather(ticker(0.05, fast, 12), ticker(0.2, slow, 3))
    finally:
        counting = False
    assert len(slow) == 3
    assert set(slow) <= set(fast)
