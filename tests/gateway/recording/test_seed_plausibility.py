"""The per-row plausibility limit: impossible seed rates are counted, real seeding untouched."""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import time
from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.gnss_reader import GnssEpoch
from drivers.seed_sensors import SeedEdgeEvent, SerialSeedSensors
from drivers.tasks import cancel_and_wait
from gateway.config import parse_config
from gateway.config.recording import DEFAULT_MAX_SEEDS_PER_S_PER_ROW
from gateway.core.alarms import AlarmBoard
from gateway.recording.health import RecordingHealth
from gateway.recording.recorder import SeedRecorder
from gateway.recording.seed_plausibility import WINDOW_S, SeedRatePlausibility
from gateway.recording.store import RecordStore
from simulator.pty_link import PtyPair
from tests.helpers import eventually


def _feed(
    limit: SeedRatePlausibility, edges: list[tuple[int, float]], batch_s: float = 0.1
) -> list[tuple[int, float]]:
    """Hand ``edges`` (sorted by time) over in batches as the recorder does, between epochs."""
    kept: list[tuple[int, float]] = []
    i = 0
    while i < len(edges):
        end = edges[i][1] + batch_s
        j = i
        while j < len(edges) and edges[j][1] < end:
            j += 1
        rows, times = limit.filter([r for r, _ in edges[i:j]], [t for _, t in edges[i:j]])
        kept += zip(rows, times, strict=True)
        i = j
    return kept


def _planter(rows: int, seeds_per_s_per_row: float, duration_s: float) -> list[tuple[int, float]]:
    rng = random.Random(3)
    edges = []
    for row in range(1, rows + 1):
        t = rng.random() / seeds_per_s_per_row
        while t < duration_s:
            edges.append((row, 100.0 + t))
            # irregular spacing as a real meter makes: misses, and doubles 2 ms apart
            gap = rng.choice([1.0, 1.0, 1.0, 2.0, 0.002 * seeds_per_s_per_row])
            t += gap / seeds_per_s_per_row * rng.uniform(0.8, 1.2)
    return sorted(edges, key=lambda e: e[1])


def test_a_48_row_planter_at_2100_seeds_per_second_is_untouched() -> None:
    limit = SeedRatePlausibility(DEFAULT_MAX_SEEDS_PER_S_PER_ROW)
    edges = _planter(48, 2100 / 48, 30.0)
    assert _feed(limit, edges) == edges
    assert limit.implausible_total == 0 and limit.rows_implausible_since(0.0) == []


def test_seeding_just_below_the_limit_keeps_every_seed() -> None:
    limit = SeedRatePlausibility(200.0)
    edges = [(1, 100.0 + k / 195.0) for k in range(195 * 20)]
    assert _feed(limit, edges) == edges


def test_a_burst_of_200000_edges_on_one_row_stores_none_of_them() -> None:
    limit = SeedRatePlausibility(200.0)
    burst = [(1, 100.0 + k * 1e-6) for k in range(200_000)]  # 0.2 s
    neighbour = [(2, 100.0 + k / 40.0) for k in range(8)]
    edges = sorted(burst + neighbour, key=lambda e: e[1])
    kept = _feed(limit, edges)
    assert [e for e in kept if e[0] == 1] == []  # a chattering row's edges are not seeds
    assert [e for e in kept if e[0] == 2] == neighbour  # other rows unaffected
    assert limit.implausible == {1: 200_000}
    assert limit.rows_implausible_since(100.1) == [1]
    assert limit.rows_implausible_since(100.3) == []


def test_a_row_chattering_at_2300_per_second_stores_nothing_while_it_chatters() -> None:
    """Issue 20 item 3: ~200 of its 2 300 edges a second were stored as seeds."""
    limit = SeedRatePlausibility(200.0)
    seeds = [(1, 100.0 + k / 40.0) for k in range(40 * 15)]  # 40 real seeds a second, 15 s
    chatter = [(1, 103.0 + k / 2300.0) for k in range(2300 * 10)]  # 3 s..13 s
    kept = _feed(limit, sorted(seeds + chatter, key=lambda e: e[1]))
    kept_times = [t for _, t in kept]
    assert not [t for t in kept_times if 103.0 <= t < 113.0]
    assert len([t for t in kept_times if t < 103.0]) == 120  # before: every seed
    # after: the quarantine's 2 s, then every seed again
    assert [t for t in kept_times if t >= 113.0] == [t for _, t in seeds if t >= 115.0]
    assert limit.implausible_total == len(seeds) + len(chatter) - len(kept)


def test_a_burst_shorter_than_the_bucket_is_kept_and_a_row_just_quarantined_is_not() -> None:
    limit = SeedRatePlausibility(200.0)
    burst = [(1, 100.0 + k * 1e-3) for k in range(int(200.0 * WINDOW_S))]  # fits the bucket
    assert _feed(limit, burst) == burst


def test_a_row_recovers_once_the_flood_stops() -> None:
    limit = SeedRatePlausibility(200.0)
    _feed(limit, [(1, 100.0 + k * 1e-5) for k in range(10_000)])
    after = [(1, 103.0 + k / 40.0) for k in range(80)]
    assert _feed(limit, after) == after


@settings(max_examples=100, deadline=None)
@given(
    gaps=st.lists(st.floats(0.0, 0.05), min_size=1, max_size=1500),
    batch_s=st.sampled_from([0.01, 0.1, 0.5]),
    window=st.floats(0.5, 5.0),
)
def test_no_interval_ever_keeps_more_than_the_limit_allows(
    gaps: list[float], batch_s: float, window: float
) -> None:
    limit = SeedRatePlausibility(100.0, window)
    t, edges = 50.0, []
    for gap in gaps:
        t += gap
        edges.append((1, t))
    kept = [tk for _, tk in _feed(limit, edges, batch_s)]
    assert limit.implausible_total == len(edges) - len(kept)
    for i, start in enumerate(kept):  # every interval that begins at a kept edge
        for j in range(i, len(kept)):
            span = kept[j] - start
            assert j - i + 1 <= 100.0 * (span + window) + 1e-6


def test_a_non_positive_limit_is_refused() -> None:
    with pytest.raises(ValueError, match="max_per_s"):
        SeedRatePlausibility(0.0)


# ---- over a real pty: the edge-capture module's UART, the driver, the recorder, the store ----

PTY_ROWS = 48


@contextlib.asynccontextmanager
async def _recording(tmp_path: Path) -> AsyncIterator[tuple[PtyPair, SeedRecorder, AlarmBoard]]:
    """Serial seed sensors on a pty feeding a recorder and its store, 10 Hz GNSS epochs of a
    drive at 16 km/h, and RecordingHealth checking every 50 ms, until the block ends."""
    settings = parse_config({"machine": {"rows": PTY_ROWS, "working_width_m": 36.0}})
    store = RecordStore(tmp_path / "records.sqlite3", "seeder-01")
    alarms = AlarmBoard()
    recorder = SeedRecorder(settings, store)
    health = RecordingHealth(alarms, recorder=recorder)
    start = time.monotonic()

    async def receiver() -> None:
        while True:
            now = time.monotonic()
            recorder.on_epoch(GnssEpoch(
                utc=datetime(2026, 4, 20, 8, tzinfo=UTC) + timedelta(seconds=now - start),
                t_mono=now, lat=52.0, lon=13.0 + (now - start) * 6.5e-5, alt_m=40.0,
                fix="rtk_fixed", speed_kmh=16.0, course_deg=90.0, heading_deg=90.0,
                heading_valid=True, num_sv=24,
            ))
            health.check()
            await asyncio.sleep(0.05)

    with PtyPair(tmp_path / "ttySEED") as pair:
        sensors = SerialSeedSensors(
            pair.device_path, 115200, PTY_ROWS, lambda event: recorder.on_edge(event)
        )
        tasks = [asyncio.create_task(t) for t in (sensors.run(), recorder.run(), receiver())]
        try:
            await eventually(lambda: sensors.available, what="the seed sensor port to open")
            yield pair, recorder, alarms
        finally:
            for task in tasks:  # the sensors hand over, then the recorder stores everything
                await cancel_and_wait(task)
            store.close()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view) :]
        except BlockingIOError:
            time.sleep(0.001)


async def test_a_burst_of_200000_lines_over_a_pty_stores_only_what_a_row_can_drop(
    tmp_path: Path,
) -> None:
    arrivals: list[float] = []
    async with _recording(tmp_path) as (pty, recorder, alarms):
        on_edge = recorder.on_edge

        def stamped(event: SeedEdgeEvent) -> None:
            arrivals.append(event.t_mono)
            on_edge(event)

        recorder.on_edge = stamped  # type: ignore[method-assign]
        await asyncio.to_thread(_write_all, pty.master_fd, b"D,1\r\n" * 200_000)
        await eventually(
            lambda: len(arrivals) >= 200_000
            and "seed_sensors.implausible_rate" in {a.code for a in alarms.active},
            60.0, "every edge and the implausible-rate alarm",
            detail=lambda: f"{len(arrivals)} edges, alarms {alarms.active}",
        )
        alarm = next(a for a in alarms.active if a.code == "seed_sensors.implausible_rate")
        assert "row(s) 1 " in alarm.message
    dropped = recorder.plausibility.implausible_total
    # every read brings ~200 lines of row 1 with one stamp, more than its bucket holds: each
    # read's batch runs it dry, and a chattering row's edges are not seeds
    assert recorder.records_stored == 0
    assert dropped == 200_000  # every edge counted
    assert recorder.plausibility.implausible == {1: dropped}
    assert recorder.state().rows[1].implausible_edges == dropped


async def test_2100_seeds_per_second_on_48_rows_over_a_pty_are_all_stored(
    tmp_path: Path,
) -> None:
    seconds, per_tick = 3.0, 21  # 21 lines every 10 ms: 2 100 seeds/s, 43.75 a row
    lines = [f"D,{1 + k % PTY_ROWS}\r\n".encode() for k in range(int(2100 * seconds))]
    async with _recording(tmp_path) as (pty, recorder, alarms):
        for i in range(0, len(lines), per_tick):
            os.write(pty.master_fd, b"".join(lines[i : i + per_tick]))
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.6)  # the last lines reach the recorder's queue
        assert alarms.active == []
    assert recorder.plausibility.implausible_total == 0
    assert recorder.records_stored == len(lines)


def test_gpio_edges_with_kernel_stamps_meet_the_same_limit(tmp_path: Path) -> None:
    from drivers.seed_sensors import GpioSeedSensors
    from tests.drivers.test_seed_sensors import FakeChip, falling

    store = RecordStore(tmp_path / "records.sqlite3", "seeder-01")
    try:
        recorder = SeedRecorder(parse_config({"machine": {"rows": 2}}), store)
        gpio = GpioSeedSensors("chip", [5, 6], 0.0, recorder.on_edge, request_factory=FakeChip())
        noise = [falling(5, 100.0 + k * 1e-5) for k in range(5000)]  # 5 000 edges in 50 ms
        seeds = [falling(6, 100.0 + k / 40.0) for k in range(10)]
        gpio.handle_events(sorted(noise + seeds, key=lambda e: e.timestamp_ns))
        recorder.flush()  # what the recorder's tick does
        assert recorder.plausibility.implausible[1] == 5000  # none of the noise is a seed
        assert recorder.plausibility.implausible.get(2, 0) == 0
    finally:
        store.close()
