"""Rows about the devices: every Modbus fault on one daemon, then the serial lines fuzzed on
another (faults that do not interfere share a daemon and run one after the other)."""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Awaitable, Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

from gateway.recording.store import RecordStore
from tests.helpers import eventually
from tests.mosquitto import Mosquitto, Subscriber
from tests.reliability.harness import (
    MACHINE_ID,
    DaemonProcess,
    RowResult,
    Steady,
    TracedMachine,
    dashboard,
    finish_row,
    fmt_s,
    late_epochs_note,
    mqtt_overrides,
    records_vs_edges,
    recovered_after,
    sowing_drive,
    steady_drive,
    steady_duty,
)
from tests.reliability.rows import (
    AFTER_FAULT_S,
    BINARY_LOG_BYTES,
    DUTY_TOLERANCE_PCT,
    FUZZ_S,
    LOG_LINES_PER_FUZZ_MAX,
    MODBUS_FAULT_S,
    MOTOR_STOPPED_WITHIN_S,
    RECOVERY_MAX_S,
    RSS_GROWTH_MAX_MB,
    SPEED_GAP_S,
)

# ---- Modbus faults on one daemon ------------------------------------------------------------


async def _modbus_fault(
    machine: TracedMachine,
    dash: Subscriber,
    daemon: DaemonProcess,
    steady: Steady,
    fault: str,
) -> RowResult:
    res = RowResult()
    sim = machine.rs485
    assert sim is not None
    radar_id = sim.radar.device_id
    tb0 = daemon.tracebacks()
    t0 = time.monotonic()
    if fault == "speed_gap":
        sim.hold_radar(0.0)
    elif fault == "vanished":
        sim.vanish()
    else:
        sim.set_fault(radar_id, fault)  # type: ignore[arg-type]
    stopped_at: float | None = None
    while time.monotonic() - t0 < (SPEED_GAP_S if fault == "speed_gap" else MODBUS_FAULT_S):
        if stopped_at is None and machine.motor_pct() == 0.0:
            stopped_at = time.monotonic() - t0
        await asyncio.sleep(0.05)
    if fault == "speed_gap":
        sim.hold_radar(None)
    elif fault == "vanished":
        sim.restore()
    else:
        sim.set_fault(radar_id, None)
    t1 = time.monotonic()
    await asyncio.sleep(AFTER_FAULT_S)
    t2 = time.monotonic()
    during = max(machine.duty_between(t0, t1), default=0.0)
    after = machine.duty_between(t1, t2)
    recovered = recovered_after(machine, t1, steady, DUTY_TOLERANCE_PCT)
    res.duty = f"{during:.1f} / {max(after, default=0.0):.1f} (steady {steady})"
    res.recovery = fmt_s(recovered)
    limit = steady.high + DUTY_TOLERANCE_PCT
    res.check(during <= limit, f"duty {during:.1f} % during the fault, above {limit:.1f} %")
    res.check(max(after, default=0.0) <= limit,
              f"duty up to {max(after, default=0.0):.1f} % after the fault (steady {steady}, "
              f"limit {limit:.1f} %)")
    res.check(recovered is not None and recovered <= RECOVERY_MAX_S,
              f"duty back at steady after {fmt_s(recovered)} (limit {RECOVERY_MAX_S:g} s)")
    res.check(daemon.running, "daemon exited")
    alarms = dash.alarms_between(t0, t1 + 1.0)
    if fault == "vanished":
        res.check(stopped_at is not None and stopped_at <= MOTOR_STOPPED_WITHIN_S,
                  f"the PWM module kept driving the motor ({during:.1f} %) "
                  + ("for the whole outage" if stopped_at is None else f"for {stopped_at:.1f} s")
                  + f" with the port gone (limit {MOTOR_STOPPED_WITHIN_S:g} s)")
        res.check("pwm.unavailable" in alarms, "pwm.unavailable not published while the port "
                                               f"was gone (seen: {sorted(alarms)})")
    elif stopped_at is not None and fault != "speed_gap":  # 0 km/h read: standing, not lost
        res.check(bool({"speed.lost", "radar.unavailable"} & alarms),
                  "metering stopped without speed.lost / radar.unavailable on MQTT "
                  f"(seen: {sorted(alarms)})")
    res.notes.append(
        "metering " + ("stopped after " + fmt_s(stopped_at) if stopped_at is not None
                       else "did not stop")
        + f"; alarms: {', '.join(sorted(alarms)) or 'none'}"
    )
    finish_row(res, daemon, tb0)
    return res


MODBUS_FAULTS = ("silent", "crc", "wrong_id", "exception", "truncated", "noise", "speed_gap",
                 "vanished")


def _modbus_row(fault: str) -> str:
    if fault == "speed_gap":
        return "radar_speed_gap_1s"
    return "modbus_port_vanished" if fault == "vanished" else f"modbus_radar_{fault}"


async def group_modbus(tmp: Path) -> dict[str, RowResult]:
    out: dict[str, RowResult] = {}
    with Mosquitto() as broker:
        async with dashboard(broker.port) as dash, TracedMachine(drive=steady_drive()) as machine:
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
                await asyncio.sleep(6.0)  # up to speed, the speed filter full
                steady = await steady_duty(machine, 5.0)
                for fault in MODBUS_FAULTS:
                    out[_modbus_row(fault)] = await _modbus_fault(
                        machine, dash, daemon, steady, fault
                    )
            finally:
                await daemon.close()
    return out


# ---- serial lines fuzzed, on one daemon -----------------------------------------------------


def _junk(rng: random.Random, n: int, banned: bytes) -> bytes:
    return bytes(b for b in rng.randbytes(n * 2) if b not in banned)[:n]


async def group_serial(tmp: Path) -> dict[str, RowResult]:
    out: dict[str, RowResult] = {}
    rng = random.Random(7)
    machine = TracedMachine(drive=sowing_drive(75.0), with_gnss=True, with_seed_tubes=True)
    with Mosquitto() as broker:
        async with dashboard(broker.port), machine:
            tubes, gnss, hmi = machine.seed_tubes, machine.gnss, machine.hmi
            assert hmi is not None
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            db = tmp / "state" / "records.sqlite3"
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            windows: dict[str, tuple[float, float]] = {}
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)
                await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
                await asyncio.sleep(6.0)
                steady = await steady_duty(machine, 4.0)

                async def hmi_fuzz() -> None:
                    hmi.send_raw(rng.randbytes(64))

                async def seed_fuzz() -> None:
                    tubes.inject(_junk(rng, rng.randint(1, 200), b"\r\n") + b"\r\n")

                lines: list[tuple[str, Callable[[], Awaitable[None]] | None]] = [
                    ("serial_fuzz_hmi", hmi_fuzz),
                    ("serial_fuzz_gnss", None),
                    ("serial_fuzz_seed_line", seed_fuzz),
                ]
                for name, step in lines:
                    res = RowResult()
                    tb0, rss0 = daemon.tracebacks(), daemon.rss_mb()
                    log0 = len(daemon.own_log_lines())
                    t0 = time.monotonic()
                    if step is None:
                        gnss.interleave(_junk(rng, BINARY_LOG_BYTES, b"\n$#"))
                    while time.monotonic() - t0 < FUZZ_S:
                        if step is not None:
                            await step()
                        await asyncio.sleep(0.05)
                    if step is None:
                        gnss.interleave(None)
                    t1 = time.monotonic()
                    windows[name] = (t0, t1)
                    await asyncio.sleep(3.0)
                    # the daemon's own lines: pymodbus's "Repeating...." under load is not
                    # the daemon flooding the journal
                    new_lines = daemon.own_log_lines()[log0:]
                    logged = len(new_lines)
                    grown = daemon.rss_mb() - rss0
                    during = max(machine.duty_between(t0, time.monotonic()), default=0.0)
                    res.duty = f"{during:.1f} (steady {steady})"
                    limit = steady.high + DUTY_TOLERANCE_PCT
                    res.check(during <= limit, f"duty {during:.1f} % above {limit:.1f} %")
                    low = min(machine.duty_between(t0, time.monotonic()), default=0.0)
                    res.check(low >= steady.low - DUTY_TOLERANCE_PCT,
                              f"duty fell to {low:.1f} % (steady {steady}): the fuzz changed "
                              "what the motor does")
                    res.check(daemon.running, "daemon exited")
                    res.check(logged <= LOG_LINES_PER_FUZZ_MAX,
                              f"{logged} log lines in {FUZZ_S + 3:g} s (max "
                              f"{LOG_LINES_PER_FUZZ_MAX}: not rate-limited); the first: "
                              + " | ".join(line[24:160] for line in new_lines[:6]))
                    res.check(grown <= RSS_GROWTH_MAX_MB, f"RSS grew {grown:.1f} MB")
                    res.notes.append(f"{logged} log lines; RSS {grown:+.1f} MB")
                    finish_row(res, daemon, tb0)
                    out[name] = res
                sent, stored = await records_vs_edges(out["serial_fuzz_seed_line"], machine,
                                                       daemon, db, n_open)
            finally:
                await daemon.close()
            seed_row = out["serial_fuzz_seed_line"]
            seed_row.lost = f"{max(0, sent - stored)} of {sent} seed lines not stored"
            seed_row.check(stored >= sent, f"{sent - stored} valid seed lines lost among the junk")
            seed_row.daemon = daemon.describe_exit()
            out["serial_fuzz_hmi"].daemon = out["serial_fuzz_gnss"].daemon = seed_row.daemon
            _judge_gnss_window(out["serial_fuzz_gnss"], gnss, db, windows["serial_fuzz_gnss"])
    return out


def _judge_gnss_window(res: RowResult, gnss: Any, db: Path, window: tuple[float, float]) -> None:
    """Seeds that landed while the binary output was on: positioned from real epochs?"""
    first = gnss.truth[0]

    def utc_at(t_mono: float) -> Any:
        return first.utc + timedelta(seconds=t_mono - first.t_mono)

    lo, hi = utc_at(window[0] + 0.5), utc_at(window[1])
    with RecordStore.open_readonly(db, MACHINE_ID) as store:
        seeds = [r for r in store.query_seeds() if lo <= r.utc <= hi]
    poor = [r for r in seeds if r.fix != "rtk_fixed" or r.extrapolated]
    res.lost = f"{len(poor)} of {len(seeds)} seeds of the window without an RTK epoch"
    res.check(bool(seeds), "no seed recorded while the binary output was on")
    res.check(not poor, f"{len(poor)} of {len(seeds)} seeds recorded during the binary output "
                        "were extrapolated or not RTK-fixed: sentences after it were dropped"
                        + late_epochs_note(gnss, window))


