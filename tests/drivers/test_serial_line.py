"""SerialLine, the reopen loop the UART drivers share, over real pty pairs."""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.backoff import Backoff
from drivers.serial_line import Drain, SerialLine
from simulator.pty_link import PtyPair
from tests.drivers.helpers import running
from tests.helpers import eventually


def fast() -> Backoff:
    return Backoff(initial_s=0.02, cap_s=0.05)


class Recorder:
    """The driver side: what the line handed over, in order."""

    def __init__(self) -> None:
        self.chunks: list[tuple[bytes, float]] = []
        self.calls: list[str] = []

    @property
    def data(self) -> bytes:
        return b"".join(chunk for chunk, _ in self.chunks)

    def on_data(self, data: bytes, t_arrival: float) -> None:
        self.chunks.append((data, t_arrival))

    def on_open(self, _writer: asyncio.StreamWriter) -> None:
        self.calls.append("open")

    def on_idle(self, _now: float) -> None:
        self.calls.append("idle")

    def on_close(self) -> None:
        self.calls.append("close")


@pytest.fixture
def pty(tmp_path: Path) -> Iterator[PtyPair]:
    with PtyPair(tmp_path / "ttyTEST") as pair:
        yield pair


def line_for(port: str, rec: Recorder, **options: object) -> SerialLine:
    return SerialLine(
        port,
        115200,
        label="test",
        on_data=rec.on_data,
        on_open=rec.on_open,
        on_close=rec.on_close,
        backoff=fast(),
        **options,  # type: ignore[arg-type]
    )


async def test_bytes_reach_the_driver_stamped_by_the_injected_clock(pty: PtyPair) -> None:
    rec = Recorder()
    ticks = iter(range(1000, 100000))
    line = line_for(pty.device_path, rec, clock=lambda: float(next(ticks)))
    async with running(line):
        await eventually(lambda: line.connected)
        assert line.writer is not None and rec.calls == ["open"]
        os.write(pty.master_fd, b"hello")
        await eventually(lambda: rec.data == b"hello")
        os.write(pty.master_fd, b" world")
        await eventually(lambda: rec.data == b"hello world")
    stamps = [t for _, t in rec.chunks]
    assert stamps == sorted(stamps) and all(t >= 1000.0 for t in stamps)
    assert line.stats.connects == 1 and line.stats.reconnects == 0
    assert line.stats.last_error is None


async def test_the_writer_sends_to_the_device(pty: PtyPair) -> None:
    rec = Recorder()
    line = line_for(pty.device_path, rec)
    async with running(line):
        await eventually(lambda: line.writer is not None)
        assert line.writer is not None
        line.writer.write(b"ping")
        got = b""

        def arrived() -> bool:
            nonlocal got
            with contextlib.suppress(BlockingIOError):
                got += os.read(pty.master_fd, 64)
            return got == b"ping"

        await eventually(arrived)


async def test_a_missing_port_is_retried_until_it_appears(tmp_path: Path) -> None:
    link = tmp_path / "ttyLATE"
    rec = Recorder()
    line = line_for(str(link), rec)
    async with running(line) as task:
        await eventually(lambda: line.stats.open_failures >= 3)
        assert not line.connected and not task.done() and line.writer is None
        assert line.stats.last_error is not None
        assert line.stats.last_error.startswith(f"cannot open {link}")
        with PtyPair(link):  # plugged in late
            await eventually(lambda: line.connected)
    assert line.stats.connects == 1 and rec.calls == ["open", "close"]


async def test_a_setting_the_port_refuses_is_retried_not_fatal(pty: PtyPair) -> None:
    """pyserial raises ValueError for an impossible baud rate: a failed open, not a crash."""
    rec = Recorder()
    line = SerialLine(pty.device_path, -1, label="test", on_data=rec.on_data, backoff=fast())
    async with running(line) as task:
        await eventually(lambda: line.stats.open_failures >= 2)
        assert not task.done() and not line.connected
    assert "cannot open" in (line.stats.last_error or "")


async def test_a_vanished_port_is_closed_and_reopened_when_it_returns(tmp_path: Path) -> None:
    link = tmp_path / "ttyUSB"
    rec = Recorder()
    first = PtyPair(link)
    line = line_for(str(link), rec)
    try:
        async with running(line):
            await eventually(lambda: line.connected)
            first.close()  # unplugged
            await eventually(lambda: not line.connected)
            assert line.stats.disconnects == 1 and rec.calls == ["open", "close"]
            assert line.writer is None and line.stats.last_error is not None
            with PtyPair(link) as second:  # plugged back in
                await eventually(lambda: line.connected)
                os.write(second.master_fd, b"back")
                await eventually(lambda: rec.data == b"back")
    finally:
        first.close()
    assert line.stats.connects == 2 and line.stats.reconnects == 1
    assert line.stats.last_error is not None  # why it was lost is kept after reopening


async def test_a_silent_port_is_reopened(pty: PtyPair) -> None:
    rec = Recorder()
    line = line_for(pty.device_path, rec, silence_reconnect_s=0.1)
    async with running(line):
        await eventually(lambda: line.stats.connects >= 2)
    assert line.stats.disconnects >= 1
    assert line.stats.last_error == f"{pty.device_path}: no data for 0.1 s"
    assert rec.calls[:3] == ["open", "close", "open"]


async def test_bytes_keep_a_port_with_a_silence_limit_open(pty: PtyPair) -> None:
    rec = Recorder()
    line = line_for(pty.device_path, rec, silence_reconnect_s=0.2)
    async with running(line):
        await eventually(lambda: line.connected)
        for _ in range(8):  # 0.4 s of talk, a byte every 50 ms
            os.write(pty.master_fd, b".")
            await asyncio.sleep(0.05)
        assert line.stats.connects == 1 and line.stats.disconnects == 0


async def test_idle_is_called_only_while_the_driver_asks_for_it(pty: PtyPair) -> None:
    rec = Recorder()
    wanted: list[float | None] = [None]
    line = line_for(pty.device_path, rec, on_idle=rec.on_idle, idle_after_s=lambda: wanted[0])
    async with running(line):
        await eventually(lambda: line.connected)
        await asyncio.sleep(0.15)
        assert "idle" not in rec.calls  # the driver holds nothing: no timeout at all
        wanted[0] = 0.03
        os.write(pty.master_fd, b"x")  # the next read asks again
        await eventually(lambda: rec.calls.count("idle") >= 2)
    assert line.connected is False and line.stats.disconnects == 0  # idle is not a loss


async def test_a_cancel_closes_the_port_and_tells_the_driver(pty: PtyPair) -> None:
    rec = Recorder()
    line = line_for(pty.device_path, rec)
    async with running(line) as task:
        await eventually(lambda: line.connected)
    assert task.cancelled()
    assert rec.calls == ["open", "close"]
    assert not line.connected and line.writer is None
    assert line.stats.disconnects == 0 and line.stats.last_error is None


async def test_with_drain_a_cancel_first_hands_over_what_was_already_sent(pty: PtyPair) -> None:
    rec = Recorder()
    line = line_for(pty.device_path, rec, drain=Drain(quiet_s=0.05, timeout_s=0.3))
    payload = bytes(range(256)) * 8
    task = asyncio.create_task(line.run(), name="serial-line-under-test")
    await eventually(lambda: line.connected)
    os.write(pty.master_fd, payload)
    task.cancel()  # no await between: the line has not read the bytes yet
    with contextlib.suppress(asyncio.CancelledError):
        await task
    assert task.cancelled()
    assert rec.data == payload and rec.calls == ["open", "close"]


async def test_without_drain_a_cancel_is_honoured_at_once(pty: PtyPair) -> None:
    rec = Recorder()
    line = line_for(pty.device_path, rec)
    task = asyncio.create_task(line.run(), name="serial-line-under-test")
    await eventually(lambda: line.connected)
    os.write(pty.master_fd, b"late")
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    assert rec.data == b""


async def test_a_bug_in_the_driver_on_close_still_closes_the_port(pty: PtyPair) -> None:
    def broken_close() -> None:
        raise RuntimeError("driver bug")

    rec = Recorder()
    line = SerialLine(
        pty.device_path, 115200, label="test", on_data=rec.on_data, on_close=broken_close,
        backoff=fast(),
    )
    task = asyncio.create_task(line.run(), name="serial-line-under-test")
    await eventually(lambda: line.connected)
    writer = line.writer
    task.cancel()
    with pytest.raises(RuntimeError, match="driver bug"):
        await task
    assert writer is not None and writer.is_closing() and not line.connected


async def test_a_write_the_device_is_slow_to_take_leaves_no_busy_writer(pty: PtyPair) -> None:
    """pyserial-asyncio-fast 0.16 leaves its writer callback registered after a partial write
    completes and then asserts on the empty buffer on every loop turn (a busy loop of logged
    tracebacks); the line's guard removes the callback instead."""
    rec = Recorder()
    errors: list[str] = []
    loop = asyncio.get_running_loop()
    loop.set_exception_handler(lambda _loop, ctx: errors.append(str(ctx.get("exception"))))
    line = line_for(pty.device_path, rec)
    try:
        async with running(line):
            await eventually(lambda: line.writer is not None)
            assert line.writer is not None
            line.writer.write(b"x" * 200_000)  # far more than a pty buffer holds: partial
            got = 0

            def drained() -> bool:
                nonlocal got
                with contextlib.suppress(BlockingIOError):
                    while chunk := os.read(pty.master_fd, 65536):
                        got += len(chunk)
                return got >= 200_000

            await eventually(drained, 30)
            for _ in range(50):  # the fd stays writable: any callback left would fire now
                await asyncio.sleep(0.001)
            assert line.writer.transport.get_write_buffer_size() == 0
    finally:
        loop.set_exception_handler(None)
    assert errors == []
