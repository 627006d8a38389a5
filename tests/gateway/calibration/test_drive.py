"""`sowgate calibrate rotation --drive modbus|can` runs the meter itself, set point after set
point, and leaves it off: between runs, after any error, on Ctrl-C (SIGINT) and SIGTERM.

Paper A's motor is driven over a real pty against the simulated PWM module (the duties it was
told, in order, are the evidence); paper B's channel over python-can's virtual bus against
the simulated metering controller.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import itertools
import signal
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest
from rich.console import Console

from drivers.can_bus import CanBus
from gateway.calibration import drive as drive_mod
from gateway.calibration import fits as cal
from gateway.calibration.cli import add_calibration_commands, run_calibration
from gateway.config import parse_config
from protocol.can_metering import FaultCode
from simulator.can_pid import MeteringControllerSim, MeterPlant
from simulator.modbus_devices import Rs485Simulator
from tests.helpers import Plant, eventually, sowgate_env, spawn_sowgate

SPAWN_TIMEOUT_S = 60.0  # a `sowgate` child process up and driving (imports on a loaded host)
WHEAT_W = [22.0, 30.0, 38.0, 44.0]  # shaft r/min the operator reads at each duty
WHEAT_DUTIES = [(w + 19.8309) / 0.6671 for w in WHEAT_W]  # paper A eq. 5 for wheat


def wheat_catch_g(w: float, seconds: float) -> float:
    """What the scale shows after a run of the whole machine at ``w`` r/min (paper A eq. 6)."""
    return (-0.644 * w * w + 132.212 * w - 398.316) * seconds / 60.0


def parse(argv: list[str]) -> argparse.Namespace:
    root = argparse.ArgumentParser(prog="sowgate")
    add_calibration_commands(root.add_subparsers(dest="command"))
    return root.parse_args(argv)


def run(argv: list[str], ask: Callable[[str], float]) -> tuple[int, str]:
    out = io.StringIO()
    code = run_calibration(parse(argv), console=Console(file=out, width=160), ask=ask)
    return code, out.getvalue()


def motor_steps(plant: Plant) -> list[float]:
    """The motor duties written, repeats (keep-alive) folded."""
    return [k for k, _ in itertools.groupby(p for ch, p in plant.duties if ch == "motor")]


def paper_a_config(tmp_path: Path, sim: Rs485Simulator) -> Path:
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(f'[machine]\nrows = 6\n[rs485]\nport = "{sim.device_path}"\n'
                   "[actuators]\ncomm_timeout_s = 2.0\n")
    return cfg


def paper_a_argv(tmp_path: Path, cfg: Path, seconds: float, *extra: str) -> list[str]:
    return ["calibrate", "--config", str(cfg), "--state-dir", str(tmp_path), "rotation",
            "--channel", "wheat", "--model", "paper_a", "--drive", "modbus",
            "--duties", ",".join(f"{d:.1f}" for d in WHEAT_DUTIES),
            "--rpm", ",".join(map(str, WHEAT_W)), "--seconds", str(seconds),
            "--fan-settle", "0.2", *extra]


# ---- paper A: the PWM module on RS485 ---------------------------------------------------------


async def test_modbus_drive_runs_each_duty_in_order_with_the_motor_off_between(
    tmp_path: Path, sim: Rs485Simulator, plant: Plant,
) -> None:
    cfg = paper_a_config(tmp_path, sim)
    questions: list[str] = []
    at_prompt: list[tuple[float, float]] = []  # (motor, fan) while the operator weighs

    def ask(question: str) -> float:
        questions.append(question)
        at_prompt.append((sim.duty_pct["motor"], sim.duty_pct["fan"]))
        return wheat_catch_g(WHEAT_W[len(questions) - 1], 0.6)

    code, out = await asyncio.to_thread(run, paper_a_argv(tmp_path, cfg, 0.6), ask)
    assert code == 0, out
    assert motor_steps(plant) == [0.0, *(x for d in WHEAT_DUTIES for x in (round(d, 1), 0.0))]
    # the fan at wheat's seeding duty before the first run, off at the end
    first_motor = next(i for i, (ch, p) in enumerate(plant.duties) if ch == "motor" and p > 0)
    assert ("fan", 85.0) in plant.duties[:first_motor]
    assert sim.duty_pct == {"motor": 0.0, "fan": 0.0}
    assert at_prompt == [(0.0, 85.0)] * 4  # weighed with the motor stopped, the fan still on
    assert sim.comm_timeout_writes >= 1 and sim.comm_timeout_s == 2.0  # the watchdog is armed
    # each prompt says the unit and which outlets the catch is from
    assert all(" in g" in q and "6 outlet(s) of 6" in q for q in questions), questions
    entry = cal.CalibrationStore(tmp_path).get("rotation.wheat")
    assert entry is not None
    assert entry["result"]["motor"]["slope"] == pytest.approx(0.6671, rel=0.01)


async def test_modbus_drive_stops_the_motor_after_a_bus_error_mid_run(
    tmp_path: Path, sim: Rs485Simulator, plant: Plant,
) -> None:
    """A garbled reply to a keep-alive write during run 2: the test ends, motor and fan 0."""
    cfg = paper_a_config(tmp_path, sim)

    def ask(_question: str) -> float:
        return 100.0

    task = asyncio.create_task(asyncio.to_thread(run, paper_a_argv(tmp_path, cfg, 3.0), ask))
    await eventually(lambda: round(WHEAT_DUTIES[1], 1) in motor_steps(plant), what="run 2")
    sim.corrupt_next_crc(1)
    code, out = await task
    assert code == 1, out
    assert "stopped answering" in " ".join(out.split())
    steps = motor_steps(plant)
    assert steps[-1] == 0.0 and round(WHEAT_DUTIES[2], 1) not in steps  # run 3 never started
    assert sim.duty_pct == {"motor": 0.0, "fan": 0.0}
    assert cal.CalibrationStore(tmp_path).get("rotation.wheat") is None  # nothing saved


async def test_a_module_without_a_watchdog_is_not_driven(tmp_path: Path) -> None:
    plant = Plant()
    async with Rs485Simulator(radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0,
                              on_duty=plant.on_duty, pwm_watchdog=False) as sim:
        cfg = paper_a_config(tmp_path, sim)
        code, out = await asyncio.to_thread(
            run, paper_a_argv(tmp_path, cfg, 0.5), lambda _q: pytest.fail("asked"))
    assert code == 1 and "no communication-loss watchdog" in " ".join(out.split()), out
    assert not any(p > 0 for ch, p in plant.duties if ch == "motor")


@pytest.mark.parametrize(("sig", "exit_code", "said", "ignored_at_exec"), [
    (signal.SIGINT, 130, "interrupted (Ctrl-C)", False),
    # started as a background job (`make test &`): the shell ignores SIGINT for it and the
    # ignore is inherited through exec; sowgate takes Ctrl-C back all the same
    (signal.SIGINT, 130, "interrupted (Ctrl-C)", True),
    (signal.SIGTERM, 143, "terminated (SIGTERM)", False),
], ids=["sigint", "sigint-ignored-at-exec", "sigterm"])
async def test_a_signal_mid_run_leaves_motor_and_fan_off(
    tmp_path: Path, sim: Rs485Simulator, plant: Plant, sig: signal.Signals, exit_code: int,
    said: str, ignored_at_exec: bool,
) -> None:
    """The real `sowgate` process: Ctrl-C (or systemd's SIGTERM) while the motor runs."""
    from tests.helpers import sowgate_argv

    cfg = paper_a_config(tmp_path, sim)
    masses = ",".join(f"{wheat_catch_g(w, 30):.1f}" for w in WHEAT_W)
    argv = paper_a_argv(tmp_path, cfg, 30.0, "--mass", masses)
    if ignored_at_exec:
        proc = await asyncio.create_subprocess_exec(
            "bash", "-c", 'trap "" INT; exec "$@"', "sowgate", *sowgate_argv(*argv),
            env=sowgate_env(tmp_path), stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    else:
        proc = await spawn_sowgate(*argv, env=sowgate_env(tmp_path))
    try:
        # a child `sowgate` starts (imports) in seconds on a loaded host: waited for, not timed
        await eventually(lambda: sim.duty_pct["motor"] > 0, SPAWN_TIMEOUT_S, "the motor running")
        proc.send_signal(sig)
        stdout, stderr = await asyncio.wait_for(proc.communicate(), 30)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    text = " ".join(stdout.decode().split())
    assert proc.returncode == exit_code, (text, stderr.decode())
    assert said in text and "the meter is off" in text
    assert sim.duty_pct == {"motor": 0.0, "fan": 0.0}
    assert motor_steps(plant)[-2:] == [round(WHEAT_DUTIES[0], 1), 0.0]
    assert cal.CalibrationStore(tmp_path).get("rotation.wheat") is None


def test_paper_a_default_duties_span_the_crops_fitted_range() -> None:
    from gateway.calibration.cli import _default_duties

    wheat = parse_config({}).control.crops["wheat"]
    duties = _default_duties(wheat)
    rpm = [wheat.motor_slope * d + wheat.motor_intercept for d in duties]
    assert len(duties) == 6 and duties == sorted(duties)
    assert rpm[0] == pytest.approx(wheat.omega_min_rpm, abs=0.5)
    assert rpm[-1] == pytest.approx(wheat.omega_max_rpm, abs=0.5)


# ---- paper B: a can_pid controller on CAN -----------------------------------------------------


class RecordingPlant(MeterPlant):
    """A meter plant that remembers every target it was commanded (folded repeats)."""

    targets: list[float]

    def command(self, target_rpm: float, enable: bool, sequence: int) -> None:
        if not hasattr(self, "targets"):
            self.targets = []
        if not self.targets or self.targets[-1] != target_rpm:
            self.targets.append(target_rpm)
        super().command(target_rpm, enable, sequence)


def can_config(tmp_path: Path, can_channel: str) -> Path:
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(
        f'[can]\ninterface = "virtual"\nchannel = "{can_channel}"\n'
        '[[channel]]\nname = "seed"\ntarget_rate_kg_ha = 225\nnode_id = 3\noutlets = 4\n'
        "grams_per_rev = 11.0\n"
    )
    return cfg


async def test_can_drive_runs_each_speed_and_measures_the_shaft(tmp_path: Path) -> None:
    """The controller is commanded 20, 0, 40, 0 r/min; each catch is asked for with the shaft
    stopped; g/rev is the catch over the turns the encoder reported (run-down included)."""
    can_channel = f"cal-{uuid.uuid4().hex[:8]}"
    cfg = can_config(tmp_path, can_channel)
    plant = RecordingPlant(grams_per_rev=11.2, outlets=4)
    at_prompt: list[tuple[float, float]] = []  # (target, shaft r/min) while weighing
    weighed_so_far = 0.0
    revs_at_prompt: list[float] = []

    def ask(question: str) -> float:
        nonlocal weighed_so_far
        assert " in g" in question and "4 outlet(s) of 4" in question, question
        at_prompt.append((plant.target_rpm, plant.rpm))
        revs_at_prompt.append(plant.revs)
        catch = plant.mass_g - weighed_so_far
        weighed_so_far = plant.mass_g
        return catch

    async with CanBus("virtual", can_channel) as bus:
        sim = asyncio.create_task(MeteringControllerSim(bus, {3: plant}).run())
        try:
            argv = ["calibrate", "--config", str(cfg), "--state-dir", str(tmp_path),
                    "rotation", "--channel", "seed", "--drive", "can", "--speeds", "20,40",
                    "--seconds", "1.5"]
            code, out = await asyncio.to_thread(run, argv, ask)
        finally:
            sim.cancel()
            await asyncio.gather(sim, return_exceptions=True)
    assert code == 0, out
    assert plant.targets == [0.0, 20.0, 0.0, 40.0, 0.0]
    assert all(target == 0.0 and rpm < 1.0 for target, rpm in at_prompt), at_prompt
    saved = cal.CalibrationStore(tmp_path).get("rotation.seed")
    assert saved is not None
    true_rpm = [revs / (1.5 / 60) for revs in (revs_at_prompt[0],
                                               revs_at_prompt[1] - revs_at_prompt[0])]
    used = [r["rpm"] for r in saved["result"]["used"]]
    assert used == pytest.approx(true_rpm, rel=0.03)  # the encoder's turns, not 20 / 40
    assert saved["result"]["grams_per_rev"] == pytest.approx(11.2, rel=0.03)  # per outlet


async def test_can_drive_stops_on_a_controller_fault(tmp_path: Path) -> None:
    can_channel = f"cal-{uuid.uuid4().hex[:8]}"
    cfg = can_config(tmp_path, can_channel)
    plant = RecordingPlant(grams_per_rev=11.2, outlets=4)
    async with CanBus("virtual", can_channel) as bus:
        sim = asyncio.create_task(MeteringControllerSim(bus, {3: plant}).run())
        try:
            argv = ["calibrate", "--config", str(cfg), "--state-dir", str(tmp_path),
                    "rotation", "--channel", "seed", "--drive", "can", "--speeds", "20,40",
                    "--seconds", "3"]
            task = asyncio.create_task(asyncio.to_thread(run, argv, lambda _q: 100.0))
            await eventually(lambda: plant.rpm > 10, what="run 1 turning")
            plant.fault_code = FaultCode.VALVE
            code, out = await task
            await eventually(lambda: plant.target_rpm == 0.0, what="target 0")
        finally:
            sim.cancel()
            await asyncio.gather(sim, return_exceptions=True)
    assert code == 1 and "controller reports fault valve" in out, out
    assert plant.targets[-1] == 0.0 and 40.0 not in plant.targets
    assert cal.CalibrationStore(tmp_path).get("rotation.seed") is None


async def test_cancelling_a_can_driven_test_commands_the_shaft_off(tmp_path: Path) -> None:
    """Ctrl-C reaches drive_runs as a cancellation (asyncio.run): the finally stops the shaft."""
    can_channel = f"cal-{uuid.uuid4().hex[:8]}"
    settings = parse_config({"can": {"interface": "virtual", "channel": can_channel},
                             "channel": [{"name": "seed", "target_rate_kg_ha": 225,
                                          "node_id": 3}]})
    plant = RecordingPlant(grams_per_rev=11.2)
    drive = drive_mod.CanMeterDrive(settings, "seed")

    async def after_run(_i: int, _turns: float | None) -> None:
        return None

    async with CanBus("virtual", can_channel) as bus:
        sim = asyncio.create_task(MeteringControllerSim(bus, {3: plant}).run())
        try:
            runs = asyncio.create_task(drive_mod.drive_runs(
                drive, [30.0, 40.0], 20.0, lambda _r: None, after_run))
            await eventually(lambda: plant.rpm > 10, what="the shaft turning")
            runs.cancel()
            with pytest.raises(asyncio.CancelledError):
                await runs
            await eventually(lambda: plant.rpm < 1.0, what="the shaft stopped", timeout=5)
        finally:
            sim.cancel()
            await asyncio.gather(sim, return_exceptions=True)
    assert plant.targets == [0.0, 30.0, 0.0]
    assert not drive.bus.connected


async def test_no_answer_at_the_prompt_ends_the_test_with_the_meter_off(
    tmp_path: Path, sim: Rs485Simulator, plant: Plant,
) -> None:
    """Standard input closed (a script without --mass): EOF at the first prompt, fan on."""
    cfg = paper_a_config(tmp_path, sim)

    def ask(_question: str) -> float:
        raise EOFError

    code, out = await asyncio.to_thread(run, paper_a_argv(tmp_path, cfg, 0.5), ask)
    assert code == 1 and "no answer at the prompt" in " ".join(out.split()), out
    assert motor_steps(plant) == [0.0, round(WHEAT_DUTIES[0], 1), 0.0]
    assert sim.duty_pct == {"motor": 0.0, "fan": 0.0}


def test_the_meter_is_not_driven_while_a_daemon_owns_the_bus(tmp_path: Path) -> None:
    from gateway.calibration.presence import remove_presence, write_presence

    write_presence(tmp_path, {"calibration": {}})  # a daemon running (this process)
    try:
        cfg = tmp_path / "sowgate.toml"
        cfg.write_text('[rs485]\nport = "/dev/null-no-such-port"\n')
        code, out = run(paper_a_argv(tmp_path, cfg, 0.5), lambda _q: pytest.fail("asked"))
    finally:
        remove_presence(tmp_path)
    assert code == 1 and "is running and owns the bus" in " ".join(out.split()), out


async def test_a_module_gone_silent_mid_run_is_reported_and_its_watchdog_stops_it(
    tmp_path: Path, sim: Rs485Simulator, plant: Plant,
) -> None:
    """The off cannot be written to a dead module: the CLI says so, and says what stops it."""
    cfg = paper_a_config(tmp_path, sim)
    task = asyncio.create_task(asyncio.to_thread(
        run, paper_a_argv(tmp_path, cfg, 5.0), lambda _q: pytest.fail("asked")))
    await eventually(lambda: sim.duty_pct["motor"] > 0, what="run 1")
    sim.set_silent(sim.device_ids["pwm"], True)
    code, out = await task
    text = " ".join(out.split())
    assert code == 1, text
    assert "stopped answering" in text and "could not switch the meter off" in text
    assert "comm_timeout_s = 2 s" in text
    await eventually(lambda: sim.duty_pct == {"motor": 0.0, "fan": 0.0}, timeout=5,
                     what="the module's own watchdog")
    assert sim.watchdog_trips == 1


def test_a_port_with_nothing_on_it_says_so(tmp_path: Path) -> None:
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(f'[rs485]\nport = "{tmp_path / "no-such-port"}"\n')
    code, out = run(paper_a_argv(tmp_path, cfg, 0.5), lambda _q: pytest.fail("asked"))
    text = " ".join(out.split())
    assert code == 1 and "does not answer" in text and "switch the meter off" not in text, text


async def test_ctrl_c_at_the_mass_prompt_switches_the_fan_off_and_exits(
    tmp_path: Path, sim: Rs485Simulator, plant: Plant,
) -> None:
    """The prompt waits in its own thread; Ctrl-C there still reaches the safe-off at once."""
    from tests.helpers import sowgate_argv

    cfg = paper_a_config(tmp_path, sim)
    proc = await asyncio.create_subprocess_exec(
        *sowgate_argv(*paper_a_argv(tmp_path, cfg, 0.5)), env=sowgate_env(tmp_path),
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE)
    try:
        # run 1 over: the motor stopped, the fan still on while the operator weighs
        await eventually(lambda: motor_steps(plant)[-2:] == [round(WHEAT_DUTIES[0], 1), 0.0],
                         SPAWN_TIMEOUT_S, "run 1 over")
        await asyncio.sleep(0.5)  # at the prompt now
        assert sim.duty_pct == {"motor": 0.0, "fan": 85.0}
        proc.send_signal(signal.SIGINT)
        stdout, stderr = await asyncio.wait_for(proc.communicate(), 30)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 130, (stdout.decode(), stderr.decode())
    assert "weighed mass of run 1" in stdout.decode()
    assert sim.duty_pct == {"motor": 0.0, "fan": 0.0}


def test_a_can_controller_that_does_not_answer_is_not_driven(tmp_path: Path) -> None:
    cfg = can_config(tmp_path, f"cal-{uuid.uuid4().hex[:8]}")  # nobody on this bus
    argv = ["calibrate", "--config", str(cfg), "--state-dir", str(tmp_path), "rotation",
            "--channel", "seed", "--drive", "can", "--speeds", "20,40", "--seconds", "1"]
    code, out = run(argv, lambda _q: pytest.fail("asked"))
    assert code == 1 and "no status from its controller (node 3)" in " ".join(out.split()), out
