"""The real daemon stores its alarms without MQTT, marks its starts and stops in the store,
and the field report ends an alarm still active at a stop there: a faulty start (the PWM
module not answering) followed by a clean run does not draw the fault across the clean run."""

from __future__ import annotations

import asyncio
import csv
import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from gateway.app.cli import main as sowgate
from gateway.core.records import us_to_utc, utc_to_us
from gateway.recording.store import RecordStore
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from tests.helpers import eventually
from tests.integration.conftest import running

MACHINE_ID = "seeder-01"
SEEDS = 300


@dataclass(frozen=True)
class TwoRuns:
    state: Path
    config: Path


def machine() -> SimulatedMachine:
    drive = Drive(legs=[Leg(3.0, 0.0), Leg(40.0, 8.0), Leg(600.0, 0.0)], dt=0.02)
    return SimulatedMachine(drive=drive, with_gnss=True, with_seed_tubes=True)


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TwoRuns]:
    """A faulty run (MQTT off: the default), stopped with ``pwm.unavailable`` still active;
    then a clean run on the same state directory that sows."""
    tmp = tmp_path_factory.mktemp("runs")

    async def faulty() -> None:
        m = machine()
        async with running(tmp, m) as rig:
            assert not rig.daemon.settings.mqtt.enabled
            sim = rig.machine.rs485
            assert sim is not None
            sim.set_silent(sim.device_ids["pwm"], True)
            await rig.until(lambda: rig.daemon.alarms.is_active("pwm.unavailable"), 20.0,
                            "pwm.unavailable raised")
            await rig.stop()

    async def clean() -> None:
        m = machine()
        async with running(tmp, m, control={"start_working": True}) as rig:
            tubes = rig.machine.seed_tubes
            assert tubes is not None
            await eventually(lambda: len(tubes.truth) >= SEEDS, 40.0, f"{SEEDS} seeds dropped")
            assert not rig.daemon.alarms.is_active("pwm.unavailable")
            await rig.stop()
            m.write_config(tmp / "sowgate.toml", control={"start_working": True})

    asyncio.run(faulty())
    asyncio.run(clean())
    yield TwoRuns(tmp / "state", tmp / "sowgate.toml")


def test_alarms_are_stored_without_mqtt_and_both_runs_are_marked(two_runs: TwoRuns) -> None:
    with RecordStore.open_readonly(two_runs.state / "records.sqlite3", MACHINE_ID) as store:
        alarms = list(store.query_alarms())
        runs = store.runs()
    pwm = [a for a in alarms if a.code == "pwm.unavailable"]
    assert [a.active for a in pwm] == [True]  # raised, never cleared: the stop came first
    assert len(runs) == 2 and all(r.clean for r in runs)
    first, second = runs
    assert first.start_us <= utc_to_us(pwm[0].utc) <= first.stop_us  # type: ignore[operator]
    assert first.stop_us is not None and first.stop_us <= second.start_us
    assert second.settings["target_spacing_m"] is not None


def test_the_report_ends_the_alarm_at_the_faulty_runs_stop(
    two_runs: TwoRuns, tmp_path: Path
) -> None:
    out = tmp_path / "report.html"
    assert sowgate(["report", "--config", str(two_runs.config), "--state-dir",
                    str(two_runs.state), "--output", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    m = re.search(r'id="report-data">(.*?)</script>', text, re.S)
    assert m is not None
    data = json.loads(m.group(1).replace("<\\/", "</"))
    (period,) = [p for p in data["alarm_periods"] if p["code"] == "pwm.unavailable"]
    first, second = data["daemon_runs"]
    assert period["end"] == "stop"
    assert period["to_utc"] == first["stop_utc"]
    # not drawn across the clean run (alarms and runs are on the box's clock; seeds carry
    # the receiver's, so they are not compared here)
    assert period["to_utc"] <= second["start_utc"] < second["stop_utc"]
    # the alarm table lists it, and the stop that ended it
    assert "<td>pwm.unavailable</td>" in text
    assert "alarms still active end here: pwm.unavailable" in text
    assert "No alarm was raised" not in text


def test_the_alarm_export_ends_it_at_the_stop_too(two_runs: TwoRuns, tmp_path: Path) -> None:
    out = tmp_path / "alarms.csv"
    assert sowgate(["export", "--what", "alarms", "--state-dir", str(two_runs.state),
                    "--output", str(out)]) == 0
    with out.open(encoding="utf-8") as f:
        periods = [r for r in csv.DictReader(f) if r["code"] == "pwm.unavailable"]
    with RecordStore.open_readonly(two_runs.state / "records.sqlite3", MACHINE_ID) as store:
        first, _second = store.runs()
    (period,) = periods
    assert period["ended"] == "stop" and period["severity"] == "critical"
    assert period["ended_utc"] == _iso(first.stop_us)
    assert "not answering" in period["message"]
    assert sowgate(["export", "--what", "alarms", "--state-dir", str(two_runs.state),
                    "--output", str(tmp_path / "alarms.geojson")]) == 2  # CSV only


def _iso(us: int | None) -> str:
    assert us is not None
    return us_to_utc(us).isoformat().replace("+00:00", "Z")
