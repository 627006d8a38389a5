"""Rows about the receiver's time (issue 20 item 4), on one daemon sowing at 8 km/h: a UTC
leap second, two epochs stamped 2 h ahead, dates 1024 weeks early, then the receiver's time
stepping back an hour for good. The simulated UM982 stamps its sentences and heading log as
the faulty receiver would (``Um982Emulator.shift_stamps``, ``week_rollover``,
``insert_leap_second``); each fault's seeds are then looked up in the store one by one, by
the stamp and the place the ground truth says they should have."""

from __future__ import annotations

import asyncio
import bisect
import math
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pymap3d

from gateway.core.records import SeedRecord
from gateway.recording.store import RecordStore
from simulator.machine import ORIGIN_LAT, ORIGIN_LON
from tests.helpers import eventually
from tests.mosquitto import Mosquitto
from tests.reliability.harness import (
    MACHINE_ID,
    DaemonProcess,
    RowResult,
    TracedMachine,
    dashboard,
    edge_mono,
    finish_row,
    late_epochs_note,
    mqtt_overrides,
    sowing_drive,
)
from tests.reliability.rows import (
    GNSS_STEP_EXTRAPOLATED_S,
    GNSS_TIME_POSITION_M,
    GNSS_TIME_WINDOW_S,
)

MIDNIGHT = datetime(2027, 1, 1, tzinfo=UTC)  # a leap second is inserted before it
LEAP_AFTER_S = 45.0  # drive seconds from the start to that midnight
SOW_S = 110.0
ORIGIN_ALT_M = 100.0  # the emulator's default origin height
# A record's stamp vs the truth's landing instant: the model's fall time and the seed line's
# arrival stamps on a loaded host put it tens of ms off (up to 92 ms seen with two busy loops
# beside the run); the faults judged here are 1 s to 2 h. The simulator's own late writes
# (its timer starved, up to 0.19 s seen) are not the daemon's: the truth is the seed as sent.
STAMP_MATCH_S = 0.15
ALARM_WAIT_S = 4.0  # for the alarm to reach the broker after the fault (hold 1 s, 1 Hz state)


def _sleep_until(t_mono: float) -> Any:
    return asyncio.sleep(max(0.0, t_mono - time.monotonic()))


async def group_gnss_time(tmp: Path) -> dict[str, RowResult]:
    utc_start = MIDNIGHT - timedelta(seconds=LEAP_AFTER_S)
    machine = TracedMachine(drive=sowing_drive(SOW_S), with_gnss=True, with_seed_tubes=True,
                            gnss_utc_start=utc_start)
    out = {name: RowResult() for name in (
        "gnss_leap_second", "gnss_two_epochs_2h_ahead", "gnss_week_rollover",
        "gnss_time_step_back_1h",
    )}
    windows: dict[str, tuple[float, float]] = {}
    step_at = math.inf
    with Mosquitto() as broker:
        async with dashboard(broker.port) as dash, machine:
            gnss, tubes = machine.gnss, machine.seed_tubes
            gnss.insert_leap_second(MIDNIGHT)
            t_leap = gnss.t0_mono + LEAP_AFTER_S
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            db = tmp / "state" / "records.sqlite3"
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
                out["gnss_leap_second"].check(
                    time.monotonic() < t_leap - 3.0,
                    "the daemon was not sowing before the leap second (started too slowly)",
                )
                windows["gnss_leap_second"] = (t_leap - 2.0, t_leap + GNSS_TIME_WINDOW_S - 2.0)
                await _sleep_until(t_leap + GNSS_TIME_WINDOW_S)

                t0 = time.monotonic()
                gnss.shift_stamps(timedelta(hours=2), epochs=2)
                windows["gnss_two_epochs_2h_ahead"] = (t0, t0 + GNSS_TIME_WINDOW_S)
                await _sleep_until(t0 + GNSS_TIME_WINDOW_S + 1.0)

                t0 = time.monotonic()
                gnss.week_rollover(True)
                windows["gnss_week_rollover"] = (t0, t0 + GNSS_TIME_WINDOW_S)
                await _sleep_until(t0 + GNSS_TIME_WINDOW_S)
                gnss.week_rollover(False)
                await asyncio.sleep(1.0)

                step_at = time.monotonic()
                gnss.shift_stamps(timedelta(hours=-1))
                windows["gnss_time_step_back_1h"] = (step_at, step_at + GNSS_TIME_WINDOW_S)
                await _sleep_until(step_at + GNSS_TIME_WINDOW_S + ALARM_WAIT_S)
                for res in out.values():
                    res.check(daemon.running, "daemon exited")
                code = await daemon.stop()
                out["gnss_time_step_back_1h"].check(code == 0, f"graceful stop exited {code}")
            finally:
                await daemon.close()
            for res in out.values():
                finish_row(res, daemon)
            records = _records_by_row(db)

            def stamp_of(t_land_sim: float) -> datetime:
                """What a correct daemon stamps a seed that landed at drive time t: UTC, with
                the leap second, and in the receiver's new time after the step."""
                true = utc_start + timedelta(seconds=t_land_sim)
                if MIDNIGHT <= true < MIDNIGHT + timedelta(seconds=1):
                    return MIDNIGHT - timedelta(microseconds=1)
                if true >= MIDNIGHT:
                    true -= timedelta(seconds=1)
                if gnss.t0_mono + t_land_sim >= step_at:
                    true -= timedelta(hours=1)
                return true

            alarms = {
                "gnss_leap_second": "gnss.leap_second",
                "gnss_two_epochs_2h_ahead": "gnss.time_outlier",
                "gnss_week_rollover": "gnss.week_rollover",
                "gnss_time_step_back_1h": "gnss.time_step",
            }
            for name, (w0, w1) in windows.items():
                res = out[name]
                skip = (
                    (step_at - 0.2, step_at + GNSS_STEP_EXTRAPOLATED_S)
                    if name == "gnss_time_step_back_1h" else None
                )
                _judge(res, tubes, records, stamp_of, (w0, w1), skip)
                if res.problems:
                    res.problems[-1] += late_epochs_note(gnss, (w0, w1))
                seen = dash.alarms_between(w0, w1 + ALARM_WAIT_S)
                res.check(alarms[name] in seen,
                          f"{alarms[name]} not published (seen: {sorted(seen)})")
                res.recovery = f"`{alarms[name]}` on MQTT" if alarms[name] in seen else "—"
            future = [r for rows in records.values() for r in rows
                      if r.utc > stamp_of(SOW_S + 200.0) + timedelta(hours=1)]
            out["gnss_two_epochs_2h_ahead"].check(
                not future, f"{len(future)} records stamped in the future (first {future[:1]})"
            )
    return out


def _records_by_row(db: Path) -> dict[int, list[SeedRecord]]:
    rows: dict[int, list[SeedRecord]] = {}
    if not db.exists():
        return rows
    with RecordStore.open_readonly(db, MACHINE_ID) as store:
        for r in store.query_seeds():
            rows.setdefault(r.row, []).append(r)
    for recs in rows.values():
        recs.sort(key=lambda r: r.utc)
    return rows


def _judge(
    res: RowResult,
    tubes: Any,
    records: dict[int, list[SeedRecord]],
    stamp_of: Callable[[float], datetime],
    window: tuple[float, float],
    skip: tuple[float, float] | None,
) -> None:
    """Every seed that landed in ``window`` (host monotonic): a record of its row stamped when
    it landed, where it landed, not extrapolated (but in ``skip``)."""
    seeds = [s for s in tubes.truth if window[0] <= edge_mono(tubes, s.t_land) <= window[1]]
    missing = far = extrapolated = 0
    misses: list[str] = []
    stamped: list[datetime] = []  # the expected stamps of the seeds judged
    worst = 0.0
    leap_end = MIDNIGHT - timedelta(microseconds=1)
    for s in seeds:
        if skip is not None and skip[0] <= edge_mono(tubes, s.t_land) <= skip[1]:
            continue
        expected = stamp_of(s.t_land)
        recs = records.get(s.row, [])
        near = _stamped_near(recs, expected)
        # a seed landing within the model's few ms of the leap second's edges may be stamped
        # on either side of it
        if min(abs((stamp_of(s.t_land + d) - expected).total_seconds())
               for d in (-STAMP_MATCH_S, STAMP_MATCH_S)) > 0.5:
            near += _stamped_near(recs, leap_end)
        if not near:
            missing += 1
            if len(misses) < 4:
                closest = min(recs, key=lambda r: abs((r.utc - expected).total_seconds()),
                              default=None)
                misses.append(f"row {s.row} landed {expected:%H:%M:%S.%f}: nearest record "
                              + ("none" if closest is None else
                                 f"{(closest.utc - expected).total_seconds():+.3f} s, "
                                 f"{_error_m(closest, s):.2f} m"))
            continue
        # neighbours in the row are stamped ~0.1 s apart: the seed's record is the closest
        # in space (that no record is lost is counted below)
        best = min(near, key=lambda r: _error_m(r, s))
        stamped.append(expected)
        err = _error_m(best, s)
        worst = max(worst, err)
        far += err > GNSS_TIME_POSITION_M
        extrapolated += best.extrapolated or best.fix == "none"
    judged = len(seeds) - (0 if skip is None else sum(
        1 for s in seeds if skip[0] <= edge_mono(tubes, s.t_land) <= skip[1]))
    res.lost = f"{missing} of {judged} seeds of the window without a record at their stamp"
    res.check(judged > 20, f"only {judged} seeds landed in the window")
    res.check(missing == 0, f"{missing} of {judged} seeds have no record stamped when they "
                            "landed (lost, or stamped in another time): " + "; ".join(misses))
    res.check(extrapolated == 0, f"{extrapolated} of {judged} records extrapolated or without fix")
    res.check(far == 0, f"{far} of {judged} records more than {GNSS_TIME_POSITION_M:g} m from "
                        f"where the seed landed (worst {worst:.2f} m)")
    if stamped:
        lo, hi = min(stamped), max(stamped)
        in_range = sum(1 for recs in records.values() for r in recs if lo <= r.utc <= hi)
        res.check(in_range >= 0.98 * len(stamped),
                  f"{in_range} records stamped in the window for {len(stamped)} seeds")
    res.duty = "—"
    res.notes.append(f"{judged} seeds judged, worst position error {worst * 100:.1f} cm")
    late = [s.late_s for s in seeds if s.late_s]
    if late:  # the truth of these is the seed as sent (simulator.seed_tubes), not the plan
        res.notes.append(f"{len(late)} edges written late by the simulator (up to "
                         f"{max(late) * 1000:.0f} ms)")


def _stamped_near(recs: list[SeedRecord], stamp: datetime) -> list[SeedRecord]:
    """The records (sorted by stamp) stamped within STAMP_MATCH_S of ``stamp``."""
    i = bisect.bisect_left([r.utc for r in recs], stamp - timedelta(seconds=STAMP_MATCH_S))
    out = []
    for r in recs[i:]:
        if r.utc > stamp + timedelta(seconds=STAMP_MATCH_S):
            break
        out.append(r)
    return out


def _error_m(record: SeedRecord, seed: Any) -> float:
    east, north, _ = pymap3d.geodetic2enu(record.lat, record.lon, ORIGIN_ALT_M, ORIGIN_LAT,
                                          ORIGIN_LON, ORIGIN_ALT_M)
    return math.hypot(float(east) - seed.east, float(north) - seed.north)
