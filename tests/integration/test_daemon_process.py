"""``sowgate run`` as the separate process systemd starts, against the simulated machine."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import AsyncIterator
from pathlib import Path

from simulator.machine import SimulatedMachine
from simulator.modbus_devices import Rs485Simulator
from tests.helpers import eventually, sowgate_env, sowgate_process
from tests.integration.conftest import steady_drive


@contextlib.asynccontextmanager
async def metering_process(
    tmp_path: Path,
) -> AsyncIterator[tuple[asyncio.subprocess.Process, Rs485Simulator]]:
    """``sowgate run`` in its own process against the simulated machine, once the metering
    motor and the fan turn; the process and the simulated RS485 bus."""
    async with SimulatedMachine(drive=steady_drive()) as machine:
        cfg = machine.write_config(tmp_path / "sowgate.toml", control={"start_working": True})
        env = sowgate_env(tmp_path / "state")
        async with sowgate_process("run", "--config", str(cfg), env=env) as proc:
            sim = machine.rs485
            assert sim is not None
            await eventually(lambda: sim.duty_pct["motor"] > 0 and sim.duty_pct["fan"] > 0, 20.0,
                             "motor and fan turning")
            yield proc, sim


async def test_sigterm_sets_motor_and_fan_to_zero_before_the_process_exits(
    tmp_path: Path,
) -> None:
    async with metering_process(tmp_path) as (proc, sim):
        proc.send_signal(signal.SIGTERM)
        _, stderr = await asyncio.wait_for(proc.communicate(), 10.0)
        assert proc.returncode == 0, stderr.decode()
        assert sim.duty_pct == {"motor": 0.0, "fan": 0.0}


async def _demo(state: Path, *args: str) -> str:
    """``sowgate demo --no-tui ARGS`` in its own process, its store in ``state``; its output."""
    async with sowgate_process("demo", "--no-tui", "--state-dir", str(state), *args) as proc:
        out, err = await asyncio.wait_for(proc.communicate(), 60.0)
    assert proc.returncode == 0, err.decode()
    return out.decode()


async def test_demo_runs_and_reports_the_applied_rate(tmp_path: Path) -> None:
    out = await _demo(tmp_path, "--duration", "4")
    # the simulated tractor stands for its first 4 s: at most a start-up has been sown, and
    # the demo must say so instead of presenting that as the controller's rate error
    line = next(line for line in out.splitlines() if line.startswith("demo finished: "))
    assert "nothing sown yet" in line or "not representative" in line, line


async def test_demo_with_paper_b_channels_drives_the_simulated_can_controllers(
    tmp_path: Path,
) -> None:
    # 6 s is mostly the start from standstill (~55 % of target applied, marginal under load);
    # by 10 s the shafts have clearly followed the targets (~85 %)
    out = await _demo(tmp_path, "--channels", "--duration", "10")
    lines = {
        line.split(":")[0].removeprefix("channel "): line
        for line in out.splitlines()
        if line.startswith("channel ")
    }
    assert sorted(lines) == ["deep", "seed", "shallow"]
    for name, target in (("shallow", 150.0), ("deep", 300.0), ("seed", 225.0)):
        applied = float(lines[name].split("applied ")[1].split(" ")[0])
        assert 0.5 * target < applied < 1.2 * target, lines[name]  # the shafts really turned


async def test_systemd_notify_ready_watchdog_and_stopping(tmp_path: Path) -> None:
    import socket

    sock_path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.setblocking(False)
    received: list[str] = []
    loop = asyncio.get_running_loop()
    loop.add_reader(sock.fileno(), lambda: received.append(sock.recv(4096).decode()))
    try:
        async with SimulatedMachine(drive=steady_drive()) as machine:
            cfg = machine.write_config(tmp_path / "sowgate.toml")
            env = sowgate_env(tmp_path / "state", {
                "NOTIFY_SOCKET": str(sock_path),
                "WATCHDOG_USEC": "1000000",  # pings every 0.5 s while the loop runs
            })
            async with sowgate_process(
                "run", "--config", str(cfg), env=env, stdout=asyncio.subprocess.DEVNULL
            ) as proc:
                await eventually(lambda: any("READY=1" in m for m in received), 20.0, "READY=1")
                await eventually(lambda: sum("WATCHDOG=1" in m for m in received) >= 3, 10.0,
                                 "three WATCHDOG=1")
                proc.send_signal(signal.SIGTERM)
                await asyncio.wait_for(proc.wait(), 10.0)
            await eventually(lambda: any("STOPPING=1" in m for m in received), 5.0, "STOPPING=1")
    finally:
        loop.remove_reader(sock.fileno())
        sock.close()


async def test_demo_publishes_to_the_broker_named_in_the_environment(tmp_path: Path) -> None:
    """What docker/compose.yaml relies on: `sowgate demo` + SOWGATE_MQTT__* → seeds on MQTT."""
    from tests.mosquitto import Mosquitto, subscriber

    with Mosquitto() as broker:
        async with subscriber(broker.port, "sowgate/seeder-01") as sub:
            # as in compose.yaml: naming the broker switches MQTT on, no ENABLED needed
            env = sowgate_env(env={
                "SOWGATE_MQTT__HOST": "127.0.0.1", "SOWGATE_MQTT__PORT": str(broker.port)})
            async with sowgate_process(
                "demo", "--no-tui", "--duration", "8", "--state-dir", str(tmp_path), env=env
            ) as proc:
                out, err = await asyncio.wait_for(proc.communicate(), 60.0)
            assert proc.returncode == 0, err.decode()
            await eventually(lambda: sub.on("status")[-1:] == [b"offline"], 5.0, "offline")
    assert sub.on("status")[0] == b"online"
    assert sub.on("state") and sub.seed_ids()
    # and it told the user where it publishes
    said = out.decode()
    assert f"MQTT: broker 127.0.0.1:{broker.port} (reachable)" in said, said
    assert "sowgate/seeder-01/status" in said, said


async def test_sowgate_run_says_so_and_exits_1_when_the_pwm_module_is_silent_at_stop(
    tmp_path: Path,
) -> None:
    async with metering_process(tmp_path) as (proc, sim):
        sim.set_fault(sim.device_ids["pwm"], "silent")
        proc.send_signal(signal.SIGTERM)
        _, stderr = await asyncio.wait_for(proc.communicate(), 10.0)
    text = stderr.decode()
    assert proc.returncode == 1, text
    last = text.strip().splitlines()[-1]
    assert last.startswith("sowgate: could not set motor and fan to 0 on exit: PWM module"), text
    assert "actuators.comm_timeout_s = 2 s" in last
    assert "ERROR gateway.app.daemon: could not set motor and fan to 0 on exit" in text


async def test_an_absent_rs485_port_is_one_clear_line_not_pymodbus_noise(tmp_path: Path) -> None:
    """The adapter not plugged in: one line names the port, why it is down and what is retried;
    no per-device, per-register repeats of it and nothing of pymodbus's own logging."""
    port = tmp_path / "ttyRS485"  # never created
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(f'[machine]\nid = "m1"\n[rs485]\nport = "{port}"\n[hmi]\nenabled = false\n')
    async with sowgate_process("run", "--config", str(cfg),
                               env=sowgate_env(tmp_path / "state")) as proc:
        assert proc.stderr is not None
        seen: list[str] = []

        async def until_the_port_line() -> None:
            assert proc.stderr is not None
            while "is down" not in "".join(seen):
                line = await proc.stderr.readline()
                assert line, "".join(seen)
                seen.append(line.decode())

        await asyncio.wait_for(until_the_port_line(), 30.0)
        await asyncio.sleep(1.5)  # requests to radar, inclinometer and PWM module fail meanwhile
        proc.send_signal(signal.SIGTERM)
        _, rest = await asyncio.wait_for(proc.communicate(), 30.0)
    lines = [*seen, *rest.decode().splitlines(keepends=True)]
    text = "".join(lines)
    down = [line for line in lines if "is down" in line and "WARNING" in line]
    assert len(down) == 1, text
    assert f"RS485 port {port} is down ({port} does not exist): sowgate retries opening it" in (
        down[0]), text
    assert "pymodbus" not in text and "Repeating" not in text, text
    assert "reconnecting" not in text, text
    # the stop cannot reach the PWM module: said once, with the port's reason, not per register
    last = lines[-1]
    assert last.startswith("sowgate: could not set motor and fan to 0 on exit"), text
    assert last.count(str(port)) == 2 and len(last) - 2 * len(str(port)) < 280, last
