"""Daemon runs in the record store: when each start and stop happened, and with what settings.

Why. An alarm event is stored when the alarm is raised and when it clears. An alarm still
active when the daemon stops is never cleared in the store, so without a stop marker a view
could only draw it to the end of whatever it showed: a ``pwm.unavailable`` of a faulty start
was drawn across every later, clean run. Each run is one row here (start, stop, clean or
not); the views (``sowgate report``, ``sowgate export --what alarms``) end such an alarm at
its run's stop.

A clean stop (SIGTERM, Ctrl-C, a failed task: anything that reaches the daemon's ordered stop)
writes its stop time. An unclean one (SIGKILL, a power cut) writes nothing: the next start
closes that run at its last seed or alarm, the last moment anything is known of it, and marks
it unclean. A reader does the same for the newest run if it has no stop (it may still be
running; then its last record is about now anyway).

The run also keeps the settings its records depend on (``RUN_SETTINGS``: the target spacing,
rows, working width, crop), so ``sowgate export`` without ``--config`` judges spacings against
the same target as the daemon and ``sowgate report`` did.

A marker that cannot be written (disk full, read-only card) is logged and skipped: it must
never stop the daemon, and the seeds and alarms are what matter.
"""

from __future__ import annotations

import json
import logging
import sqlite3
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from gateway.core.records import us_to_utc

log = logging.getLogger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    start_us INTEGER NOT NULL,
    stop_us INTEGER,                    -- NULL: running, or stopped uncleanly (see below)
    clean INTEGER NOT NULL DEFAULT 0,   -- 1: the daemon wrote its stop itself
    settings TEXT NOT NULL DEFAULT '{}' -- JSON of RUN_SETTINGS
);
"""

# What a run keeps of its config: what reading its records back depends on.
RUN_SETTINGS = ("target_spacing_m", "rows", "working_width_m", "crop", "machine_id")


@dataclass(frozen=True)
class Run:
    id: int
    start_us: int
    stop_us: int | None  # None: the newest run, still running or never closed
    clean: bool
    settings: Mapping[str, Any]


def _has_runs(db: sqlite3.Connection) -> bool:
    return db.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'runs'"
    ).fetchone() is not None


def last_activity_us(db: sqlite3.Connection, start_us: int, before_us: int | None) -> int:
    """The last seed or alarm time from ``start_us`` on (before ``before_us``): where a run
    that wrote no stop of its own ended, as far as anything is known. ``start_us`` if none."""
    hi = 2**63 - 1 if before_us is None else before_us
    times = [start_us]
    for sql in (
        "SELECT MAX(max_utc_us) FROM seed_spans WHERE max_utc_us >= ? AND max_utc_us < ?",
        "SELECT MAX(utc_us) FROM alarms WHERE utc_us >= ? AND utc_us < ?",
    ):
        try:
            row = db.execute(sql, (start_us, hi)).fetchone()
        except sqlite3.OperationalError:  # an older store without that table
            continue
        if row and row[0] is not None:
            times.append(int(row[0]))
    return max(times)


def start_run(db: sqlite3.Connection, now_us: int, settings: Mapping[str, Any]) -> int | None:
    """Close the runs that never wrote a stop (unclean) and open a new one: its id, or None
    when the marker could not be written (logged)."""
    try:
        open_runs = db.execute(
            "SELECT id, start_us FROM runs WHERE stop_us IS NULL ORDER BY start_us"
        ).fetchall()
        starts = [s for (s,) in db.execute("SELECT start_us FROM runs ORDER BY start_us")]
        for run_id, start_us in open_runs:
            later = [s for s in starts if s > start_us]
            before = min(later) if later else now_us
            end = last_activity_us(db, start_us, before)
            db.execute("UPDATE runs SET stop_us = ?, clean = 0 WHERE id = ?", (end, run_id))
            log.warning(
                "record store: the run started %s ended without a stop (power cut or kill); "
                "it is taken as ended at its last record", _iso(start_us),
            )
        kept = {k: settings[k] for k in RUN_SETTINGS if k in settings}
        cur = db.execute(
            "INSERT INTO runs (start_us, settings) VALUES (?, ?)", (now_us, json.dumps(kept))
        )
    except sqlite3.Error as exc:
        log.warning("record store: daemon start not marked: %s", exc)
        return None
    return cur.lastrowid


def stop_run(db: sqlite3.Connection, run_id: int, now_us: int) -> None:
    try:
        db.execute("UPDATE runs SET stop_us = ?, clean = 1 WHERE id = ?", (now_us, run_id))
    except sqlite3.Error as exc:
        log.warning("record store: daemon stop not marked: %s", exc)


def read_runs(db: sqlite3.Connection) -> list[Run]:
    """Every run, oldest first; a run without a stop that is not the newest gets the end the
    next start would give it (its last record before that start). [] for an older store."""
    if not _has_runs(db):
        return []
    rows = db.execute(
        "SELECT id, start_us, stop_us, clean, settings FROM runs ORDER BY start_us, id"
    ).fetchall()
    out: list[Run] = []
    for k, (run_id, start_us, stop_us, clean, text) in enumerate(rows):
        if stop_us is None and k + 1 < len(rows):
            stop_us = last_activity_us(db, start_us, rows[k + 1][1])
        try:
            settings = json.loads(text)
        except ValueError:
            settings = {}
        out.append(Run(int(run_id), int(start_us), None if stop_us is None else int(stop_us),
                       bool(clean), settings if isinstance(settings, dict) else {}))
    return out


def stored_setting(
    runs: Sequence[Run], key: str, since_us: int | None = None, until_us: int | None = None
) -> Any:
    """``key`` of the newest run overlapping the window that kept it (None if none did)."""
    for run in reversed(runs):
        if until_us is not None and run.start_us >= until_us:
            continue
        if since_us is not None and run.stop_us is not None and run.stop_us < since_us:
            continue
        if run.settings.get(key) is not None:
            return run.settings[key]
    return None


def _iso(us: int) -> str:
    return us_to_utc(us).isoformat()
