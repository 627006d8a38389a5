"""The control loop never waits on MQTT: control latency and tick regularity with the broker
up, stopped (connection refused) and black-holed (TCP accepted, never answered, as a dead 4G
link or a hung broker looks), while seeds flow from the simulator into the outbox."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import socket
import statistics
import time
from collections.abc import Iterator
from pathlib import Path

from gateway.control.controller import ControlOutputs
from tests.integration.conftest import running
from tests.integration.test_recording_end_to_end import BASE, recording_machine
from tests.mosquitto import Mosquitto, subscriber

POLL_HZ = 10.0
PHASE_S = 5.0
# A connect or publish that blocked the event loop shows up as a tick gap of a second or more
# (the connect timeout here is 10 s): no tick may come later than 0.3 s after the previous one
# (period 0.1 s). Reply -> PWM write: median within 2 ms, p99 (about the max of 50 samples)
# within 20 ms, a bound a shared CI machine's scheduling hiccups stay under; the benchmark's
# 5 ms p99 target is for a quiet machine (typical runs here: 0.2-2 ms in every phase).
MAX_P50_S = 0.002
MAX_P99_S = 0.020
MAX_TICK_GAP_S = 0.3


@contextlib.contextmanager
def black_hole(port: int) -> Iterator[None]:
    """Listen on ``port``, accept every connection, never send a byte."""
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen(16)  # the kernel completes the handshakes; nobody ever reads
    try:
        yield
    finally:
        srv.close()


def p99(samples: list[float]) -> float:
    return statistics.quantiles(samples, n=100)[98] if len(samples) >= 2 else float("nan")


async def test_control_latency_is_the_same_with_the_broker_up_down_and_black_holed(
    tmp_path: Path,
) -> None:
    ticks: list[float] = []
    figures: dict[str, tuple[float, float, float, int]] = {}
    with Mosquitto() as broker:
        async with subscriber(broker.port, BASE) as sub:
            machine = recording_machine(60.0)
            overrides = {
                "mqtt": {"enabled": True, "port": broker.port, "keepalive": 5,
                         "reconnect_max_s": 1.0},
                "control": {"start_working": True},
                "rs485": {"poll_hz": POLL_HZ},
                "actuators": {"refresh_s": 0.05},  # a duty write, so a latency sample, per tick
            }
            async with running(tmp_path, machine, **overrides) as rig:
                daemon = rig.daemon
                link = daemon.parts.mqtt

                def on_tick(_: ControlOutputs) -> None:
                    ticks.append(time.monotonic())

                daemon.tick_hooks.append(on_tick)

                async def phase(name: str) -> None:
                    daemon.latencies_s.clear()
                    ticks.clear()
                    stored = link.store.backlog()
                    await asyncio.sleep(PHASE_S)
                    lat = list(daemon.latencies_s)
                    gaps = [b - a for a, b in itertools.pairwise(ticks)]
                    figures[name] = (statistics.median(lat), p99(lat), max(gaps), len(lat))
                    assert len(ticks) >= PHASE_S * POLL_HZ * 0.8, f"{name}: {len(ticks)} ticks"
                    if name != "up":
                        assert link.store.backlog() > stored  # seeds kept coming meanwhile

                await rig.until(lambda: len(sub.seed_ids()) > 100, 20.0, "seeds on the broker")
                await phase("up")
                broker.stop()
                await rig.until(lambda: not link.connected, 10.0, "link down")
                await phase("down")
                with black_hole(broker.port):
                    await phase("black-holed")
                    assert not link.connected
    report = ", ".join(
        f"{k}: p50 {v[0] * 1e3:.2f} ms, p99 {v[1] * 1e3:.2f} ms, max tick gap "
        f"{v[2] * 1e3:.0f} ms ({v[3]} samples)"
        for k, v in figures.items()
    )
    print(f"control latency vs broker: {report}")
    for name, (lat_p50, lat_p99, gap, _) in figures.items():
        assert lat_p50 <= MAX_P50_S and lat_p99 <= MAX_P99_S, f"{name}: {report}"
        assert gap <= MAX_TICK_GAP_S, f"{name}: {report}"
