"""The rotation test started from the touchscreen (F=09): the daemon runs the motor at each
duty for the run time with the fan on, then off; the operator types the shaft speed and the
catch; "save" fits, saves and applies it at once. Stop ends a run at once."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from gateway.app.daemon import Daemon
from gateway.calibration import fits as cal
from simulator.machine import SimulatedMachine
from tests.integration.conftest import Rig, daemon_task, running, steady_drive

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


# ---- run lengths per set point from the scale (issue 25 §3) ----------------------------------

SCALE_G = 2.0  # [calibration] scale_g
RAPE_DUTIES = [20.0, 40.0, 67.0]


def rape_rpm(duty: float) -> float:
    """This rapeseed drill's motor (its own line, not the config's eq. 5)."""
    return round(0.55 * duty - 6.0, 1)


def rape_catch_g(rpm: float, seconds: float) -> float:
    """Its catch: g/min proportional to the shaft (not eq. 6's quadratic), 11–17 % under
    what the config's model predicts at these duties, so the model's run lengths fall short."""
    return round(4.2 * rpm * seconds / 60.0, 1)


async def timed_run(rig: Rig, skip: list[float], duty: float) -> float:
    """One run at ``duty`` on the daemon's clock, fast-forwarded to just before the end it
    announced: the motor must still turn there and stop after; returns the run's length."""
    hmi, sim = rig.machine.hmi, rig.machine.rs485
    assert hmi is not None and sim is not None
    hmi.rotation_test("run", duty)
    msg = await hmi.wait_text("t_msg", lambda s: f"duty {duty:g} % for" in s)
    seconds = float(msg.split(" for ")[1].split(" s")[0])
    await rig.until(lambda: sim.duty_pct == {"motor": duty, "fan": 70.0},
                    what=f"the motor at {duty} % with the fan on")
    until = rig.daemon.rotation_test.running_until
    assert until is not None
    skip[0] = until - 0.5 - time.monotonic()  # the daemon's clock half a second before
    await asyncio.sleep(0.3)  # a few control ticks
    assert sim.duty_pct["motor"] == duty, f"the {seconds:g} s run ended early"
    await rig.until(lambda: sim.duty_pct == {"motor": 0.0, "fan": 0.0}, what="motor off")
    await hmi.wait_text("t_msg", lambda s: "done: enter its shaft r/min" in s)
    rpm = rape_rpm(duty)
    hmi.rotation_test("rpm", rpm)
    await hmi.wait_text("t_msg", lambda s: f"shaft {rpm:g} r/min" in s)
    hmi.rotation_test("mass", rape_catch_g(rpm, seconds))
    await hmi.wait_text("t_msg", lambda s: "g from all" in s)
    return seconds


async def test_with_the_scale_known_each_set_point_runs_as_long_as_it_needs(
    tmp_path: Path,
) -> None:
    """[calibration] scale_g: the screen's test runs the small catches long and the large
    ones short, makes up a first run the model misjudged, and ends within the CLI's target
    at every set point in one test (the CLI needs a 60 s pass first to know)."""
    skip = [0.0]
    machine = SimulatedMachine(drive=steady_drive(), crop="rapeseed")
    async with machine:
        settings = machine.settings(control={"crop": "rapeseed", "rotation_test_s": 30.0},
                                    calibration={"scale_g": SCALE_G})
        daemon = Daemon(settings, tmp_path / "state", clock=lambda: time.monotonic() + skip[0])
        async with daemon_task(daemon) as task:
            rig = Rig(machine, daemon, task)
            hmi = machine.hmi
            assert hmi is not None
            await hmi.wait_text("t_state", lambda s: s == "STOPPED")
            lengths: dict[float, list[float]] = {}
            for duty in RAPE_DUTIES:
                for _ in range(3):  # paper A's 3 runs per set point
                    lengths.setdefault(duty, []).append(await timed_run(rig, skip, duty))
            hmi.rotation_test("save")
            saved = await hmi.wait_text("t_msg", lambda s: s.startswith("saved rotation."))
    low, mid, high = (lengths[d] for d in RAPE_DUTIES)
    assert low[0] > mid[0] > high[0] >= 30.0  # each set point its own length
    assert low[1] > low[0]  # the catch came in under the model: the later runs make it up
    assert "too short" not in saved
    # judged here from the catches typed, not from the daemon's advice: each set point's mean
    # over its 3 runs within 1 % at p90 on a ±2 g scale
    for duty, ts in lengths.items():
        mean_catch = sum(rape_catch_g(rape_rpm(duty), t) for t in ts) / len(ts)
        assert SCALE_G / mean_catch / 3**0.5 * 100 <= 1.0 / 1.645, (duty, ts)
    # shorter than one length for all: the longest run at every set point
    total = sum(sum(ts) for ts in lengths.values())
    assert total < 0.75 * 9 * max(max(ts) for ts in lengths.values())
    entry = cal.CalibrationStore(tmp_path / "state").get("rotation.rapeseed")
    assert entry is not None and entry["weighing"]["short_set_points"] == []
    assert entry["weighing"]["scale_g"] == SCALE_G


async def test_a_coarse_scale_is_named_on_the_screen(tmp_path: Path) -> None:
    """A ±10 g kitchen scale on rapeseed: the run says how long the set point takes and which
    scale would do it in the configured run length."""
    machine = SimulatedMachine(drive=steady_drive(), crop="rapeseed")
    over = {"control": {"crop": "rapeseed", "rotation_test_s": 60.0},
            "calibration": {"scale_g": 10.0}}
    async with running(tmp_path, machine, **over):
        hmi = machine.hmi
        assert hmi is not None
        await hmi.wait_text("t_state", lambda s: s == "STOPPED")
        hmi.rotation_test("run", 20.0)
        msg = await hmi.wait_text("t_msg", lambda s: "duty 20 % for" in s)
        seconds = float(msg.split(" for ")[1].split(" s")[0])
        assert seconds > 1200  # 25 g a minute on a ±10 g scale
        assert "+-10 g scale, 3 runs here" in msg and "g scale does it in 60 s" in msg
        hmi.rotation_test("cancel")
        await hmi.wait_text("t_msg", lambda s: "cancelled" in s)
