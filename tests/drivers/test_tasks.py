"""Stopping tasks for real: the shutdown path that sets the motor and fan to 0 depends on it."""

from __future__ import annotations

import asyncio
import contextlib

import pytest

from drivers.tasks import cancel_all, cancel_and_wait


def _poller(replies: list[asyncio.Future[bytes]], reads: list[bytes]) -> asyncio.Task[None]:
    """A device-polling loop built like pymodbus's and the GNSS reader's: ``wait_for`` on a
    reply, forever."""
    loop = asyncio.get_running_loop()

    async def poll() -> None:
        while True:
            reply: asyncio.Future[bytes] = loop.create_future()
            replies.append(reply)
            reads.append(await asyncio.wait_for(reply, 10.0))

    return asyncio.create_task(poll(), name="poller")


async def test_a_loop_whose_wait_for_swallowed_the_cancel_is_still_stopped() -> None:
    replies: list[asyncio.Future[bytes]] = []
    reads: list[bytes] = []
    task = _poller(replies, reads)
    await asyncio.sleep(0)  # the poller now waits for a reply
    # The reply arrives in the same loop iteration as the stop: on Python 3.11 wait_for hands
    # back the reply and drops the cancellation, and the loop polls on.
    replies[-1].set_result(b"\x01\x03\x02\x01\xf4")
    await asyncio.wait_for(cancel_and_wait(task, recancel_after_s=0.05), 2.0)
    assert task.cancelled()


async def test_a_task_that_ignores_one_cancel_is_cancelled_again() -> None:
    cancels_seen = 0

    async def stubborn() -> None:
        nonlocal cancels_seen
        while True:
            try:
                await asyncio.sleep(10)
            except asyncio.CancelledError:
                cancels_seen += 1
                if cancels_seen > 1:
                    raise

    task = asyncio.create_task(stubborn())
    await asyncio.sleep(0)
    await asyncio.wait_for(cancel_and_wait(task, recancel_after_s=0.05), 2.0)
    assert task.cancelled()
    assert cancels_seen == 2


async def test_a_task_cleaning_up_is_given_time_before_a_second_cancel() -> None:
    cleaned = asyncio.Event()

    async def closes_its_port() -> None:
        try:
            await asyncio.sleep(10)
        finally:
            await asyncio.sleep(0.1)  # e.g. waiting for the serial transport to close the fd
            cleaned.set()

    task = asyncio.create_task(closes_its_port())
    await asyncio.sleep(0)
    await cancel_and_wait(task, recancel_after_s=0.5)
    assert cleaned.is_set()


async def test_a_cancelled_caller_still_finishes_stopping_its_child_first() -> None:
    """A driver cancelled while it stops its reader must not leave the reader running."""
    child_cancels = 0

    async def reader_swallowing_one_cancel() -> None:
        nonlocal child_cancels
        while True:
            try:
                await asyncio.sleep(10)
            except asyncio.CancelledError:
                child_cancels += 1
                if child_cancels > 1:
                    raise

    child = asyncio.create_task(reader_swallowing_one_cancel())

    async def driver_stopping() -> None:
        await cancel_and_wait(child, recancel_after_s=0.2)

    caller = asyncio.create_task(driver_stopping())
    await asyncio.sleep(0.05)  # the caller has cancelled the child once, which swallowed it
    caller.cancel()  # e.g. the daemon's supervisor cancelling the driver task again
    await asyncio.wait({caller}, timeout=2.0)
    assert caller.cancelled()
    assert child.done() and child_cancels == 2


async def test_cancel_all_names_the_tasks_that_outlive_the_timeout() -> None:
    release = asyncio.Event()

    async def immortal() -> None:
        while not release.is_set():
            try:
                await asyncio.sleep(10)
            except asyncio.CancelledError:
                continue

    async def polite() -> None:
        await asyncio.sleep(10)

    stuck = asyncio.create_task(immortal(), name="stuck")
    fine = asyncio.create_task(polite(), name="fine")
    await asyncio.sleep(0)
    left = await cancel_all([stuck, fine], timeout_s=0.2, recancel_after_s=0.05)
    assert left == [stuck]
    assert fine.cancelled()
    release.set()
    await cancel_and_wait(stuck)
    assert stuck.done()


async def test_an_exception_the_task_ended_with_is_raised() -> None:
    async def broken() -> None:
        raise RuntimeError("port exploded")

    task = asyncio.create_task(broken())
    await asyncio.sleep(0)
    with pytest.raises(RuntimeError, match="port exploded"):
        await cancel_and_wait(task)


async def test_none_is_accepted() -> None:
    await cancel_and_wait(None)


async def test_a_loop_that_swallowed_a_cancel_still_stops_at_its_next_check() -> None:
    """A cancel swallowed inside a loop (what a 3.11 ``wait_for`` can do) stays counted in
    ``Task.cancelling()``: ``raise_if_cancelled`` after the swallowing call honours it, so a
    TaskGroup that cancelled its children once is not left waiting for this one for ever."""
    from drivers.tasks import raise_if_cancelled

    laps = 0
    started = asyncio.Event()

    async def publisher_loop() -> None:
        nonlocal laps
        while True:
            laps += 1
            started.set()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.sleep(3600)  # swallowed, as the inner wait_for of a publish can
            raise_if_cancelled()

    async with asyncio.TaskGroup() as tg:
        task = tg.create_task(publisher_loop())
        await started.wait()
        task.cancel()  # once, as a TaskGroup's abort does
    assert task.cancelled() and laps == 1
