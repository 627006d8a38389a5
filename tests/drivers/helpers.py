"""What several driver tests need: run a read loop for the duration of a block (waiting for a
condition is ``tests.helpers.eventually``)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Coroutine
from typing import Any, Protocol


class Runs(Protocol):
    def run(self) -> Coroutine[Any, Any, None]: ...


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
        await asyncio.sleep(0.05)  # let a serial transport close its fd
