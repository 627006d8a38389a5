"""The rotation test started from the touchscreen (F=09): the daemon runs the motor at each
duty for the run time with the fan on, then off; the operator types the shaft speed and the
catch; "save" fits, saves and applies it at once. Stop ends a run at once."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.calibration import fits as cal
from simulator.machine import SimulatedMachine
from tests.integration.conftest import Rig, running, steady_drive

DUTIES = [50.0, 65.0, 80.0, 95.0]
SECONDS = 1.0


def shaft_rpm(duty: float) -> float:
    """This drill's motor, as the operator's tachometer reads it (not the config's line)."""
    return round(0.70 * duty - 20.0, 1)


def catch_g(rpm: float) -> float:
    """The catch of all outlets over one run (paper A eq. 6 for wheat)."""
    return round((-0.644 * rpm * rpm + 132.212 * rpm - 398.316) * SECONDS / 60.0, 1)


def overrides() -> dict[str, object]:
    return {"control": {"crop": "wheat", "rotation_test_s": SECONDS}}


async def one_run(rig: Rig, duty: float) -> None:
    hmi, sim = rig.machine.hmi, rig.machine.rs485
    assert hmi is not None and sim is not None
    hmi.rotation_test("run", duty)
    await rig.until(lambda: sim.duty_pct == {"motor": duty, "fan": 85.0},
                    what=f"the motor at {duty} % with the fan on")
    hmi.rotation_test("rpm", 10.0)  # too early: the run is still on
    await hmi.wait_text("t_msg", lambda s: "wait until the run has ended" in s)
    await rig.until(lambda: sim.duty_pct == {"motor": 0.0, "fan": 0.0}, what="motor off")
    await hmi.wait_text("t_msg", lambda s: "done: enter its shaft r/min" in s)
    rpm = shaft_rpm(duty)
    hmi.rotation_test("rpm", rpm)
    await hmi.wait_text("t_msg", lambda s: f"shaft {rpm:g} r/min" in s)
    hmi.rotation_test("mass", catch_g(rpm))
    await hmi.wait_text("t_msg", lambda s: "g from all" in s)


async def test_a_rotation_test_from_the_touchscreen_is_run_fitted_and_applied(
    tmp_path: Path,
) -> None:
    machine = SimulatedMachine(drive=steady_drive(), crop="wheat")
    async with running(tmp_path, machine, **overrides()) as rig:
        hmi = machine.hmi
        assert hmi is not None
        await hmi.wait_text("t_state", lambda s: s == "STOPPED")  # the screen is connected
        hmi.rotation_test("save")
        await hmi.wait_text("t_msg", lambda s: "need 3 runs" in s)
        for duty in DUTIES:
            await one_run(rig, duty)
        hmi.rotation_test("save")
        saved = await hmi.wait_text("t_msg", lambda s: s.startswith("saved rotation.wheat"))
        # 1 s runs catch 30-60 g: too short on paper A's ±2 g scale; the screen (ASCII) says so
        assert "runs too short for a +-2 g scale: rotation_test_s 30" in saved
        wheat = rig.daemon.controller.crop_model
        assert wheat.motor_slope == pytest.approx(0.70, rel=0.01)
        assert wheat.meter_b == pytest.approx(132.212, rel=0.02)
        entry = cal.CalibrationStore(tmp_path / "state").get("rotation.wheat")
        assert entry is not None and entry["source"] == "hmi"
        assert (entry["crop"], entry["seed_lot"]) == ("wheat", "default")
        assert entry["outlets_weighed"] == rig.daemon.settings.machine.rows
        assert entry["weighing"]["advised_seconds"] > SECONDS


async def test_stop_ends_a_run_at_once_and_work_cannot_start_one(tmp_path: Path) -> None:
    machine = SimulatedMachine(drive=steady_drive(), crop="wheat")
    over = {"control": {"crop": "wheat", "rotation_test_s": 30.0}}
    async with running(tmp_path, machine, **over) as rig:
        hmi, sim = machine.hmi, machine.rs485
        assert hmi is not None and sim is not None
        await hmi.wait_text("t_state", lambda s: s == "STOPPED")  # the screen is connected
        hmi.rotation_test("run", 60.0)
        await rig.until(lambda: sim.duty_pct["motor"] == 60.0, what="the run going")
        hmi.press_stop()
        await rig.until(lambda: sim.duty_pct == {"motor": 0.0, "fan": 0.0}, timeout=3.0,
                        what="motor and fan off at the stop")
        hmi.press_start()
        await rig.until(lambda: rig.daemon.controller.mode.value != "stopped", what="working")
        hmi.rotation_test("run", 60.0)
        await hmi.wait_text("t_msg", lambda s: "stop work first" in s)
