"""The operator is told when the as-planted map is not being recorded as it should be."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from datetime import UTC, datetime
from pathlib import Path

import pytest

from drivers.gnss_reader import GnssEpoch, GnssReader
from drivers.seed_sensors import SerialSeedSensors
from gateway.core.alarms import AlarmBoard
from gateway.core.records import AlarmEvent, SeedDrop, SeedRecord
from gateway.recording.health import RecordingHealth
from gateway.recording.recorder import MAX_BUFFERED_DROPS, SeedRecorder
from gateway.recording.store import RecordStore
from tests.gateway.recording.test_recorder import MONO0, feed, settings


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class FailingStore:
    """A store that refuses every batch (card full) until ``heal`` is called."""

    def __init__(self, inner: RecordStore) -> None:
        self.inner = inner
        self.failing = True

    def add_seeds(self, drops: Sequence[SeedDrop]) -> list[SeedRecord]:
        if self.failing:
            raise OSError(28, "No space left on device")
        return self.inner.add_seeds(drops)


@pytest.fixture
def store(tmp_path: Path) -> Iterator[RecordStore]:
    s = RecordStore(tmp_path / "records.sqlite3", "seeder-01")
    yield s
    s.close()


def _epoch(t_mono: float, fix: str = "rtk_fixed", heading_valid: bool = True) -> GnssEpoch:
    return GnssEpoch(
        utc=datetime(2026, 4, 20, 8, tzinfo=UTC), t_mono=t_mono, lat=52.0, lon=13.0, alt_m=40.0,
        fix=fix, speed_kmh=8.0, course_deg=90.0, heading_deg=90.0,  # type: ignore[arg-type]
        heading_valid=heading_valid, num_sv=24,
    )


def _codes(alarms: AlarmBoard) -> dict[str, str]:
    return {a.code: a.severity for a in alarms.active}


def test_a_receiver_that_never_opened_alarms_after_the_hold_and_names_its_port() -> None:
    clock = Clock()
    alarms = AlarmBoard("m")
    reader = GnssReader("/dev/sowgate-gnss", on_epoch=lambda e: None, clock=clock)
    health = RecordingHealth(alarms, gnss=reader, clock=clock)
    health.check()
    assert alarms.active == []  # start-up: the port is still opening
    clock.t += 1.0
    health.check()
    (alarm,) = alarms.active
    assert alarm.code == "gnss.unavailable" and alarm.severity == "warning"
    assert "/dev/sowgate-gnss" in alarm.message


def test_gnss_fix_and_heading_quality_alarm_only_while_recording(store: RecordStore) -> None:
    clock = Clock()
    events: list[AlarmEvent] = []
    alarms = AlarmBoard("m", on_event=events.append)
    reader = GnssReader("/dev/gnss", on_epoch=lambda e: None, clock=clock)
    recorder = SeedRecorder(settings(), store, clock=clock)
    health = RecordingHealth(alarms, gnss=reader, recorder=recorder, clock=clock)
    for _ in range(3):
        reader.latest = _epoch(clock.t, fix="rtk_float", heading_valid=False)
        health.check()
        clock.t += 0.6
    assert _codes(alarms) == {"gnss.not_rtk_fixed": "warning", "gnss.heading_invalid": "info"}
    assert "rtk_float" in next(a.message for a in alarms.active if a.code.endswith("fixed"))
    reader.latest = _epoch(clock.t)
    health.check()
    assert alarms.active == []  # back to RTK fixed: cleared at once
    assert [(e.code, e.active) for e in events].count(("gnss.not_rtk_fixed", True)) == 1
    # a stale epoch is a lost receiver, not a degraded fix
    clock.t += 5.0
    for _ in range(3):
        health.check()
        clock.t += 0.6
    assert set(_codes(alarms)) == {"gnss.unavailable"}
    assert "seed positions are estimates" in alarms.active[0].message
    # without recording, fix quality is nobody's business (the speed does not need RTK)
    quiet = AlarmBoard("m")
    speed_only = RecordingHealth(quiet, gnss=reader, clock=clock)
    reader.latest = _epoch(clock.t, fix="single", heading_valid=False)
    for _ in range(3):
        speed_only.check()
        clock.t += 0.6
        reader.latest = _epoch(clock.t, fix="single", heading_valid=False)
    assert quiet.active == []


def test_seed_sensors_that_are_not_read_alarm() -> None:
    clock = Clock()
    alarms = AlarmBoard("m")
    sensors = SerialSeedSensors("/dev/sowgate-seeds", 115200, 6, lambda e: None)
    health = RecordingHealth(alarms, sensors=sensors, clock=clock)
    health.check()
    clock.t += 1.5
    health.check()
    (alarm,) = alarms.active
    assert alarm.code == "seed_sensors.unavailable"
    assert "seeds are not being recorded" in alarm.message


def test_a_failing_store_raises_one_critical_alarm_until_it_recovers(store: RecordStore) -> None:
    clock = Clock(MONO0 + 3.0)
    events: list[AlarmEvent] = []
    alarms = AlarmBoard("m", on_event=events.append)
    failing = FailingStore(store)
    recorder = SeedRecorder(settings(), failing, clock=clock)
    health = RecordingHealth(alarms, recorder=recorder, store=store, clock=clock)
    feed(recorder, [(3, 1.0), (3, 1.1)], until=2.0)
    for _ in range(4):
        recorder.flush()
        health.check()
        clock.t += 0.5
    (alarm,) = alarms.active
    assert alarm.code == "records.store_failed" and alarm.severity == "critical"
    assert "No space left on device" in alarm.message
    assert sum(e.active for e in events) == 1  # one event, not one per retry
    failing.failing = False
    assert len(recorder.flush()) == 2  # nothing was lost
    health.check()
    assert alarms.active == []


def test_records_dropped_when_the_store_fails_too_long_are_counted(store: RecordStore) -> None:
    dense = settings()  # 10 025 seeds in 4 s on 6 rows: 418 a second a row, above the default
    dense.seed_sensors.max_seeds_per_s_per_row = 1000.0
    recorder = SeedRecorder(dense, FailingStore(store), clock=lambda: MONO0 + 6.0)
    n = MAX_BUFFERED_DROPS + 25
    feed(recorder, [(1 + i % 6, 1.0 + 4.0 * i / n) for i in range(n)], until=5.5)
    recorder.flush()
    assert recorder.records_lost == 25
    assert recorder.state().records_lost == 25
    assert recorder.state().buffered == MAX_BUFFERED_DROPS


def test_a_flood_of_edges_on_one_row_raises_implausible_rate_naming_the_row_then_clears(
    store: RecordStore,
) -> None:
    clock = Clock(MONO0)
    alarms = AlarmBoard()
    recorder = SeedRecorder(settings(), store, clock=clock)
    health = RecordingHealth(alarms, recorder=recorder, clock=clock)
    flood = [(3, 1.0 + k * 1e-5) for k in range(20_000)]  # 20 000 edges in 0.2 s
    normal = [(1, 1.0 + 0.1 * k) for k in range(10)]
    feed(recorder, flood + normal, until=2.5)
    clock.t = MONO0 + 1.5
    recorder.flush()
    health.check()
    clock.t = MONO0 + 2.6  # past the hold
    health.check()
    active = {a.code: a for a in alarms.active}
    assert "seed_sensors.implausible_rate" in active
    assert "row(s) 3 " in active["seed_sensors.implausible_rate"].message
    state = recorder.state()
    assert state.implausible_edges == recorder.plausibility.implausible[3]
    assert state.rows[3].seeds + state.rows[3].implausible_edges <= 20_000
    assert state.rows[3].seeds <= 200 * (0.2 + 1.0)
    assert state.rows[1].seeds == 10 and state.rows[1].implausible_edges == 0
    clock.t = MONO0 + 1.2 + 5.1  # no implausible edge for longer than the clear delay
    health.check()
    assert "seed_sensors.implausible_rate" not in _codes(alarms)
