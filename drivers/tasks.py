"""Small asyncio helpers shared by drivers, the simulator and the gateway."""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any


async def cancel_and_wait(task: asyncio.Task[Any] | None) -> None:
    """Cancel ``task`` (if any) and wait until it has really finished.

    Waiting matters: a cancelled task that still holds a port or a socket would otherwise
    close it after the caller has already reopened the same device.
    """
    if task is None:
        return
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
