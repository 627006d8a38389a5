"""The AgOpenGPS row: AgIO drives the speed over UDP while a stranger on the LAN floods the
module port with well-formed frames of another speed and junk, and AgIO's own line carries
frames with bad checksums (docs/agopengps.md, "What the source trusts")."""

from __future__ import annotations

import asyncio
import random
import socket
import time
from pathlib import Path

from protocol import agopengps as aog
from tests.helpers import eventually
from tests.reliability.harness import (
    DaemonProcess,
    RowResult,
    TracedMachine,
    finish_row,
    sowing_drive,
    steady_duty,
)
from tests.reliability.rows import (
    AGOPENGPS_KMH,
    DUTY_TOLERANCE_PCT,
    FUZZ_S,
    LOG_LINES_PER_FUZZ_MAX,
    STRANGER_FRAMES_PER_TICK,
)

TICK_S = 0.1  # AgOpenGPS sends at its GNSS rate, 10 Hz


def _udp(host: str) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((host, 0))
    s.setblocking(False)
    return s


async def group_agopengps(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    rng = random.Random(11)
    machine = TracedMachine(drive=sowing_drive(60.0))
    agio, stranger = _udp("127.0.0.1"), _udp("127.0.0.2")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = int(probe.getsockname()[1])
    module = ("127.0.0.1", port)
    sections = [True] * 16
    fuzzing = False

    async def agio_sends() -> None:
        while True:
            agio.sendto(aog.encode_steer_data(AGOPENGPS_KMH, sections), module)
            agio.sendto(aog.encode_machine_data(AGOPENGPS_KMH, sections), module)
            if fuzzing:  # AgIO's own line corrupted: one bad checksum per tick
                bad = bytearray(aog.encode_steer_data(30.0, sections))
                bad[-1] ^= 0x5A
                agio.sendto(bytes(bad), module)
                stranger.sendto(rng.randbytes(rng.randint(0, 64)), module)
                for _ in range(STRANGER_FRAMES_PER_TICK):
                    stranger.sendto(aog.encode_steer_data(30.0, sections), module)
            await asyncio.sleep(TICK_S)

    async with machine:
        cfg = machine.write_config(
            tmp / "sowgate.toml",
            control={"start_working": True},
            speed={"source": "agopengps_then_radar"},
            agopengps={"listen": f"127.0.0.1:{port}",
                       "agio": f"127.0.0.1:{agio.getsockname()[1]}"},
        )
        daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
        sender = asyncio.create_task(agio_sends(), name="fake-agio")
        try:
            await daemon.start()
            await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
            await asyncio.sleep(4.0)
            steady = await steady_duty(machine, 3.0)
            tb0, log0 = daemon.tracebacks(), daemon.log_lines()
            t0 = time.monotonic()
            fuzzing = True
            await asyncio.sleep(FUZZ_S)
            fuzzing = False
            await asyncio.sleep(2.0)
            t1 = time.monotonic()
            during = machine.duty_between(t0, t1)
            high, low = max(during, default=0.0), min(during, default=0.0)
            res.duty = f"{low:.1f}–{high:.1f} (steady {steady})"
            res.check(high <= steady.high + DUTY_TOLERANCE_PCT,
                      f"duty {high:.1f} % above steady {steady}: the stranger moved the motor")
            res.check(low >= steady.low - DUTY_TOLERANCE_PCT,
                      f"duty fell to {low:.1f} % (steady {steady})")
            logged = daemon.log_lines() - log0
            res.check(logged <= LOG_LINES_PER_FUZZ_MAX,
                      f"{logged} log lines in {FUZZ_S + 2:g} s (not rate-limited)")
            res.check(daemon.running, "daemon exited")
            res.notes.append(f"{logged} log lines")
            finish_row(res, daemon, tb0)
        finally:
            sender.cancel()
            await asyncio.gather(sender, return_exceptions=True)
            await daemon.close()
            agio.close()
            stranger.close()
    return {"agopengps_stranger_flood": res}
