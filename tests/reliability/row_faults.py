"""Rows about the seed rows themselves (issue 20 items 2 and 3): one row silent, every row
silent, one row's sensor chattering, on one daemon sowing at 8 km/h, one fault after the other.

Judged from the outside: what reached the broker (alarms, the state's ``row_monitor``) and
what the store holds per row against the seeds the simulated tubes really sent.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections import Counter
from pathlib import Path

from gateway.recording.store import RecordStore
from tests.helpers import eventually
from tests.mosquitto import Mosquitto, Subscriber
from tests.reliability.harness import (
    MACHINE_ID,
    DaemonProcess,
    RowResult,
    TracedMachine,
    dashboard,
    edge_mono,
    finish_row,
    mqtt_overrides,
    sowing_drive,
)
from tests.reliability.rows import (
    CHATTER_LINES_PER_S,
    CHATTER_ROW,
    CHATTER_S,
    ROW_ALARM_WITHIN_S,
    ROW_SILENT_S,
    SILENT_ROW,
)

ROWS_SOW_S = 110.0
SETTLE_S = 8.0  # sowing this long before a fault: the monitor has judged every row once


def _rows_alarmed(dash: Subscriber, t0: float, t1: float) -> set[str]:
    return {c for c in dash.alarms_between(t0, t1)
            if c.startswith("row.") or c == "seed_sensors.all_rows_silent"}


def _first_alarm(dash: Subscriber, code: str, t0: float) -> float | None:
    """Seconds from ``t0`` to the first alarm event raising ``code``."""
    for t, payload in dash.timed("alarms"):
        if t >= t0:
            with contextlib.suppress(ValueError, KeyError, TypeError):
                event = json.loads(payload)
                if event["code"] == code and event["active"]:
                    return t - t0
    return None


def _stored_per_row(db: Path) -> Counter[int]:
    with RecordStore.open_readonly(db, MACHINE_ID) as store:
        return Counter(r.row for r in store.query_seeds())


def _judge_alarm(res: RowResult, dash: Subscriber, code: str, t0: float, t1: float,
                 allowed: set[str]) -> None:
    took = _first_alarm(dash, code, t0)
    res.recovery = (f"`{code}` on MQTT {took:.1f} s after the fault began" if took is not None
                    else f"`{code}` never on MQTT")
    res.check(took is not None and took <= ROW_ALARM_WITHIN_S,
              f"{code} not raised on MQTT within {ROW_ALARM_WITHIN_S:g} s of the fault "
              f"(took {took})")
    others = _rows_alarmed(dash, t0, t1) - allowed - {code}
    res.check(not others, f"other row alarms raised: {', '.join(sorted(others))}")


async def group_rows(tmp: Path) -> dict[str, RowResult]:
    one, every, chatter = RowResult(), RowResult(), RowResult()
    counted = 0
    n_open = 0
    chatter_window = (0.0, 0.0)
    machine = TracedMachine(drive=sowing_drive(ROWS_SOW_S), with_gnss=True, with_seed_tubes=True)
    with Mosquitto() as broker:
        async with dashboard(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            rows = machine.base_settings.machine.rows
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            db = tmp / "state" / "records.sqlite3"
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)  # seeds sent before the port was open were not read
                await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
                await asyncio.sleep(SETTLE_S)
                t_start = time.monotonic()
                quiet = _rows_alarmed(dash, 0.0, t_start)
                for res in (one, every, chatter):
                    res.check(not quiet, "row alarms while every row sowed: "
                                         + ", ".join(sorted(quiet)))

                # ---- one row silent
                tb0 = daemon.tracebacks()
                t0 = time.monotonic()
                tubes.silent_rows.add(SILENT_ROW)
                await asyncio.sleep(ROW_SILENT_S)
                tubes.silent_rows.clear()
                t1 = time.monotonic()
                code = f"row.{SILENT_ROW}.blocked"
                # recovering, the row's window passes through "skipping"
                _judge_alarm(one, dash, code, t0, t1, {f"row.{SILENT_ROW}.skipping"})
                try:
                    cleared = await eventually(
                        lambda: code not in _active_now(dash), 30.0, f"{code} cleared")
                    one.notes.append(f"cleared {cleared:.1f} s after the row sowed again")
                except AssertionError as exc:
                    one.problems.append(str(exc))
                one.check(daemon.running, "daemon exited")
                finish_row(one, daemon, tb0)
                await asyncio.sleep(6.0)

                # ---- every row silent
                tb0 = daemon.tracebacks()
                t0 = time.monotonic()
                tubes.silent_rows.update(range(1, rows + 1))
                await asyncio.sleep(ROW_SILENT_S)
                tubes.silent_rows.clear()
                t1 = time.monotonic()
                _judge_alarm(every, dash, "seed_sensors.all_rows_silent", t0, t1, set())
                try:
                    cleared = await eventually(
                        lambda: "seed_sensors.all_rows_silent" not in _active_now(dash), 30.0,
                        "seed_sensors.all_rows_silent cleared")
                    every.notes.append(f"cleared {cleared:.1f} s after the rows sowed again")
                except AssertionError as exc:
                    every.problems.append(str(exc))
                every.check(daemon.running, "daemon exited")
                finish_row(every, daemon, tb0)
                await asyncio.sleep(6.0)

                # ---- one row chattering
                tb0 = daemon.tracebacks()
                t0 = time.monotonic()
                per_write = CHATTER_LINES_PER_S // 20
                written = 0
                line = f"D,{CHATTER_ROW}\r\n".encode()
                while time.monotonic() - t0 < CHATTER_S:
                    written += tubes.inject(line * per_write) // len(line)
                    await asyncio.sleep(0.05)
                t1 = time.monotonic()
                chatter_window = (t0, t1)
                chatter.duty = f"{written / CHATTER_S:.0f} lines/s injected for {CHATTER_S:g} s"
                _judge_alarm(chatter, dash, f"row.{CHATTER_ROW}.chattering", t0, t1 + 2.0, set())
                seen = dash.alarms_between(t0, t1 + 3.0)
                chatter.check("seed_sensors.implausible_rate" in seen,
                              "seed_sensors.implausible_rate not on MQTT")
                await asyncio.sleep(3.0)
                counted = _published_implausible(dash, CHATTER_ROW)
                chatter.check(counted >= 0.9 * written,
                              f"state.row_monitor.rows.{CHATTER_ROW}.implausible_edges is "
                              f"{counted}, of {written} chatter lines")
                chatter.check(daemon.running, "daemon exited")
                finish_row(chatter, daemon, tb0)

                await eventually(lambda: machine.pose().speed_kmh == 0.0, 120.0,
                                 "end of the pass")
                await asyncio.sleep(2.0)
                code_stop = await daemon.stop()
                chatter.check(code_stop == 0, f"graceful stop exited {code_stop}")
            finally:
                await daemon.close()
            sent = Counter(s.row for s in tubes.truth[n_open:])
            sent_all = Counter(s.row for s in tubes.truth)  # at most this many real seeds
            stored = _stored_per_row(db)
            lost = {r: sent[r] - stored[r] for r in range(1, rows + 1) if stored[r] < sent[r]}
            # real seeds of the row sent while it surely chattered (from 0.5 s in): none of
            # them can be stored, so more stored than the rest is chatter stored as seeds
            c0, c1 = chatter_window
            during = sum(1 for s in tubes.truth[n_open:] if s.row == CHATTER_ROW
                         and c0 + 0.5 <= edge_mono(tubes, s.t_edge) <= c1)
            phantom = stored[CHATTER_ROW] - (sent_all[CHATTER_ROW] - during)
            chatter.lost = (f"{max(0, phantom)} chatter edges stored as seeds; "
                            f"{sent[CHATTER_ROW] - stored[CHATTER_ROW]} real seeds of row "
                            f"{CHATTER_ROW} dropped with the chatter ({during} sent during it)")
            chatter.check(during > 0, "no real seed of the row was sent during the chatter")
            chatter.check(phantom <= 0, f"{phantom} of the chatter's edges stored as seeds")
            for res in (one, every):
                other = {r: n for r, n in lost.items() if r != CHATTER_ROW}
                res.lost = f"{sum(other.values())} of {sum(sent.values())} seeds sent not stored"
                res.check(not other, f"seeds sent and not stored, per row: {other}")
            chatter.notes.append(f"{counted} edges counted implausible (published per row)")
    return {"seed_row_silent_15s": one, "seed_rows_all_silent_15s": every,
            "seed_row_chatter": chatter}


def _active_now(dash: Subscriber) -> set[str]:
    """Codes active in the latest state message."""
    states = dash.on("state")
    if not states:
        return set()
    with contextlib.suppress(ValueError, KeyError, TypeError):
        return {a["code"] for a in json.loads(states[-1])["alarms"]}
    return set()


def _published_implausible(dash: Subscriber, row: int) -> int:
    states = dash.on("state")
    for payload in reversed(states):
        with contextlib.suppress(ValueError, KeyError, TypeError):
            return int(json.loads(payload)["row_monitor"]["rows"][str(row)]["implausible_edges"])
    return 0
