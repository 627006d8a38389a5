"""The record store marks each daemon start and stop: a clean stop writes its own time, an
unclean one (kill, power cut) is closed by the next start at the run's last seed or alarm."""

from __future__ import annotations

import sqlite3
from datetime import UTC, datetime, timedelta
from pathlib import Path

from gateway.core.records import AlarmEvent, SeedDrop, utc_to_us
from gateway.recording.runs import stored_setting
from gateway.recording.store import RecordStore

T0 = datetime(2026, 5, 2, 6, 0, tzinfo=UTC)
SETTINGS = {"target_spacing_m": 0.2, "rows": 6, "working_width_m": 2.0, "crop": "maize",
            "machine_id": "seeder-01", "not kept": 1}


def seed(t: datetime) -> SeedDrop:
    return SeedDrop(row=1, utc=t, lat=52.0, lon=13.0, fix="rtk_fixed", speed_kmh=8.0,
                    spacing_m=0.2)


def alarm(t: datetime, code: str = "pwm.unavailable", active: bool = True) -> AlarmEvent:
    return AlarmEvent(machine_id="seeder-01", code=code, active=active, severity="critical",
                      message="PWM module not answering", utc=t)


def test_a_clean_run_keeps_its_start_stop_and_settings(tmp_path: Path) -> None:
    with RecordStore(tmp_path / "r.sqlite3", "seeder-01") as store:
        store.start_run(SETTINGS, T0)
        store.add_seeds([seed(T0 + timedelta(seconds=1))])
        store.flush()
        store.stop_run(T0 + timedelta(seconds=10))
    with RecordStore.open_readonly(tmp_path / "r.sqlite3", "seeder-01") as ro:
        (run,) = ro.runs()
    assert (run.start_us, run.stop_us, run.clean) == (
        utc_to_us(T0), utc_to_us(T0 + timedelta(seconds=10)), True)
    assert dict(run.settings) == {k: v for k, v in SETTINGS.items() if k != "not kept"}
    assert stored_setting([run], "target_spacing_m") == 0.2


def test_an_unclean_stop_ends_at_its_last_record_when_the_next_run_starts(
    tmp_path: Path,
) -> None:
    path = tmp_path / "r.sqlite3"
    store = RecordStore(path, "seeder-01")
    store.start_run(SETTINGS, T0)
    store.add_seeds([seed(T0 + timedelta(seconds=s)) for s in (1, 2, 3)])
    store.add_alarm(alarm(T0 + timedelta(seconds=5)))
    store.flush()
    store.close()  # killed: no stop_run
    with RecordStore.open_readonly(path, "seeder-01") as ro:
        (running,) = ro.runs()
    assert running.stop_us is None  # the newest run without a stop may still be running
    with RecordStore(path, "seeder-01") as store:
        store.start_run({**SETTINGS, "target_spacing_m": 0.25}, T0 + timedelta(minutes=5))
        first, second = store.runs()
        store.stop_run(T0 + timedelta(minutes=6))
    assert first.stop_us == utc_to_us(T0 + timedelta(seconds=5))  # its last alarm
    assert not first.clean
    assert second.stop_us is None and second.start_us == utc_to_us(T0 + timedelta(minutes=5))
    with RecordStore.open_readonly(path, "seeder-01") as ro:
        runs = ro.runs()
    assert [r.clean for r in runs] == [False, True]
    # the newest run overlapping a window gives the setting
    assert stored_setting(runs, "target_spacing_m") == 0.25
    assert stored_setting(runs, "target_spacing_m",
                          until_us=utc_to_us(T0 + timedelta(minutes=1))) == 0.2


def test_an_older_store_has_no_runs_and_reads_as_before(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite3"
    RecordStore(path, "seeder-01").close()
    db = sqlite3.connect(path)
    db.execute("DROP TABLE runs")  # as a store written before the runs were marked
    db.commit()
    db.close()
    with RecordStore.open_readonly(path, "seeder-01") as ro:
        assert ro.runs() == []
