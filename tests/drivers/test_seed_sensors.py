"""Seed-tube sensors behind one interface: serial over a real pty, GPIO over a fake request."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import pytest

from drivers.backoff import Backoff
from drivers.errors import DeviceUnavailable
from drivers.seed_sensors import (
    GPIO_READ_INTERVAL_S,
    GpioSeedSensors,
    SeedEdgeEvent,
    SeedSensorSource,
    SerialSeedSensors,
    gpiod_request,
)
from simulator.pty_link import PtyPair
from tests.drivers.helpers import running
from tests.helpers import eventually

FAST = Backoff(initial_s=0.02, cap_s=0.05)


@pytest.fixture
def pty(tmp_path: Path) -> Iterator[PtyPair]:
    with PtyPair(tmp_path / "ttySEED") as pair:
        yield pair


# ---------------------------------------------------------------- serial


async def test_serial_lines_become_edges_stamped_on_arrival(pty: PtyPair) -> None:
    got: list[SeedEdgeEvent] = []
    ticks = iter(range(1000, 100000))
    src = SerialSeedSensors(
        pty.device_path, 115200, 6, got.append, clock=lambda: float(next(ticks)), backoff=FAST
    )
    async with running(src):
        await eventually(lambda: src.available)
        os.write(pty.master_fd, b"D,1\r\n")
        await eventually(lambda: len(got) == 1)
        os.write(pty.master_fd, b"D,6\r\n")
        await eventually(lambda: len(got) == 2)
    assert [e.row for e in got] == [1, 6]
    assert got[0].t_mono < got[1].t_mono  # each stamped by the clock when it arrived
    assert src.stats.edges == 2


async def test_serial_stamps_are_the_monotonic_arrival_time(pty: PtyPair) -> None:
    got: list[SeedEdgeEvent] = []
    src = SerialSeedSensors(pty.device_path, 115200, rows=6, on_edge=got.append, backoff=FAST)
    async with running(src):
        await eventually(lambda: src.available)
        before = time.monotonic()
        os.write(pty.master_fd, b"D,3\r\n")
        await eventually(lambda: bool(got))
        after = time.monotonic()
    assert before <= got[0].t_mono <= after


async def test_serial_bad_lines_are_counted_and_reading_continues(pty: PtyPair) -> None:
    got: list[SeedEdgeEvent] = []
    src = SerialSeedSensors(pty.device_path, 115200, rows=4, on_edge=got.append, backoff=FAST)
    async with running(src):
        await eventually(lambda: src.available)
        os.write(pty.master_fd, b"D,9\r\n\xff\xfe\r\nD,2\r\n")
        await eventually(lambda: len(got) == 1)
    assert got[0].row == 2
    assert src.stats.rejected == 2
    assert src.stats.rejected_by_reason == {"bad_row": 1, "malformed": 1}
    assert src.stats.last_rejected is not None and "not ASCII" in src.stats.last_rejected


async def test_serial_bad_lines_are_warned_about_once_per_kind_and_interval(
    pty: PtyPair, caplog: pytest.LogCaptureFixture
) -> None:
    """Rejected lines were logged at DEBUG only: silent at INFO however many there were."""
    caplog.set_level(logging.INFO)
    got: list[SeedEdgeEvent] = []
    src = SerialSeedSensors(pty.device_path, 115200, rows=4, on_edge=got.append, backoff=FAST)
    async with running(src):
        await eventually(lambda: src.available)
        os.write(pty.master_fd, b"D,9\r\n" * 200 + b"X,1\r\n" * 50 + b"D,2\r\n")
        await eventually(lambda: len(got) == 1)
    assert src.stats.rejected_by_reason == {"bad_row": 200, "malformed": 50}
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2, warnings
    assert "row 9 outside 1..4" in warnings[0] and "unknown record type 'X'" in warnings[1]


async def test_serial_a_failing_callback_does_not_stop_the_reader(pty: PtyPair) -> None:
    seen: list[int] = []

    def flaky(ev: SeedEdgeEvent) -> None:
        seen.append(ev.row)
        if ev.row == 1:
            raise RuntimeError("consumer bug")

    src = SerialSeedSensors(pty.device_path, 115200, rows=6, on_edge=flaky, backoff=FAST)
    async with running(src):
        await eventually(lambda: src.available)
        os.write(pty.master_fd, b"D,1\r\nD,2\r\n")
        await eventually(lambda: seen == [1, 2])


async def test_serial_reconnects_when_the_port_vanishes_and_returns(tmp_path: Path) -> None:
    link = tmp_path / "ttySEED"
    got: list[SeedEdgeEvent] = []
    first = PtyPair(link)
    src = SerialSeedSensors(str(link), 115200, rows=6, on_edge=got.append, backoff=FAST)
    try:
        async with running(src):
            await eventually(lambda: src.available)
            first.close()  # unplugged
            await eventually(lambda: not src.available)
            assert src.stats.last_error is not None
            with PtyPair(link) as second:  # plugged back in
                await eventually(lambda: src.available)
                os.write(second.master_fd, b"D,5\r\n")
                await eventually(lambda: bool(got))
    finally:
        first.close()
    assert got[0].row == 5
    assert src.stats.reconnects >= 1


async def test_serial_a_missing_port_is_retried_not_fatal(tmp_path: Path) -> None:
    src = SerialSeedSensors(str(tmp_path / "nope"), 115200, 6, lambda e: None, backoff=FAST)
    async with running(src):
        await eventually(lambda: src.stats.last_error is not None)
        assert not src.available
    assert "cannot open" in (src.stats.last_error or "")


async def stopped_right_after(
    src: SeedSensorSource, deliver: Callable[[], object]
) -> asyncio.Task[None]:
    """Run ``src`` until available, ``deliver`` edges, and cancel at once: no await between,
    so the driver has not read them yet when the stop comes."""
    task = asyncio.create_task(src.run(), name="seed-sensors-under-test")
    try:
        await eventually(lambda: src.available)
        deliver()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    return task


async def test_serial_lines_already_sent_still_become_edges_when_stopped(pty: PtyPair) -> None:
    """A graceful stop right after the module sent lines: none of them may be dropped."""
    got: list[SeedEdgeEvent] = []
    src = SerialSeedSensors(pty.device_path, 115200, rows=6, on_edge=got.append, backoff=FAST)
    lines = b"".join(b"D,%d\r\n" % (k % 6 + 1) for k in range(30))
    task = await stopped_right_after(src, lambda: os.write(pty.master_fd, lines))
    await asyncio.sleep(0.05)  # let the serial transport close its fd
    assert task.cancelled()  # the stop is honoured, only after the handover
    assert [e.row for e in got] == [k % 6 + 1 for k in range(30)]


def test_serial_refuses_an_impossible_row_count() -> None:
    with pytest.raises(ValueError, match="rows must be"):
        SerialSeedSensors("/dev/null", 115200, rows=0, on_edge=lambda e: None)


# ---------------------------------------------------------------- gpio (fake line request)


class FakeEdgeType(Enum):
    RISING_EDGE = 1
    FALLING_EDGE = 2


@dataclass(frozen=True)
class FakeEdgeEvent:
    event_type: FakeEdgeType
    timestamp_ns: int
    line_offset: int
    global_seqno: int = 0  # 0: not numbered (the tests that do not care about overflow)


@dataclass
class FakeLineRequest:
    """Stands in for gpiod.LineRequest: a real fd that becomes readable when events queue."""

    offsets: Sequence[int]
    bias: str
    fail_reads: bool = False
    queue: list[FakeEdgeEvent] = field(default_factory=list)
    released: bool = False

    def __post_init__(self) -> None:
        self._r, self._w = os.pipe()
        os.set_blocking(self._r, False)

    @property
    def fd(self) -> int:
        return self._r

    def push(self, *events: FakeEdgeEvent) -> None:
        self.queue.extend(events)
        os.write(self._w, b"x")

    reads: int = 0

    def read_edge_events(self) -> list[FakeEdgeEvent]:
        self.reads += 1
        with contextlib.suppress(BlockingIOError):
            os.read(self._r, 64)
        if self.fail_reads:
            raise OSError(5, "Input/output error")
        out, self.queue = self.queue, []
        return out

    def release(self) -> None:
        if not self.released:
            self.released = True
            os.close(self._r)
            os.close(self._w)


class FakeChip:
    def __init__(self, fail_opens: int = 0) -> None:
        self.requests: list[FakeLineRequest] = []
        self.fail_opens = fail_opens
        self.calls = 0

    def __call__(self, chip: str, offsets: Sequence[int], bias: str) -> FakeLineRequest:
        self.calls += 1
        if self.calls <= self.fail_opens:
            raise FileNotFoundError(2, "No such file or directory", chip)
        req = FakeLineRequest(list(offsets), bias)
        self.requests.append(req)
        return req


def falling(offset: int, t_s: float) -> FakeEdgeEvent:
    return FakeEdgeEvent(FakeEdgeType.FALLING_EDGE, round(t_s * 1e9), offset)


async def test_gpio_falling_edges_map_lines_to_rows_with_kernel_timestamps() -> None:
    got: list[SeedEdgeEvent] = []
    chip = FakeChip()
    src = GpioSeedSensors("/dev/gpiochip0", [17, 27, 22], 2.0, got.append, request_factory=chip)
    async with running(src):
        await eventually(lambda: src.available)
        assert chip.requests[0].offsets == [17, 27, 22]
        assert chip.requests[0].bias == "pull_up"
        chip.requests[0].push(falling(27, 100.5), falling(22, 100.6))
        await eventually(lambda: len(got) == 2)
    assert got == [SeedEdgeEvent(2, 100.5), SeedEdgeEvent(3, 100.6)]
    assert chip.requests[0].released


async def test_gpio_lines_are_read_in_batches_not_once_per_edge() -> None:
    """At 2 000 edges/s a wake-up per edge would cost more CPU than the seeds themselves; the
    kernel's timestamps make batching free, so the lines are read at most once per tick."""
    got: list[SeedEdgeEvent] = []
    chip = FakeChip()
    src = GpioSeedSensors("chip", [5, 6], 0.0, got.append, request_factory=chip)
    async with running(src):
        await eventually(lambda: src.available)
        t0 = time.monotonic()
        for k in range(200):  # an edge every ~1 ms for ~0.2 s
            chip.requests[0].push(falling(5 + k % 2, 1.0 + k * 0.001))
            await asyncio.sleep(0.001)
        await eventually(lambda: len(got) == 200)
        elapsed = time.monotonic() - t0
    assert [e.t_mono for e in got] == pytest.approx([1.0 + k * 0.001 for k in range(200)], abs=1e-9)
    assert chip.requests[0].reads <= elapsed / GPIO_READ_INTERVAL_S + 2


async def test_gpio_reads_fall_on_the_shared_tick_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each read after the first waits for the next multiple of GPIO_READ_INTERVAL_S on the
    loop clock, where the recorder's and the store's ticks fall too: one wake-up for all.

    Judged by the instant each pause was scheduled to end (exactly on the grid) and the read
    not coming before it; how late a loaded host runs the callback is not the driver's."""
    loop = asyncio.get_running_loop()
    resumes: list[float] = []  # the instants the driver's pauses end at
    call_at = loop.call_at

    def spy(when: float, callback: Callable[..., object], *args: object,
            **kwargs: object) -> asyncio.TimerHandle:
        if getattr(callback, "__name__", "") == "_resume":
            resumes.append(when)
        return call_at(when, callback, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(loop, "call_at", spy)
    read_at: list[tuple[float, float | None]] = []  # (loop time, the pause it followed)
    chip = FakeChip()
    src = GpioSeedSensors("chip", [5], 0.0,
                          lambda e: read_at.append((loop.time(), resumes[-1] if resumes else None)),
                          request_factory=chip)
    async with running(src):
        await eventually(lambda: src.available)
        for k in range(40):
            chip.requests[0].push(falling(5, 1.0 + k * 0.01))
            await asyncio.sleep(0.005)
        await eventually(lambda: len(read_at) == 40)
    # the first read comes as soon as the first edge does; every later one after a pause
    reads = [(t, w) for t, w in read_at if w is not None]
    assert len({w for _t, w in reads}) >= 2  # several pauses (40 edges over ~0.2 s)
    for when in resumes:
        ticks = when / GPIO_READ_INTERVAL_S
        assert abs(ticks - round(ticks)) < 1e-6, (when, ticks)  # a pause ends on the grid
    for t, when in reads:
        assert t >= when, (t, when)  # and each read waited for its pause to end


async def test_gpio_reads_ahead_of_each_epoch_leave_the_lines_no_wake_up_of_their_own() -> None:
    """The daemon reads the lines ahead of each GNSS epoch (``read_pending``): the edges come
    at once, and the driver's own timed read keeps being put off, so it never fires."""
    got: list[SeedEdgeEvent] = []
    chip = FakeChip()
    src = GpioSeedSensors("chip", [5], 0.0, got.append, request_factory=chip)
    async with running(src):
        await eventually(lambda: src.available)
        request = chip.requests[0]
        request.push(falling(5, 1.0))
        await eventually(lambda: len(got) == 1)  # the driver's own read; it now rests
        src.read_pending()  # nothing queued: no read, but its own next one is put off
        reads = request.reads
        for k in range(8):  # "epochs" 50 ms apart, an edge before each
            request.push(falling(5, 1.1 + k * 0.1))
            await asyncio.sleep(0.05)
            src.read_pending()
            assert len(got) == k + 2  # delivered by this read, not by a later one
        assert request.reads == reads + 8  # and not one read of the driver's own
    assert [e.t_mono for e in got] == pytest.approx([1.0 + k * 0.1 for k in range(9)])


async def test_gpio_read_pending_before_the_lines_are_open_does_nothing() -> None:
    src = GpioSeedSensors("chip", [5], 0.0, lambda e: None, request_factory=FakeChip())
    src.read_pending()
    assert src.stats.edges == 0


async def test_gpio_edges_lost_to_a_kernel_queue_overflow_are_counted() -> None:
    """The kernel numbers every event of a request; a gap means its queue was full and edges
    were dropped. Nothing can bring them back, but they are counted and logged, not hidden."""
    got: list[SeedEdgeEvent] = []
    chip = FakeChip()
    src = GpioSeedSensors("chip", [5], 0.0, got.append, request_factory=chip)

    def numbered(seqno: int, t_s: float) -> FakeEdgeEvent:
        return FakeEdgeEvent(FakeEdgeType.FALLING_EDGE, round(t_s * 1e9), 5, seqno)

    async with running(src):
        await eventually(lambda: src.available)
        chip.requests[0].push(numbered(1, 1.0), numbered(2, 1.1), numbered(6, 1.5))
        await eventually(lambda: len(got) == 3)
        assert src.stats.lost == 3
        chip.requests[0].push(numbered(7, 1.6))
        await eventually(lambda: len(got) == 4)
    assert src.stats.lost == 3


async def test_gpio_edges_the_kernel_already_queued_are_delivered_when_stopped() -> None:
    got: list[SeedEdgeEvent] = []
    chip = FakeChip()
    src = GpioSeedSensors("chip", [5, 6], 2.0, got.append, request_factory=chip)
    task = await stopped_right_after(
        src, lambda: chip.requests[0].push(falling(5, 1.0), falling(6, 1.1))
    )
    assert task.cancelled()
    assert got == [SeedEdgeEvent(1, 1.0), SeedEdgeEvent(2, 1.1)]
    assert chip.requests[0].released


async def test_gpio_bounces_within_the_debounce_time_are_dropped_per_row() -> None:
    got: list[SeedEdgeEvent] = []
    src = GpioSeedSensors("chip", [5, 6], 2.0, got.append, request_factory=FakeChip())
    src.handle_event(falling(5, 10.0))
    src.handle_event(falling(5, 10.0015))  # bounce, 1.5 ms later
    src.handle_event(falling(6, 10.0015))  # other row: not a bounce
    src.handle_event(falling(5, 10.0025))  # 2.5 ms after the first: a new seed
    assert [(e.row, e.t_mono) for e in got] == [(1, 10.0), (2, 10.0015), (1, 10.0025)]
    assert src.stats.debounced == 1


def test_gpio_rising_edges_are_ignored_and_unknown_lines_counted() -> None:
    got: list[SeedEdgeEvent] = []
    src = GpioSeedSensors("chip", [5], 1.0, got.append, request_factory=FakeChip())
    src.handle_event(FakeEdgeEvent(FakeEdgeType.RISING_EDGE, 1, 5))
    src.handle_event(falling(9, 1.0))
    assert got == []
    assert src.stats.rejected == 1
    assert src.stats.rejected_by_reason == {"unknown_line": 1}


async def test_gpio_a_missing_chip_is_retried_until_it_appears() -> None:
    chip = FakeChip(fail_opens=2)
    src = GpioSeedSensors("chip", [5], 1.0, lambda e: None, request_factory=chip, backoff=FAST)
    async with running(src):
        await eventually(lambda: src.available)
    assert chip.calls == 3
    assert "cannot request lines" in (src.stats.last_error or "")


async def test_gpio_a_read_error_releases_and_requests_again() -> None:
    chip = FakeChip()
    src = GpioSeedSensors("chip", [5], 1.0, lambda e: None, request_factory=chip, backoff=FAST)
    async with running(src):
        await eventually(lambda: src.available)
        chip.requests[0].fail_reads = True
        chip.requests[0].push(falling(5, 1.0))
        await eventually(lambda: len(chip.requests) == 2 and src.available)
        assert chip.requests[0].released
    assert src.stats.reconnects == 1


@pytest.mark.parametrize(
    ("lines", "debounce", "message"),
    [([], 1.0, "one GPIO line per row"), ([4, 4], 1.0, "used twice"), ([4], -1.0, ">= 0")],
)
def test_gpio_bad_configuration_is_refused(
    lines: list[int], debounce: float, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        GpioSeedSensors("chip", lines, debounce, lambda e: None)


def test_gpio_without_libgpiod_says_how_to_install_it() -> None:
    try:
        import gpiod  # noqa: F401
    except ImportError:
        with pytest.raises(DeviceUnavailable, match=r"sowgate\[gpio\]"):
            gpiod_request("/dev/gpiochip0", [1], "pull_up")
    else:  # pragma: no cover - only where the optional extra is installed
        with pytest.raises(OSError):
            gpiod_request("/nonexistent/gpiochip", [1], "pull_up")
