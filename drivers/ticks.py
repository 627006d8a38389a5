"""Periodic work on one shared grid of instants, so that different tasks' timers fire together.

Why: on a mostly idle core a wake-up costs far more than the little work it does (cold caches,
a slow clock). On the bench machine the daemon's CPU at 2 100 seeds/s fell by a quarter when
the seed-sensor reads went from a hundred wake-ups a second to twenty. Periodic tasks that
sleep "for a period" drift apart and each wake the process on its own; tasks that sleep until
the next *multiple* of their period on the event loop's clock all wake at the same instants
whenever their periods divide one another (the idea of the kernel's ``round_jiffies``). The
seed recorder's flush and the record store's commit (every 500 ms) share one wake-up this way,
and so do the GPIO seed sensors' own reads (every 50 ms; they only need them when no GNSS
epoch comes, since the daemon reads the lines ahead of each epoch).

A tick is never more than one period away, so a task on the grid runs at least as often as
one that sleeps its period after each run.
"""

from __future__ import annotations

import asyncio
import math


def next_tick(now: float, period_s: float) -> float:
    """The first multiple of ``period_s`` strictly after ``now`` (loop clock seconds)."""
    if period_s <= 0:
        raise ValueError(f"tick period must be > 0 s, got {period_s}")
    tick = (math.floor(now / period_s) + 1) * period_s
    # now / period_s may round up to the next integer when now sits just below a tick
    return tick if tick > now else tick + period_s


def _wake(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


async def sleep_to_next_tick(period_s: float) -> None:
    """Sleep until ``next_tick(loop.time(), period_s)``.

    Scheduled with ``call_at`` at exactly the grid instant (``asyncio.sleep(delay)`` would add
    the microseconds between reading the clock and scheduling, so two tasks aiming at the same
    instant could miss each other's loop iteration).
    """
    loop = asyncio.get_running_loop()
    future: asyncio.Future[None] = loop.create_future()
    handle = loop.call_at(next_tick(loop.time(), period_s), _wake, future)
    try:
        await future
    finally:
        handle.cancel()
