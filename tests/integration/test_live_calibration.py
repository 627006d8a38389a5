"""A calibration saved while the daemon seeds takes effect without a restart, and the CLI says
so; a broken calibration file changes nothing, raises an alarm, and a good one clears it."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

import pytest

from gateway.calibration import fits as cal
from gateway.control.rate_model import plan_duty
from simulator.machine import SimulatedMachine
from tests.helpers import calibration_cli
from tests.integration.conftest import metering

W = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0]
SLOPE, INTERCEPT = 0.6671 * 1.10, -19.8309  # this drill's motor: 10 % steeper than paper A's


def rotation_argv(state: Path, config: Path) -> list[str]:
    duties = [(w - INTERCEPT) / SLOPE for w in W]
    masses = [-0.644 * w * w + 132.212 * w - 398.316 for w in W]  # 60 s runs: g == g/min
    return ["calibrate", "--config", str(config), "--state-dir", str(state), "rotation",
            "--channel", "wheat", "--model", "paper_a", "--no-wait",
            "--duties", ",".join(map(str, duties)), "--rpm", ",".join(map(str, W)),
            "--mass", ",".join(map(str, masses))]


async def test_a_rotation_test_saved_while_seeding_changes_the_duty_at_once(
    tmp_path: Path, make_machine: Callable[..., SimulatedMachine],
) -> None:
    machine = make_machine(crop="wheat")
    async with metering(tmp_path, machine) as (rig, sim):
        daemon = rig.daemon
        state = tmp_path / "state"
        config = machine.write_config(tmp_path / "sowgate.toml", control={"crop": "wheat"})
        assert daemon.controller.crop_model.motor_slope == pytest.approx(0.6671)
        code, out = await asyncio.to_thread(calibration_cli, rotation_argv(state, config))
        assert code == 0, out
        # the CLI waited for the daemon: applied already when it returns
        assert "The running daemon" in out and "applied" in out, out
        assert "wheat metering model refitted" in out
        assert daemon.controller.crop_model.motor_slope == pytest.approx(SLOPE, rel=1e-3)

        def duty_follows_the_new_line() -> bool:
            out_ = daemon.outputs
            if out_ is None or out_.speed_kmh is None or out_.motor_pct == 0:
                return False
            expected = plan_duty(daemon.controller.rate_kg_ha,
                                 daemon.settings.machine.working_width_m, out_.speed_kmh,
                                 daemon.controller.crop_model).duty_pct
            return abs(sim.duty_pct["motor"] - expected) < 1.0

        await rig.until(duty_follows_the_new_line, what="the PWM module at the refitted duty")
        assert not daemon.alarms.is_active("calibration.file_invalid")
        # undo: the config's line again, live
        code, out = await asyncio.to_thread(
            calibration_cli,
            ["calibrate", "--state-dir", str(state), "undo", "--key", "rotation.wheat"],
        )
        assert code == 0 and "applied" in out, out
        assert daemon.controller.crop_model.motor_slope == pytest.approx(0.6671)


async def test_a_broken_calibration_file_keeps_the_values_and_raises_an_alarm(
    tmp_path: Path, make_machine: Callable[..., SimulatedMachine],
) -> None:
    machine = make_machine(crop="wheat")
    state = tmp_path / "state"
    store = cal.CalibrationStore(state)
    store.save("speed.radar", cal.to_entry(cal.speed_correction("radar", 50.0, 48.0)))
    async with metering(tmp_path, machine) as (rig, _sim):
        radar = rig.daemon.controller.sources["radar"]
        assert radar.correction == pytest.approx(50 / 48)
        (state / "calibration.json").write_text('{"current": {"speed.radar": ')  # half a copy
        await rig.until(lambda: rig.daemon.alarms.is_active("calibration.file_invalid"),
                        what="calibration.file_invalid")
        assert radar.correction == pytest.approx(50 / 48)  # kept
        cal.atomic_write_json(state / "calibration.json",
                              {"version": 1, "current": {}, "history": []})
        await rig.until(lambda: not rig.daemon.alarms.is_active("calibration.file_invalid"),
                        what="the alarm cleared by a good file")
        assert radar.correction == 1.0  # the good file has no speed calibration: the config's


async def test_with_no_daemon_running_the_cli_says_it_applies_at_next_start(
    tmp_path: Path,
) -> None:
    config = tmp_path / "sowgate.toml"
    config.write_text("[machine]\nrows = 6\n")
    code, out = calibration_cli(rotation_argv(tmp_path, config))
    assert code == 0, out
    assert "No daemon is running" in out and "next start" in out
