"""The seed recorder: driver callbacks in, stored records with ids and row quality out."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import pymap3d
import pytest
from hypothesis import given
from hypothesis import settings as settings_
from hypothesis import strategies as st

from drivers.seed_sensors import SeedEdgeEvent
from gateway.config import Settings, parse_config
from gateway.core.records import SeedDrop, SeedRecord
from gateway.recording.positioning import ClockMap, LocalFrame, SeedPositioner
from gateway.recording.recorder import MAX_QUEUED_EVENTS, SeedRecorder
from gateway.recording.store import RecordStore
from simulator.plant import Drive, Leg
from tests.gateway.recording.test_positioning import FRAME, LATENCY_S, MONO0, epoch_from_pose

DRIVE = Drive(legs=[Leg(6.0, 7.2)], start_heading_deg=90.0, accel_ms2=100.0)  # 2 m/s


def settings() -> Settings:
    return parse_config(
        {"positioning": {"gnss_output_latency_ms": LATENCY_S * 1000, "target_spacing_m": 0.2}}
    )


@pytest.fixture
def store(tmp_path: Path) -> Iterator[RecordStore]:
    s = RecordStore(tmp_path / "records.sqlite3", "seeder-01")
    yield s
    s.close()


def _events(edges: list[tuple[int, float]], until: float) -> list[object]:
    """10 Hz epochs of DRIVE up to ``until`` s and the given (row, s) edges, in time order."""
    events: list[tuple[float, object]] = []
    k = 0
    while k * 0.1 <= until:
        e = epoch_from_pose(DRIVE.pose_at(k * 0.1), FRAME)
        events.append((e.t_mono, e))
        k += 1
    events += [(MONO0 + t, SeedEdgeEvent(row, MONO0 + t)) for row, t in edges]
    events.sort(key=lambda x: x[0])
    return [ev for _t, ev in events]


def feed(rec: SeedRecorder, edges: list[tuple[int, float]], until: float) -> None:
    for ev in _events(edges, until):
        if isinstance(ev, SeedEdgeEvent):
            rec.on_edge(ev)
        else:
            rec.on_epoch(ev)  # type: ignore[arg-type]


def test_positioned_seeds_reach_the_store_with_ids_and_then_the_callback(
    store: RecordStore,
) -> None:
    seen: list[SeedRecord] = []
    rec = SeedRecorder(settings(), store, on_records=seen.extend, clock=lambda: MONO0 + 3.0)
    # row 1 every 0.1 s (0.2 m), with one double at 1.3 s; row 4 twice
    edges = [(1, 1.0 + 0.1 * i) for i in range(6)] + [(1, 1.305), (4, 1.0), (4, 1.1)]
    feed(rec, edges, until=2.5)
    assert seen == []  # nothing is handed on before the store took it
    stored = rec.flush()
    assert [r.id for r in stored] == list(range(1, len(edges) + 1))
    assert seen == stored
    state = rec.state()
    assert state.records_stored == len(edges)
    assert state.rows[1].seeds == 7 and state.rows[4].seeds == 2
    assert state.rows[4].last_spacing_m == pytest.approx(0.2, abs=0.003)
    q1 = state.rows[1].quality
    assert q1.n == 6 and q1.multiples_index == pytest.approx(100 / 6)
    assert state.rows[2].seeds == 0 and state.rows[2].quality.n == 0


def test_an_edge_for_an_unknown_row_is_counted_and_recording_goes_on(
    store: RecordStore,
) -> None:
    rec = SeedRecorder(settings(), store, clock=lambda: MONO0 + 3.0)
    feed(rec, [(9, 1.0), (2, 1.0)], until=2.0)
    assert len(rec.flush()) == 1
    assert rec.bad_edges == 1 and "row 9" in (rec.state().last_error or "")


class FailingOnce:
    """A store that refuses the first batch (disk full, locked) and then recovers."""

    def __init__(self, inner: RecordStore) -> None:
        self.inner = inner
        self.calls = 0

    def add_seeds(self, drops: Sequence[SeedDrop]) -> list[SeedRecord]:
        self.calls += 1
        if self.calls == 1:
            raise OSError(28, "No space left on device")
        return self.inner.add_seeds(drops)


def test_a_store_failure_keeps_the_seeds_for_the_next_flush(store: RecordStore) -> None:
    rec = SeedRecorder(settings(), FailingOnce(store), clock=lambda: MONO0 + 3.0)
    feed(rec, [(3, 1.0), (3, 1.1)], until=2.0)
    assert rec.flush() == []
    assert rec.store_errors == 1 and "No space left" in (rec.last_error or "")
    assert len(rec.flush()) == 2


async def test_run_flushes_periodically_and_positions_the_rest_on_shutdown(
    store: RecordStore,
) -> None:
    rec = SeedRecorder(settings(), store, clock=lambda: MONO0 + 1.2)
    feed(rec, [(5, 1.0)], until=1.5)  # positioned, waiting in the buffer
    rec.on_edge(SeedEdgeEvent(5, MONO0 + 1.5))  # needs an epoch that never comes
    task = asyncio.create_task(rec.run(), name="seed-recorder")
    for _ in range(50):
        await asyncio.sleep(0.02)
        if rec.records_stored:
            break
    assert rec.records_stored == 1 and rec.positioner.pending == 1
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    assert rec.records_stored == 2
    store.flush()
    last = list(store.query_seeds())[-1]
    assert last.extrapolated and last.row == 5


# ---------------------------------------------------------------- the per-seed hot path
# The recorder positions every seed through LocalFrame.to_geodetic and ClockMap; both were
# made cheaper for the record path (bench_mqtt). These pin them to their references.


@settings_(max_examples=300, deadline=None)
@given(
    lat0=st.floats(-80.0, 80.0), lon0=st.floats(-180.0, 180.0), alt0=st.floats(-400.0, 5000.0),
    east=st.floats(-50_000.0, 50_000.0), north=st.floats(-50_000.0, 50_000.0),
    up=st.floats(-500.0, 500.0),
)
def test_seed_latitude_and_longitude_agree_with_pymap3d(
    lat0: float, lon0: float, alt0: float, east: float, north: float, up: float
) -> None:
    """The scalar ENU → WGS84 conversion equals pymap3d's to far below a millimetre."""
    lat, lon = LocalFrame(lat0, lon0, alt0).to_geodetic(east, north, up)
    ref_lat, ref_lon, _ = pymap3d.enu2geodetic(east, north, up, lat0, lon0, alt0)
    assert lat == pytest.approx(float(ref_lat), abs=1e-11)  # 1e-11° ≈ 1 µm
    assert (lon - float(ref_lon) + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-11)


def test_near_the_pole_the_conversion_still_agrees_with_pymap3d() -> None:
    """Where the closed form degenerates, pymap3d answers itself."""
    frame = LocalFrame(90.0, 0.0, 0.0)
    lat, lon = frame.to_geodetic(0.5, 0.5, 0.0)
    ref_lat, ref_lon, _ = pymap3d.enu2geodetic(0.5, 0.5, 0.0, 90.0, 0.0, 0.0)
    assert (lat, lon) == pytest.approx((float(ref_lat), float(ref_lon)), abs=1e-11)


def test_clock_offset_follows_the_window_minimum_as_old_epochs_leave_it() -> None:
    """The offset is the minimum over the window, also once the old minimum drops out."""
    clock = ClockMap(latency_s=0.0, window=3)
    for k, raw in enumerate([5.0, 5.3, 5.2, 5.4, 5.25]):
        clock.observe(100.0 + k + raw, 100.0 + k)
        window = [5.0, 5.3, 5.2, 5.4, 5.25][max(0, k - 2): k + 1]
        assert clock.offset_s == pytest.approx(min(window))


def test_a_reset_clock_maps_by_the_epochs_after_it_alone() -> None:
    """A time step (judged by gnss_time.GnssTimeGuard) restarts the offset window."""
    clock = ClockMap(latency_s=0.0)
    clock.observe(105.0, 100.0)
    clock.reset()
    assert not clock.ready
    clock.observe(110.0, 101.0)
    assert clock.offset_s == pytest.approx(9.0)


async def four_seeds_through_the_loop(
    store: RecordStore, until: Callable[[SeedRecorder], bool]
) -> SeedRecorder:
    """Four seeds of row 2, 0.2 m apart, then the periodic loop until ``until`` (≤ 1 s)."""
    rec = SeedRecorder(settings(), store, clock=lambda: MONO0 + 3.0)
    feed(rec, [(2, 1.0 + 0.1 * i) for i in range(4)], until=2.5)
    task = asyncio.create_task(rec.run(), name="seed-recorder")
    try:
        for _ in range(50):
            await asyncio.sleep(0.02)
            if until(rec):
                break
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    return rec


async def test_the_periodic_loop_stores_ids_only_and_keeps_the_row_statistics(
    store: RecordStore,
) -> None:
    """Without an on_records listener the loop stores drops without building records."""
    rec = await four_seeds_through_the_loop(store, until=lambda r: r.records_stored == 4)
    assert rec.records_stored == 4 and rec.seeds_per_row[2] == 4
    assert rec.last_spacing_m[2] == pytest.approx(0.2, abs=0.02)
    store.flush()
    assert [r.id for r in store.query_seeds()] == [1, 2, 3, 4]


# ---------------------------------------------------------------- one burst per flush


def test_driver_callbacks_only_queue_and_the_flush_positions_in_arrival_order(
    store: RecordStore,
) -> None:
    """The seed path runs in one burst per flush; the records are exactly those of feeding
    the positioner live, event by event."""
    edges = [(1 + i % 6, 1.0 + 0.05 * i) for i in range(30)]
    queued = SeedRecorder(settings(), store, clock=lambda: MONO0 + 3.0)
    feed(queued, edges, until=2.8)
    assert queued.positioner.stats.epochs == 0 and queued.state().queued > 30
    live = SeedPositioner(settings().positioning)
    landed = []
    for ev in _events(edges, until=2.8):
        if isinstance(ev, SeedEdgeEvent):
            landed += live.add_edge(ev.row, ev.t_mono)
        else:
            landed += live.add_epoch(ev)
    landed += live.poll(MONO0 + 3.0)
    records = queued.flush()
    assert [(r.row, r.utc, r.lat, r.lon, r.spacing_m) for r in records] == [
        (la.drop.row, la.drop.utc, la.drop.lat, la.drop.lon, la.drop.spacing_m) for la in landed
    ]
    assert len(records) == 30 and queued.state().queued == 0


def test_a_stalled_flush_loop_positions_inline_so_the_queue_stays_bounded(
    store: RecordStore,
) -> None:
    rec = SeedRecorder(settings(), store, clock=lambda: MONO0 + 3.0)
    feed(rec, [(1, 0.5 + i * 0.001) for i in range(MAX_QUEUED_EVENTS + 50)], until=2.8)
    assert rec.state().queued < MAX_QUEUED_EVENTS
    assert rec.positioner.stats.epochs > 0


async def test_the_periodic_loop_commits_what_it_stored_in_the_same_burst(
    store: RecordStore,
) -> None:
    """The outbox sees stored seeds at once, not at the store's next commit tick."""
    await four_seeds_through_the_loop(store, until=lambda _r: bool(store.pending_seeds(10)))
    assert [r.id for r in store.pending_seeds(10)] == [1, 2, 3, 4]


def test_a_stalled_loop_does_not_extrapolate_seeds_whose_epochs_wait_in_its_buffers(
    store: RecordStore,
) -> None:
    """The loop stalls 1.25 s → 2.0 s (a loaded box). On waking, the seed line's task runs
    first: the lines of the stall are stamped 2.0 s and queued ahead of the receiver's epochs
    of the stall, which arrive stamped 2.0 s too. The seeds sown before the stall have waited
    longer than ``pending_timeout_s`` by the stamps of the later edges, yet their epochs are
    right behind in the queue, or still in the GNSS task's buffer when the flush runs: they
    are interpolated, never extrapolated from the last epoch before the stall."""
    import dataclasses

    now = [MONO0 + 1.25]
    rec = SeedRecorder(settings(), store, clock=lambda: now[0])
    before = [(1 + i % 6, 1.0 + 0.04 * i) for i in range(6)]  # 1.0–1.2 s, before the stall
    feed(rec, before, until=1.15)  # the epochs up to 1.1 s arrived before the stall
    rec.flush()  # the flush tick just before the stall
    now[0] = MONO0 + 2.0
    for row in range(1, 7):  # the seed lines of the stall: one read, one stamp
        rec.on_edge(SeedEdgeEvent(row, MONO0 + 2.0))
    rec.flush()  # the flush tick runs before the GNSS task has queued the stall's epochs
    for k in range(12, 21):  # 1.2–2.0 s: arrive on waking, stamped 2.0 s
        epoch = epoch_from_pose(DRIVE.pose_at(k * 0.1), FRAME)
        rec.on_epoch(dataclasses.replace(epoch, t_mono=MONO0 + 2.0))
    now[0] = MONO0 + 2.5
    records = rec.flush()
    assert len(records) == len(before)  # the stall's own seeds wait for the epochs after 2.0 s
    assert not [r for r in records if r.extrapolated]
    assert rec.positioner.stats.extrapolated == 0
    assert {r.row for r in records} == set(range(1, 7))
