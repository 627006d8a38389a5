"""Small asyncio helpers shared by drivers, the simulator and the gateway.

Why cancelling needs more than ``task.cancel()``: on Python 3.11, ``asyncio.wait_for`` returns
the awaited result instead of raising ``CancelledError`` when the result and the cancellation
arrive in the same loop iteration (CPython gh-86296, fixed in 3.12 only). pymodbus waits for
every reply with ``wait_for`` and the serial readers poll with it, so a loop that reads a
device several times a second sometimes *swallows* the one cancel a TaskGroup sends and keeps
running; the daemon then never gets to set the motor to 0 and never exits, even on SIGTERM.
The helpers below cancel again while a task survives, which is harmless for a task that did
stop and the only cure for one that did not.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterable
from types import TracebackType
from typing import Any, Self

# How long a cancelled task may take to clean up (close a port, flush a file) before it is
# assumed to have swallowed the cancellation and is cancelled again.
RECANCEL_AFTER_S = 0.5


async def cancel_all(
    tasks: Iterable[asyncio.Task[Any]],
    *,
    timeout_s: float | None = None,
    recancel_after_s: float = RECANCEL_AFTER_S,
) -> list[asyncio.Task[Any]]:
    """Cancel every task and wait until each has really finished, cancelling again any that
    is still running ``recancel_after_s`` later (see the module docstring).

    Returns the tasks still running when ``timeout_s`` ran out (empty when all stopped), so
    the caller can name them in a log and carry on with what must happen regardless.

    If the caller is itself cancelled meanwhile (a driver being stopped while it stops its
    reader task), the job is finished first and the cancellation re-raised afterwards:
    giving up half-way would orphan a task that still reads its port.
    """
    pending = {t for t in tasks if not t.done()}
    loop = asyncio.get_running_loop()
    deadline = None if timeout_s is None else loop.time() + timeout_s
    caller_cancelled = False
    while pending:
        for task in pending:
            task.cancel()
        wait_s = recancel_after_s
        if deadline is not None:
            wait_s = min(wait_s, deadline - loop.time())
            if wait_s <= 0:
                break
        try:
            _, pending = await asyncio.wait(pending, timeout=wait_s)
        except asyncio.CancelledError:
            caller_cancelled = True
    if caller_cancelled:
        raise asyncio.CancelledError
    return sorted(pending, key=lambda t: t.get_name())


async def cancel_and_wait(
    task: asyncio.Task[Any] | None, *, recancel_after_s: float = RECANCEL_AFTER_S
) -> None:
    """Cancel ``task`` (if any) and wait until it has really finished.

    Waiting matters: a cancelled task that still holds a port or a socket would otherwise
    close it after the caller has already reopened the same device. A task that swallowed the
    cancellation is cancelled again rather than waited for forever. An exception the task
    ended with (other than the cancellation) is raised here, as awaiting it would.
    """
    if task is None:
        return
    await cancel_all([task], recancel_after_s=recancel_after_s)
    with contextlib.suppress(asyncio.CancelledError):
        await task


class StartClose:
    """``async with part:`` means ``await part.start()`` on the way in and ``await
    part.close()`` on the way out, even after an error: for every part that owns a port, a
    task or a server (the drivers, and the simulator's devices on their ptys)."""

    async def start(self) -> None:
        """Nothing to start unless the part says otherwise."""

    async def close(self) -> None:
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


def raise_if_cancelled() -> None:
    """Honour a cancel that an inner ``wait_for`` swallowed (gh-86296, above): the request
    stays counted in ``Task.cancelling()``. For a loop inside a TaskGroup, which cancels its
    children once: a child that went on after a swallowed cancel kept the group, and so the
    whole stop, waiting for ever."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError
