"""What several driver tests need: run a read loop for a block, wait for a condition."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable, Coroutine
from typing import Any, Protocol

WAIT_S = 3.0


class Runs(Protocol):
    def run(self) -> Coroutine[Any, Any, None]: ...


async def wait_for(cond: Callable[[], bool], wait_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + wait_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def running(part: Runs) -> AsyncIterator[asyncio.Task[None]]:
    """Run ``part.run()`` for the duration of the block, then cancel it cleanly."""
    task = asyncio.create_task(part.run(), name=f"{type(part).__name__}-under-test")
    try:
        yield task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
