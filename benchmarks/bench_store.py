"""Sustained seed-record throughput of the record store (issue 3 target: ≥ 20 000 records/s).

The store is driven the way the daemon drives it: small appends (one control tick's worth of
seeds), a commit every ``commit_interval_s`` and a WAL sync every second, in WAL mode with
``synchronous=NORMAL``. The reference measured in the same run is a bare ``executemany`` of
the same rows into an equivalent table with no ids handed back, no models built and no outbox
bookkeeping: the store's cost over raw SQLite.
"""

from __future__ import annotations

import sqlite3
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

from gateway.core.records import SeedDrop
from gateway.recording.store import SYNC_INTERVAL_S, RecordStore

RECORDS = 200_000
APPEND_SIZE = 50  # seeds per control tick at ~2 000 seeds/s and 40 Hz
COMMIT_INTERVAL_S = 0.2
TARGET_PER_S = 20_000.0


def _drops(n: int) -> list[SeedDrop]:
    t0 = datetime(2026, 4, 20, tzinfo=UTC)
    return [
        SeedDrop(row=1 + i % 48, utc=t0 + timedelta(milliseconds=i), lat=52.0 + i * 1e-8,
                 lon=13.0, fix="rtk_fixed", speed_kmh=12.0, heading_deg=90.0,
                 heading_source="dual_antenna", spacing_m=0.05)
        for i in range(n)
    ]


def _store_rate(path: Path, chunk: list[SeedDrop]) -> dict[str, float]:
    store = RecordStore(path, "bench", commit_interval_s=COMMIT_INTERVAL_S)
    try:
        t0 = last_commit = last_sync = time.perf_counter()
        written = 0
        commits = 0
        while written < RECORDS:
            store.add_seeds(chunk)
            written += len(chunk)
            now = time.perf_counter()
            if now - last_commit >= COMMIT_INTERVAL_S:
                store.flush()
                commits += 1
                last_commit = now
            if now - last_sync >= SYNC_INTERVAL_S:
                store.sync()
                last_sync = now
        store.flush()
        elapsed = time.perf_counter() - t0
        t1 = time.perf_counter()
        read = 0
        while batch := store.pending_seeds(500, after_id=read):
            read = batch[-1].id
        outbox_s = time.perf_counter() - t1
        assert read == RECORDS
        ok = store.integrity_check() == "ok"
    finally:
        store.close()
    return {"store_per_s": written / elapsed, "outbox_read_per_s": RECORDS / outbox_s,
            "commits": float(commits), "integrity_ok": float(ok)}


def _raw_rate(path: Path, chunk: list[SeedDrop]) -> float:
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=NORMAL")
    db.execute("CREATE TABLE s (id INTEGER PRIMARY KEY, utc TEXT, row INT, lat REAL, lon REAL)")
    rows = [(d.utc.isoformat(), d.row, d.lat, d.lon) for d in chunk]
    t0 = last = time.perf_counter()
    written = 0
    db.execute("BEGIN")
    while written < RECORDS:
        db.executemany("INSERT INTO s (utc, row, lat, lon) VALUES (?,?,?,?)", rows)
        written += len(rows)
        if time.perf_counter() - last >= COMMIT_INTERVAL_S:
            db.execute("COMMIT")
            db.execute("BEGIN")
            last = time.perf_counter()
    db.execute("COMMIT")
    elapsed = time.perf_counter() - t0
    db.close()
    return written / elapsed


def run() -> dict[str, object]:
    chunk = _drops(APPEND_SIZE)
    with tempfile.TemporaryDirectory() as tmp:
        fig: dict[str, object] = dict(_store_rate(Path(tmp) / "store.sqlite3", chunk))
        fig["raw_sqlite_per_s"] = _raw_rate(Path(tmp) / "raw.sqlite3", chunk)
    rate = float(fig["store_per_s"])  # type: ignore[arg-type]
    raw = float(fig["raw_sqlite_per_s"])  # type: ignore[arg-type]
    fig["markdown"] = (
        "### Record store throughput\n\n"
        f"{RECORDS} seed records appended {APPEND_SIZE} at a time, commit every "
        f"{COMMIT_INTERVAL_S:g} s, WAL sync every {SYNC_INTERVAL_S:g} s (SQLite WAL, "
        "synchronous=NORMAL). Reference: bare executemany of the same rows, same run.\n\n"
        "| store (records/s) | outbox read (records/s) | reference raw SQLite | store / raw "
        "| integrity |\n|---|---|---|---|---|\n"
        f"| {rate:,.0f} | {float(fig['outbox_read_per_s']):,.0f} | {raw:,.0f} "  # type: ignore[arg-type]
        f"| {rate / raw:.2f} | {'ok' if fig['integrity_ok'] else 'FAILED'} |\n\n"
        f"Target ≥ {TARGET_PER_S:,.0f} records/s: {'met' if rate >= TARGET_PER_S else 'NOT met'}.\n"
    )
    return fig


if __name__ == "__main__":
    print(run()["markdown"])
