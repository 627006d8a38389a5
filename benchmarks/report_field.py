"""A synthetic day of a 48-row planter, written straight into a record store (for bench_report).

The field: passes of ``PASS_M`` metres up and down, 36 m apart, at a speed that wanders
between 10 and 14 km/h; every row drops seeds at a target spacing of 20 cm with 3 % doubles,
3 % skips and a 12 % spread on the singles (row 7 skips a quarter on every third pass). A few
percent of the seeds have an RTK-float fix or an extrapolated position, and each float stretch
raises and clears ``gnss.not_rtk_fixed``.

It is written with ``executemany`` into the store's own schema (the store makes the file and
the schema first), with one ``seed_spans`` row per batch as the store's own append writes
them, so ``sowgate report`` and ``sowgate export`` read it as they read a daemon's store. The
truth here is only the bench's input: the bench measures time and memory, not accuracy.
"""

from __future__ import annotations

import math
import sqlite3
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from gateway.core.records import utc_to_us
from gateway.recording.store import RecordStore

ROWS = 48
WIDTH_M = 36.0
TARGET_SPACING_M = 0.2
PASS_M = 1000.0
T0 = datetime(2026, 5, 4, 6, 0, tzinfo=UTC)
LAT0, LON0 = 52.30, 13.10
M_PER_DEG_LAT = 111_200.0
BATCH = 1000  # rows per seed_spans entry (the daemon writes ~1 050 a flush at this rate)
MACHINE_ID = "bench-48row"
# bump when the generated field changes, so a cached store is rebuilt
GENERATOR_VERSION = 3  # 3: the terrain and re-positioning columns are filled too


def _pass_rows(k: int, rng: np.random.Generator, t_start_s: float) -> tuple[np.ndarray, ...]:
    """Seeds of pass ``k`` (all rows), sorted by time: (t_s, row, x_m, y_m, speed, spacing)."""
    speed_kmh = rng.uniform(10.0, 14.0)
    v = speed_kmh / 3.6
    ts, rows, xs, ys, sps = [], [], [], [], []
    n_guess = int(PASS_M / TARGET_SPACING_M * 1.1) + 20
    for row in range(1, ROWS + 1):
        kind = rng.random(n_guess)
        sp = rng.normal(TARGET_SPACING_M, 0.12 * TARGET_SPACING_M, n_guess)
        sp = np.where(kind < 0.03, rng.uniform(0.0, 0.08, n_guess), sp)
        # every third pass row 7's disc half-blocked: a quarter of its spacings are skips
        skip = 0.75 if k % 3 == 1 and row == 7 else 0.97
        sp = np.where(kind > skip, rng.uniform(0.33, 0.5, n_guess), sp)
        sp = np.abs(sp)
        pos = np.cumsum(sp)
        pos -= pos[0]
        keep = pos <= PASS_M
        pos, sp = pos[keep], sp[keep]
        spacing = sp.copy()
        spacing[0] = np.nan  # the first seed of a pass has no spacing (raised at the headland)
        lateral = WIDTH_M / ROWS * (row - 0.5) + k * WIDTH_M
        along = pos if k % 2 == 0 else PASS_M - pos
        ts.append(t_start_s + pos / v)
        rows.append(np.full(pos.size, row))
        xs.append(np.full(pos.size, lateral))
        ys.append(along)
        sps.append(spacing)
    t = np.concatenate(ts)
    order = np.argsort(t, kind="stable")
    speed = np.full(t.size, speed_kmh) + rng.normal(0, 0.2, t.size)
    return (t[order], np.concatenate(rows)[order], np.concatenate(xs)[order],
            np.concatenate(ys)[order], speed, np.concatenate(sps)[order])


def _rows(n: int) -> Iterator[tuple[list[tuple[Any, ...]], list[tuple[str, int, bool]]]]:
    """Batches of store rows (id, utc_us, row, lat, lon, fix, speed, heading, source,
    extrapolated, method, spacing, and the terrain columns) and the fix changes within them,
    ``n`` rows in all."""
    rng = np.random.default_rng(20260504)
    t_s = 0.0
    k = 0
    next_id = 1
    cos_lat = math.cos(math.radians(LAT0))
    fixed = True
    while next_id <= n:
        t, row, x, y, speed, spacing = _pass_rows(k, rng, t_s)
        m = min(t.size, n - next_id + 1)
        float_from = rng.uniform(0, t.size) if rng.random() < 0.7 else math.inf
        float_len = rng.uniform(2000, 30000)
        lat = LAT0 + y / M_PER_DEG_LAT
        lon = LON0 + x / (M_PER_DEG_LAT * cos_lat)
        us = utc_to_us(T0) + (t * 1e6).astype(np.int64)
        extrap = rng.random(t.size) < 0.004
        heading = 0.0 if k % 2 == 0 else 180.0
        roll = rng.normal(0.0, 1.5, t.size)
        for lo in range(0, m, BATCH):
            hi = min(m, lo + BATCH)
            idx = np.arange(lo, hi)
            in_float = (idx >= float_from) & (idx < float_from + float_len)
            changes: list[tuple[str, int, bool]] = []
            if in_float.any() == fixed:  # entering or leaving a float stretch in this batch
                fixed = not fixed
                at = int(idx[in_float][0] if not fixed else idx[0])
                changes.append(("gnss.not_rtk_fixed", int(us[at]), not fixed))
            batch = [
                (next_id + i - lo, int(us[i]), int(row[i]), float(lat[i]), float(lon[i]),
                 "rtk_float" if in_float[i - lo] else "rtk_fixed", float(speed[i]), heading,
                 "dual_antenna", bool(extrap[i]), "interpolated",
                 None if math.isnan(spacing[i]) else float(spacing[i]),
                 # what a terrain-compensated record carries (issue 16): the row holds them
                 "dual_antenna", float(roll[i]), None, 412.0, 0.7, -2.1)
                for i in range(lo, hi)
            ]
            next_id += len(batch)
            yield batch, changes
        t_s = float(t[-1]) + 25.0  # the turn at the headland
        k += 1


def build_store(path: Path, n: int) -> Path:
    """Write ``n`` seed records (and the GNSS alarms of the float stretches) at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    for p in (tmp, Path(f"{tmp}-wal"), Path(f"{tmp}-shm")):
        p.unlink(missing_ok=True)
    RecordStore(tmp, MACHINE_ID).close()  # the schema, as the daemon makes it
    db = sqlite3.connect(tmp, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=OFF")
    db.execute("BEGIN")
    written = 0
    for batch, changes in _rows(n):
        db.executemany(
            "INSERT INTO seeds (id, utc_us, row, lat, lon, fix, speed_kmh, heading_deg, "
            "heading_source, extrapolated, method, spacing_m, attitude, roll_deg, pitch_deg, "
            "delay_ms, offset_east_m, offset_north_m) VALUES "
            "(?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
            batch,
        )
        db.execute(
            "INSERT INTO seed_spans (first_id, last_id, min_utc_us, max_utc_us) VALUES (?,?,?,?)",
            (batch[0][0], batch[-1][0], min(r[1] for r in batch), max(r[1] for r in batch)),
        )
        for code, us, active in changes:
            db.execute(
                "INSERT INTO alarms (utc_us, code, active, severity, message) VALUES (?,?,?,?,?)",
                (us, code, int(active), "warning",
                 "GNSS fix is not RTK fixed" if active else "RTK fixed again"),
            )
        written += len(batch)
        if written % 500_000 < BATCH:
            db.execute("COMMIT")
            db.execute("BEGIN")
    db.execute("COMMIT")
    db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    db.close()
    tmp.replace(path)
    return path


if __name__ == "__main__":
    import sys
    import time

    t0 = time.perf_counter()
    build_store(Path(sys.argv[2]), int(sys.argv[1]))
    print(f"{time.perf_counter() - t0:.1f} s")
