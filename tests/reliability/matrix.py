"""The fault matrix: each row a fault, how it is injected, the invariant that must hold.

Rows that need their own daemon run concurrently (the broker outage alone takes a minute);
rows whose faults do not interfere share one daemon and run one after the other on it
(the Modbus faults, the serial-line fuzz). Every group measures and returns a
:class:`RowResult` per row; the invariants are judged in ``test_fault_matrix.py`` and the
table in docs/reliability.md is rendered from the same results.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import random
import time
import tomllib
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import aiomqtt
import tomli_w

from gateway.config import EXIT_CONFIG
from gateway.store import RecordStore
from simulator.seed_tubes import SeedTubeEmulator
from tests.mosquitto import Mosquitto, free_port
from tests.reliability.harness import (
    BASE,
    MACHINE_ID,
    DaemonProcess,
    RowResult,
    Steady,
    TracedMachine,
    contiguous,
    eventually,
    fill,
    integrity,
    seed_ids,
    sowing_drive,
    steady_drive,
    tmpfs,
)
from tests.reliability.watcher import Watcher, watching

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_CONFIG = REPO / "examples" / "sowgate.toml"

# ---- figures the invariants are stated in ---------------------------------------------------
KILLS = 10
# What a SIGKILL may take with it: a seed is committed at the recorder's next flush (every
# store.commit_interval_s, 0.5 s) once its bracketing GNSS epoch is in, which it waits for at
# most positioning.pending_timeout_s (0.5 s). Seeds sensed longer ago than this are durable.
COMMIT_WINDOW_S = 0.5 + 0.5
BROKER_DOWN_S = 60.0
DISK_FULL_S = 20.0
# Motor duty: "no overshoot" means never above the highest steady duty by more than this
# (the radar's 3 % noise through the speed filter moves the duty by about ±1.5 points).
DUTY_TOLERANCE_PCT = 3.0
MODBUS_FAULT_S = 5.0
AFTER_FAULT_S = 6.0
SPEED_GAP_S = 1.0
RECOVERY_MAX_S = 6.0  # after the fault ends the duty is back at steady within this
# issue 11 item 4: the PWM module stops itself when sowgate has not written it for
# [actuators] comm_timeout_s (default 2 s); the margin is one poll period and a sample
COMM_TIMEOUT_S = 2.0
MOTOR_STOPPED_WITHIN_S = COMM_TIMEOUT_S + 1.0
FUZZ_S = 5.0
# A fuzzed line may not flood the journal: warnings about it are rate-limited with a count.
LOG_LINES_PER_FUZZ_MAX = 10
RSS_GROWTH_MAX_MB = 30.0
BINARY_LOG_BYTES = 1100  # binary receiver output between two sentences (over a line's limit)


@dataclass(frozen=True)
class Row:
    name: str
    group: str
    injected: str
    invariant: str


ROWS: tuple[Row, ...] = (
    Row("sigkill_during_seeding_x10", "kills",
        f"SIGKILL the daemon {KILLS}× while seeding (~2–3 s of seeds each time), restarted at "
        "once on the same store",
        "`integrity_check` ok after every kill; ids 1..N contiguous; per kill, records lost "
        f"≤ seeds sensed in the last {COMMIT_WINDOW_S:g} s (the commit window)"),
    Row("broker_down_60s", "broker",
        f"mosquitto stopped for {BROKER_DOWN_S:g} s while seeding, then started again",
        "the store keeps recording; every seed edge becomes a record; every stored id is "
        "delivered; daemon never exits"),
    Row("disk_full_20s", "disk",
        f"state dir on a 2 MiB tmpfs, filled to the last byte for {DISK_FULL_S:g} s, then "
        "remounted 64 MiB",
        "every seed edge becomes a record (none lost); `records.store_failed` published on "
        "MQTT while full; ids contiguous; integrity ok"),
    *(
        Row(f"modbus_radar_{fault}", "modbus",
            f"radar (id 1): {how} for {MODBUS_FAULT_S:g} s at a steady 8 km/h",
            "daemon up, no traceback; motor duty during and after ≤ steady max + "
            f"{DUTY_TOLERANCE_PCT:g} points; back at steady ≤ {RECOVERY_MAX_S:g} s after; "
            "metering never stops without an alarm on MQTT")
        for fault, how in (
            ("silent", "no reply at all"),
            ("crc", "every reply with a wrong CRC"),
            ("wrong_id", "every reply from another device id (valid CRC)"),
            ("exception", "every reply a Modbus exception (device failure)"),
            ("truncated", "every reply cut after half its bytes"),
            ("noise", "1–16 bytes of line noise ahead of every reply"),
        )
    ),
    Row("radar_speed_gap_1s", "modbus",
        f"the radar reads 0 km/h for {SPEED_GAP_S:g} s at a steady 8 km/h (valid replies), then "
        "8 km/h again",
        f"motor duty after the gap ≤ steady max + {DUTY_TOLERANCE_PCT:g} points (no "
        f"overshoot); back at steady ≤ {RECOVERY_MAX_S:g} s; daemon up, no traceback"),
    Row("modbus_port_vanished", "modbus",
        f"the RS485 adapter unplugged for {MODBUS_FAULT_S:g} s (port path gone, fd EIO), "
        "then plugged back",
        f"the PWM module's motor output is 0 within {MOTOR_STOPPED_WITHIN_S:g} s (module "
        f"comm-loss timeout {COMM_TIMEOUT_S:g} s); `pwm.unavailable` on MQTT; after replug back "
        f"at steady ≤ {RECOVERY_MAX_S:g} s without overshoot"),
    Row("serial_fuzz_hmi", "serial",
        f"{FUZZ_S:g} s of random bytes (64 B every 50 ms) on the touchscreen line",
        f"daemon up, no traceback; duty unchanged (≤ steady max + {DUTY_TOLERANCE_PCT:g}); "
        f"≤ {LOG_LINES_PER_FUZZ_MAX} log lines; RSS growth ≤ {RSS_GROWTH_MAX_MB:g} MB"),
    Row("serial_fuzz_gnss", "serial",
        f"{FUZZ_S:g} s of {BINARY_LOG_BYTES} B of binary output (no line end) before every "
        "sentence on the GNSS line",
        "daemon up, no traceback; the valid sentences after the binary are kept: every seed "
        f"of the window RTK-fixed, none extrapolated; ≤ {LOG_LINES_PER_FUZZ_MAX} log lines"),
    Row("serial_fuzz_seed_line", "serial",
        f"{FUZZ_S:g} s of random junk lines (1–200 B + CRLF every 50 ms) between the seed lines",
        "daemon up, no traceback; every valid seed line becomes a record; "
        f"≤ {LOG_LINES_PER_FUZZ_MAX} log lines; RSS growth ≤ {RSS_GROWTH_MAX_MB:g} MB"),
    Row("command_fuzz", "commands",
        "hostile payloads on every `cmd/<name>` (nesting 2000 deep, wrong types, numbers as "
        "strings, NaN, invalid UTF-8, random bytes, unknown names) plus random JSON",
        "one error ack per command; the MQTT session never restarts; strict types "
        "(`\"6\"` is not a rate); daemon up, no traceback"),
    Row("config_fuzz_values", "config",
        "every key of examples/sowgate.toml given a wrong type, ±1e9, plus an unknown key "
        "per table and broken TOML; `sowgate check-config` for each, `sowgate run` for "
        "the first rejected one of each table",
        f"exit 0 (accepted) or {EXIT_CONFIG} naming the key (or the TOML line); the wrong "
        "type and unknown keys always rejected; never a traceback"),
    Row("config_fuzz_files", "config",
        "a missing `mqtt.tls.ca_file`, a missing `mqtt.password_file`, a state dir that is "
        "a file",
        f"`sowgate run` exits {EXIT_CONFIG} naming the key within 10 s; `check-config` "
        f"exits {EXIT_CONFIG} for the config file keys; never a traceback"),
)
ROWS_BY_NAME = {r.name: r for r in ROWS}


def _finish(res: RowResult, daemon: DaemonProcess, tracebacks_before: int = 0) -> None:
    """Daemon state and uncaught exceptions, common to every row with a daemon."""
    res.daemon = daemon.describe_exit()
    tb = daemon.tracebacks() - tracebacks_before
    res.tracebacks = str(tb)
    res.check(tb == 0, f"{tb} uncaught exception(s) (Traceback) in the daemon log "
                       f"{daemon.log_path}")


def _fmt_s(seconds: float | None) -> str:
    return "never" if seconds is None else f"{seconds:.1f} s"


def _edges_since(tubes: SeedTubeEmulator, n0: int) -> int:
    return len(tubes.truth) - n0


def _mono(tubes: SeedTubeEmulator, t_edge: float) -> float:
    assert tubes.t0_mono is not None
    return tubes.t0_mono + t_edge


# ---- SIGKILL ×10 ----------------------------------------------------------------------------


async def group_kills(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    rng = random.Random(11)
    machine = TracedMachine(drive=sowing_drive(KILLS * 6.0 + 10.0), with_gnss=True,
                            with_seed_tubes=True)
    async with machine:
        tubes = machine.seed_tubes
        cfg = machine.write_config(tmp / "sowgate.toml", control={"start_working": True})
        db = tmp / "state" / "records.sqlite3"
        daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
        try:
            prev = 0
            losses: list[tuple[int, int]] = []  # (lost, allowed) per kill
            restarts: list[float] = []
            t_killed: float | None = None
            for k in range(KILLS):
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0,
                                 f"seed port open (start {k + 1})")
                if t_killed is not None:
                    restarts.append(time.monotonic() - t_killed)
                n_open = len(tubes.truth)
                await eventually(lambda n0=n_open: _edges_since(tubes, n0) >= 10, 30.0,
                                 "seeds falling")
                await asyncio.sleep(1.5 + rng.uniform(0.0, 1.0))  # any phase of the commit
                n_kill, t_killed = len(tubes.truth), time.monotonic()
                code = await daemon.kill()
                res.check(code == -9, f"kill {k + 1}: exit code {code}, not -9 (SIGKILL)")
                check = integrity(db)
                res.check(check == "ok", f"kill {k + 1}: integrity_check says {check!r}")
                ids = seed_ids(db)
                res.check(contiguous(ids), f"kill {k + 1}: ids not contiguous "
                                           f"({len(ids)} rows, max {ids[-1] if ids else 0})")
                stored = len(ids) - prev
                prev = len(ids)
                sent = n_kill - n_open
                window = sum(
                    1 for s in tubes.truth[n_open:n_kill]
                    if _mono(tubes, s.t_edge) >= t_killed - COMMIT_WINDOW_S
                )
                lost = max(0, sent - stored)
                losses.append((lost, window))
                res.check(lost <= window, f"kill {k + 1}: {lost} records lost of {sent} sensed, "
                                          f"more than the {window} of the commit window")
            total_lost = sum(lost for lost, _ in losses)
            total_allowed = sum(window for _, window in losses)
            res.lost = (f"{total_lost} in {KILLS} kills (max {max(x for x, _ in losses)} a kill; "
                        f"commit window held {total_allowed})")
            median = sorted(restarts)[len(restarts) // 2]
            res.recovery = (f"restart → seed port open: median {median:.1f} s, "
                            f"max {max(restarts):.1f} s")
            res.notes.append(f"{prev} records, ids 1..{prev} contiguous; integrity ok after "
                             f"each kill" if not res.problems else f"{prev} records")
        finally:
            await daemon.close()
        _finish(res, daemon)
        res.daemon = f"{KILLS} × exit −9, restarted each time"
    return {"sigkill_during_seeding_x10": res}


# ---- broker down 60 s -----------------------------------------------------------------------


def _mqtt(port: int, **extra: Any) -> dict[str, Any]:
    return {
        "mqtt": {"enabled": True, "port": port, "keepalive": 5, "reconnect_max_s": 1.0},
        "control": {"start_working": True},
        **extra,
    }


async def _records_vs_edges(
    res: RowResult, machine: TracedMachine, daemon: DaemonProcess, db: Path, n_open: int
) -> tuple[int, int]:
    """Stop the daemon once the pass has ended; (edges sensed, records stored)."""
    await eventually(lambda: machine.pose().speed_kmh == 0.0, 120.0, "end of the pass")
    await asyncio.sleep(1.0)  # the last seeds fall
    tubes = machine.seed_tubes
    sent = _edges_since(tubes, n_open)
    code = await daemon.stop()
    res.check(code == 0, f"graceful stop exited {code}")
    ids = seed_ids(db)
    res.check(contiguous(ids), f"ids not contiguous ({len(ids)} rows)")
    check = integrity(db)
    res.check(check == "ok", f"integrity_check says {check!r}")
    return sent, len(ids)


async def group_broker(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    machine = TracedMachine(drive=sowing_drive(BROKER_DOWN_S + 20.0), with_gnss=True,
                            with_seed_tubes=True)
    with Mosquitto(persistent=True) as broker:
        async with watching(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            cfg = machine.write_config(tmp / "sowgate.toml", **_mqtt(broker.port))
            db = tmp / "state" / "records.sqlite3"
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)
                await eventually(lambda: len(dash.seed_ids()) > 100, 30.0, "seeds on the broker")
                broker.stop()
                at_down = len(seed_ids(db))
                await asyncio.sleep(BROKER_DOWN_S)
                res.check(daemon.running, "daemon exited while the broker was down")
                during = len(seed_ids(db)) - at_down
                res.check(during > 0, "the store recorded nothing while the broker was down")
                broker.start()
                backlog = seed_ids(db)
                try:
                    took = await eventually(lambda: set(backlog) <= dash.seed_ids(), 60.0,
                                            "the outage's backlog delivered")
                    res.recovery = f"backlog of {len(backlog) - at_down} delivered {took:.1f} s " \
                                   "after the broker came back"
                except AssertionError as exc:
                    res.problems.append(str(exc))
                    res.recovery = "backlog never delivered"
                sent, stored = await _records_vs_edges(res, machine, daemon, db, n_open)
                ids = seed_ids(db)
                with contextlib.suppress(AssertionError):
                    await eventually(lambda: set(ids) <= dash.seed_ids(), 10.0, "all delivered")
                undelivered = len(set(ids) - dash.seed_ids())
                res.lost = (f"{max(0, sent - stored)} of {sent} edges not stored; "
                            f"{undelivered} of {len(ids)} stored not delivered")
                res.check(stored >= sent, f"{sent - stored} of {sent} seed edges not stored")
                res.check(undelivered == 0, f"{undelivered} stored records never delivered")
                res.notes.append(f"{during} records stored during the outage")
            finally:
                await daemon.close()
            _finish(res, daemon)
    return {"broker_down_60s": res}


# ---- disk full 20 s -------------------------------------------------------------------------


async def group_disk(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    machine = TracedMachine(drive=sowing_drive(DISK_FULL_S + 20.0), with_gnss=True,
                            with_seed_tubes=True)
    with tmpfs(tmp / "disk", "2m") as disk, Mosquitto() as broker:
        async with watching(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            state = disk / "state"
            cfg = machine.write_config(tmp / "sowgate.toml", **_mqtt(broker.port))
            db = state / "records.sqlite3"
            daemon = DaemonProcess(cfg, state, tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)
                await eventually(lambda: len(seed_ids(db)) > 100, 30.0, "seeds stored")
                t_full = time.monotonic()
                filled = fill(disk)
                await asyncio.sleep(DISK_FULL_S)
                res.check(daemon.running, "daemon exited while the disk was full")
                remount = await asyncio.create_subprocess_exec(
                    "mount", "-o", "remount,size=64m", str(disk))
                res.check(await remount.wait() == 0, "could not remount the tmpfs larger")
                (disk / "filler").unlink()
                t_free = time.monotonic()
                alarms = dash.alarms_between(t_full, t_free + 1.0)
                res.check("records.store_failed" in alarms,
                          "records.store_failed never published on MQTT while the disk was full "
                          f"(seen: {', '.join(sorted(alarms)) or 'none'})")
                sent_by_free = _edges_since(tubes, n_open)
                try:
                    took = await eventually(lambda: len(seed_ids(db)) >= sent_by_free, 30.0,
                                            "the store caught up with the seeds of the outage")
                    res.recovery = f"store caught up {took:.1f} s after space came back"
                except AssertionError:
                    res.recovery = "store never caught up"
                sent, stored = await _records_vs_edges(res, machine, daemon, db, n_open)
                res.lost = f"{max(0, sent - stored)} of {sent} edges not stored"
                res.check(stored >= sent, f"{sent - stored} of {sent} seed edges lost to the "
                                          "full disk")
                res.notes.append(f"{filled // 1024} KiB filled; alarms seen while full: "
                                 f"{', '.join(sorted(alarms)) or 'none'}")
            finally:
                await daemon.close()
                with contextlib.suppress(OSError):
                    (disk / "filler").unlink()
            _finish(res, daemon)
    return {"disk_full_20s": res}


# ---- Modbus faults on one daemon ------------------------------------------------------------


async def _steady(machine: TracedMachine, seconds: float) -> Steady:
    t0 = time.monotonic()
    await asyncio.sleep(seconds)
    return Steady.of(machine.duty_between(t0, time.monotonic()))


def _recovered_after(machine: TracedMachine, t_end: float, steady: Steady) -> float | None:
    """Seconds from ``t_end`` until the duty was back in the steady band, None if not yet."""
    for t, d in machine.duty:
        if t >= t_end and steady.low - DUTY_TOLERANCE_PCT <= d <= steady.high + DUTY_TOLERANCE_PCT:
            return t - t_end
    return None


async def _modbus_fault(
    machine: TracedMachine,
    dash: Watcher,
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
    if fault == "silent":
        sim.set_silent(radar_id, True)
    elif fault == "speed_gap":
        machine.radar_override_kmh = 0.0
    elif fault == "vanished":
        sim.vanish()
    else:
        sim.set_reply_fault(radar_id, fault)  # type: ignore[arg-type]
    stopped_at: float | None = None
    while time.monotonic() - t0 < (SPEED_GAP_S if fault == "speed_gap" else MODBUS_FAULT_S):
        if stopped_at is None and machine.motor_pct() == 0.0:
            stopped_at = time.monotonic() - t0
        await asyncio.sleep(0.05)
    if fault == "silent":
        sim.set_silent(radar_id, False)
    elif fault == "speed_gap":
        machine.radar_override_kmh = None
    elif fault == "vanished":
        sim.restore()
    else:
        sim.set_reply_fault(radar_id, None)
    t1 = time.monotonic()
    await asyncio.sleep(AFTER_FAULT_S)
    t2 = time.monotonic()
    during = max(machine.duty_between(t0, t1), default=0.0)
    after = machine.duty_between(t1, t2)
    recovered = _recovered_after(machine, t1, steady)
    res.duty = f"{during:.1f} / {max(after, default=0.0):.1f} (steady {steady})"
    res.recovery = _fmt_s(recovered)
    limit = steady.high + DUTY_TOLERANCE_PCT
    res.check(during <= limit, f"duty {during:.1f} % during the fault, above {limit:.1f} %")
    res.check(max(after, default=0.0) <= limit,
              f"duty up to {max(after, default=0.0):.1f} % after the fault (steady {steady}, "
              f"limit {limit:.1f} %)")
    res.check(recovered is not None and recovered <= RECOVERY_MAX_S,
              f"duty back at steady after {_fmt_s(recovered)} (limit {RECOVERY_MAX_S:g} s)")
    res.check(daemon.running, "daemon exited")
    alarms = dash.alarms_between(t0, t1 + 1.0)
    if fault == "vanished":
        res.check(stopped_at is not None and stopped_at <= MOTOR_STOPPED_WITHIN_S,
                  f"the PWM module kept driving the motor ({during:.1f} %) "
                  + ("for the whole outage" if stopped_at is None else f"for {stopped_at:.1f} s")
                  + f" with the port gone (limit {MOTOR_STOPPED_WITHIN_S:g} s)")
        res.check("pwm.unavailable" in alarms, "pwm.unavailable not published while the port "
                                               f"was gone (seen: {sorted(alarms)})")
    elif stopped_at is not None:
        res.check(bool({"speed.lost", "radar.unavailable"} & alarms),
                  "metering stopped without speed.lost / radar.unavailable on MQTT "
                  f"(seen: {sorted(alarms)})")
    res.notes.append(
        "metering " + ("stopped after " + _fmt_s(stopped_at) if stopped_at is not None
                       else "did not stop")
        + f"; alarms: {', '.join(sorted(alarms)) or 'none'}"
    )
    _finish(res, daemon, tb0)
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
        async with watching(broker.port) as dash, TracedMachine(drive=steady_drive()) as machine:
            cfg = machine.write_config(tmp / "sowgate.toml", **_mqtt(broker.port))
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
                await asyncio.sleep(6.0)  # up to speed, the speed filter full
                steady = await _steady(machine, 5.0)
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
    machine = TracedMachine(drive=sowing_drive(55.0), with_gnss=True, with_seed_tubes=True)
    with Mosquitto() as broker:
        async with watching(broker.port), machine:
            tubes, gnss, hmi = machine.seed_tubes, machine.gnss, machine.hmi
            assert hmi is not None
            cfg = machine.write_config(tmp / "sowgate.toml", **_mqtt(broker.port))
            db = tmp / "state" / "records.sqlite3"
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            windows: dict[str, tuple[float, float]] = {}
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)
                await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
                await asyncio.sleep(6.0)
                steady = await _steady(machine, 4.0)

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
                    tb0, log0, rss0 = daemon.tracebacks(), daemon.log_lines(), daemon.rss_mb()
                    t0 = time.monotonic()
                    if step is None:
                        gnss.interleave(_junk(rng, BINARY_LOG_BYTES, b"\r\n$#"))
                    while time.monotonic() - t0 < FUZZ_S:
                        if step is not None:
                            await step()
                        await asyncio.sleep(0.05)
                    if step is None:
                        gnss.interleave(None)
                    t1 = time.monotonic()
                    windows[name] = (t0, t1)
                    await asyncio.sleep(3.0)
                    logged = daemon.log_lines() - log0
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
                              f"{LOG_LINES_PER_FUZZ_MAX}: not rate-limited)")
                    res.check(grown <= RSS_GROWTH_MAX_MB, f"RSS grew {grown:.1f} MB")
                    res.notes.append(f"{logged} log lines; RSS {grown:+.1f} MB")
                    _finish(res, daemon, tb0)
                    out[name] = res
                sent, stored = await _records_vs_edges(out["serial_fuzz_seed_line"], machine,
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
                        "were extrapolated or not RTK-fixed: sentences after it were dropped")


# ---- command fuzz ---------------------------------------------------------------------------

COMMAND_NAMES = ("rate", "channel_rate", "start", "stop", "zero_tilt", "tilt_critical",
                 "speed_cal", "no_such_command", "rate/extra", "RATE")


def command_corpus(seed: int = 5, random_count: int = 120) -> list[tuple[str, bytes]]:
    """(command name, payload): the hostile classics on every name, then random JSON."""
    rng = random.Random(seed)
    classics = [
        b"[" * 2000, b"{\"a\":" * 1000 + b"1" + b"}" * 1000, b"[" * 100_000,
        b"", b"null", b"true", b"0", b"\"rate\"", b"[]", b"{}", b"{\"crop\":",
        b"\xff\xfe\x00garbage", b"\x00" * 64, rng.randbytes(512),
        b"{\"crop\": \"rapeseed\", \"rate_kg_ha\": \"6\"}",
        b"{\"crop\": \"rapeseed\", \"rate_kg_ha\": NaN}",
        b"{\"crop\": \"rapeseed\", \"rate_kg_ha\": 1e999}",
        b"{\"crop\": \"rapeseed\", \"rate_kg_ha\": -1e999}",
        b"{\"crop\": \"rapeseed\", \"rate_kg_ha\": 123456789012345678901234567890}",
        b"{\"crop\": [\"rapeseed\"], \"rate_kg_ha\": {\"x\": 1}}",
        b"{\"crop\": \"rapeseed\", \"rate_kg_ha\": 6, \"request_id\": {\"a\": [1, 2]}}",
        b"{\"channel\": \"\\u0000\", \"rate_kg_ha\": 6}",
        b"{\"action\": \"finish\", \"distance_m\": \"12\"}",
        b"{\"action\": " + b"\"" + b"x" * 3000 + b"\"}",
        json.dumps({"crop": "rapeseed", "rate_kg_ha": 6, "extra": "x" * 3900}).encode(),
    ]
    out = [(name, p) for name in COMMAND_NAMES for p in classics]
    for _ in range(random_count):
        out.append((rng.choice(COMMAND_NAMES), json.dumps(_random_json(rng, 0)).encode()))
    return out


def _random_json(rng: random.Random, depth: int) -> Any:
    kind = rng.randrange(7 if depth < 4 else 4)
    if kind == 0:
        return rng.choice([None, True, False])
    if kind == 1:
        return rng.choice([0, -1, 6, 6.0, 2**63, -(2**63), 1e308, 0.1])
    if kind == 2:
        return rng.choice(["", "rapeseed", "wheat", "start", "finish", "x" * 300, "\u202e"])
    if kind == 3:
        return rng.uniform(-1e6, 1e6)
    if kind == 4:
        return [_random_json(rng, depth + 1) for _ in range(rng.randrange(4))]
    keys = ["crop", "rate_kg_ha", "channel", "action", "distance_m", "request_id", "z"]
    return {rng.choice(keys): _random_json(rng, depth + 1) for _ in range(rng.randrange(5))}


async def group_commands(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    corpus = command_corpus()
    machine = TracedMachine(drive=steady_drive())
    with Mosquitto() as broker:
        async with watching(broker.port) as dash, machine:
            commands = {"enabled": ["rate", "channel_rate", "start", "stop", "zero_tilt",
                                    "tilt_critical", "speed_cal"]}
            cfg = machine.write_config(tmp / "sowgate.toml", commands=commands,
                                       **_mqtt(broker.port))
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: bool(dash.on("status")), 30.0, "daemon online")
                await asyncio.sleep(1.0)
                sent: dict[str, int] = {}
                async with aiomqtt.Client("127.0.0.1", broker.port,
                                          identifier="reliability-fuzzer") as client:
                    for name, payload in corpus:
                        await client.publish(f"{BASE}/cmd/{name}", payload, qos=1)
                        sent[name] = sent.get(name, 0) + 1

                def acks(name: str) -> list[bytes]:
                    return [p for _, p in dash.on(f"cmd/{name}/ack")]

                def all_acked() -> bool:
                    return all(len(acks(n)) >= c for n, c in sent.items())

                with contextlib.suppress(AssertionError):
                    await eventually(all_acked, 20.0, "an ack for every command")
                missing = {n: c - len(acks(n)) for n, c in sent.items() if len(acks(n)) < c}
                total = sum(sent.values())
                res.lost = f"{sum(missing.values())} of {total} commands without an ack"
                res.check(not missing, f"commands without an ack: {missing}")
                strict = [json.loads(p) for p in acks("rate")]
                as_string = b"{\"crop\": \"rapeseed\", \"rate_kg_ha\": \"6\"}"
                index = [p for n, p in corpus if n == "rate"].index(as_string)
                if index < len(strict):
                    res.check(strict[index].get("ok") is False,
                              f"rate_kg_ha \"6\" (a string) accepted: {strict[index]}")
                sessions = daemon.log_text().count("mqtt connected to")
                onlines = len([p for _, p in dash.on("status") if p == b"online"])
                res.recovery = f"{sessions} MQTT session(s) for {total} commands"
                res.check(sessions == 1 and onlines == 1,
                          f"the MQTT session restarted: {sessions} connects, 'online' published "
                          f"{onlines}×")
                res.check(daemon.running, "daemon exited")
                ok = sum(1 for n in sent for p in acks(n) if json.loads(p).get("ok"))
                res.notes.append(f"{total} commands on {len(sent)} names, {ok} accepted")
            finally:
                if daemon.running:
                    await daemon.stop()
                await daemon.close()
            _finish(res, daemon)
    return {"command_fuzz": res}


# ---- config fuzz ----------------------------------------------------------------------------


def _leaves(table: dict[str, Any], prefix: str = "") -> Iterable[tuple[str, Any]]:
    for key, value in table.items():
        if isinstance(value, dict):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _with(base: dict[str, Any], dotted: str, value: Any) -> dict[str, Any]:
    data = json.loads(json.dumps(base))
    *path, last = dotted.split(".")
    node = data
    for part in path:
        node = node[part]
    node[last] = value
    return data


def _wrong_type(value: Any) -> Any:
    if isinstance(value, bool):
        return "perhaps"
    if isinstance(value, (int, float)):
        return "not-a-number"
    if isinstance(value, str):
        return {"nested": [1, 2]}
    if isinstance(value, list):
        return {"not": "a list"}
    return "wrong"


@dataclass
class ConfigCase:
    key: str  # the dotted key the error must name ("" for TOML syntax: a line number)
    what: str
    text: str
    must_reject: bool


def example_config() -> dict[str, Any]:
    """examples/sowgate.toml, its broker moved to a free local port nobody listens on (a run
    of it must never reach a real broker on 1883)."""
    base = tomllib.loads(EXAMPLE_CONFIG.read_text())
    base["mqtt"]["port"] = free_port()
    return base


def config_cases() -> list[ConfigCase]:
    base = example_config()
    cases: list[ConfigCase] = []
    for key, value in _leaves(base):
        cases.append(ConfigCase(key, f"{key} wrong type", tomli_w.dumps(
            _with(base, key, _wrong_type(value))), True))
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            for extreme in (-1e9, 1e9):
                cases.append(ConfigCase(key, f"{key} = {extreme:g}", tomli_w.dumps(
                    _with(base, key, type(value)(extreme))), False))
    for table in base:
        cases.append(ConfigCase(f"{table}.no_such_key", f"unknown key in [{table}]",
                                tomli_w.dumps(_with(base, f"{table}.no_such_key", 1)), True))
    good = tomli_w.dumps(base)
    for what, text in (
        ("unclosed table header", good.replace("[radar]", "[radar", 1)),
        ("string without its quote", good.replace('crop = "rapeseed"', 'crop = "rapeseed', 1)),
        ("key twice", good + "\n[machine]\nrows = 7\n"),
        ("binary junk", good + "\n\x00\x01\xff\n"),
    ):
        cases.append(ConfigCase("", what, text, True))
    return cases


def _check_config_in_process(path: Path) -> tuple[int, str]:
    from gateway.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(["check-config", str(path)])
        except BaseException as exc:  # a crash is the finding
            import traceback

            return -1, "Traceback\n" + "".join(traceback.format_exception(exc))
    return code, err.getvalue()


async def _run_process(
    config: Path, env: dict[str, str] | None = None, timeout: float = 10.0
) -> tuple[int | None, str]:
    import os
    import sys

    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "gateway.cli", "run", "--config", str(config),
        env={**os.environ, **(env or {})}, stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
    )
    try:
        _, err = await asyncio.wait_for(proc.communicate(), timeout)
        return proc.returncode, err.decode(errors="replace")
    except TimeoutError:
        proc.kill()
        _, err = await proc.communicate()
        return None, err.decode(errors="replace")


def _names(case: ConfigCase, text: str) -> bool:
    if case.key:
        return case.key in text
    return "line" in text.lower()


async def group_config(tmp: Path) -> dict[str, RowResult]:
    values = RowResult()
    cases = config_cases()
    rejected = accepted = run_ok = 0
    run_tables: set[str] = set()
    for i, case in enumerate(cases):
        path = tmp / f"case{i}.toml"
        path.write_text(case.text)
        code, err = _check_config_in_process(path)
        values.check("Traceback" not in err, f"{case.what}: check-config crashed: {err[-300:]}")
        if code == 0:
            accepted += 1
            values.check(not case.must_reject, f"{case.what}: accepted by check-config")
            continue
        rejected += 1
        values.check(code == EXIT_CONFIG, f"{case.what}: check-config exit {code}")
        values.check(_names(case, err), f"{case.what}: check-config does not name "
                                        f"{case.key or 'the line'}: {err.strip()[:200]}")
        table = case.key.split(".")[0]
        if table in run_tables:
            continue  # the run path is the same load_config: one process per table suffices
        run_tables.add(table)
        run_code, run_err = await _run_process(path, {"SOWGATE_STATE_DIR": str(tmp / "st")})
        values.check(run_code == EXIT_CONFIG and _names(case, run_err),
                     f"{case.what}: `sowgate run` exit {run_code}: {run_err.strip()[:200]}")
        values.check("Traceback" not in run_err, f"{case.what}: run printed a traceback")
        run_ok += run_code == EXIT_CONFIG
    values.lost = "—"
    values.daemon = (f"check-config: {rejected} rejected, {accepted} accepted; `sowgate run` "
                     f"on one per table: {run_ok} of {len(run_tables)} exit {EXIT_CONFIG}")
    values.tracebacks = str(sum("Traceback" in p for p in values.problems))
    values.notes.append(f"{len(cases)} mutated configs")

    files = RowResult()
    base = example_config()
    missing = tmp / "no-such-dir" / "ca.pem"
    a_file = tmp / "i-am-a-file"
    a_file.write_text("not a directory\n")
    file_cases = [
        ("mqtt.tls.ca_file", _with(base, "mqtt.tls", {"ca_file": str(missing)}), None, True),
        ("mqtt.password_file", _with(_with(base, "mqtt.username", "box"), "mqtt.password_file",
                                     str(missing)), None, True),
        ("state", base, {"SOWGATE_STATE_DIR": str(a_file)}, False),
    ]
    codes = []
    for key, data, env, checked_by_check_config in file_cases:
        path = tmp / f"files-{key}.toml"
        path.write_text(tomli_w.dumps(data))
        run_code, run_err = await _run_process(
            path, env or {"SOWGATE_STATE_DIR": str(tmp / "st")}
        )
        codes.append(f"{key}: {run_code if run_code is not None else 'still running'}")
        files.check(run_code == EXIT_CONFIG and key in run_err,
                    f"{key}: `sowgate run` "
                    + ("still running after 10 s" if run_code is None else f"exit {run_code}")
                    + f", output: {run_err.strip()[-200:] or 'nothing'}")
        files.check("Traceback" not in run_err, f"{key}: run printed a traceback")
        if checked_by_check_config:
            code, err = _check_config_in_process(path)
            files.check(code == EXIT_CONFIG and key in err,
                        f"{key}: check-config exit {code}: {err.strip()[:200] or 'nothing'}")
    files.daemon = "; ".join(codes)
    files.tracebacks = str(sum("traceback" in p for p in files.problems))
    return {"config_fuzz_values": values, "config_fuzz_files": files}


GROUPS: dict[str, Callable[[Path], Awaitable[dict[str, RowResult]]]] = {
    "kills": group_kills,
    "broker": group_broker,
    "disk": group_disk,
    "modbus": group_modbus,
    "serial": group_serial,
    "commands": group_commands,
    "config": group_config,
}


async def run_campaign(tmp: Path, wanted: Iterable[str]) -> dict[str, RowResult]:
    """Run the groups the ``wanted`` rows belong to, concurrently; a result for every row."""
    wanted = set(wanted)
    groups = sorted({ROWS_BY_NAME[name].group for name in wanted})

    async def one(group: str) -> dict[str, RowResult]:
        directory = tmp / group
        directory.mkdir(parents=True, exist_ok=True)
        started = time.monotonic()
        try:
            out = await GROUPS[group](directory)
        except Exception as exc:  # a broken harness shows in every row
            import traceback

            text = "".join(traceback.format_exception(exc))
            out = {}
            for row in ROWS:
                if row.group == group:
                    out[row.name] = RowResult(problems=[f"the run of this row failed: {exc!r}"],
                                              notes=[text[-1500:]])
        took = time.monotonic() - started
        for res in out.values():
            res.notes.append(f"group {group}: {took:.0f} s")
        return out

    results: dict[str, RowResult] = {}
    for part in await asyncio.gather(*(one(g) for g in groups)):
        results.update(part)
    for name in wanted:
        results.setdefault(name, RowResult(problems=["the row produced no result"]))
    return results
