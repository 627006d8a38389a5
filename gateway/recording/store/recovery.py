"""Opening the store for writing, whatever the card left behind.

A store that does not pass its check (a zero-length file, not a database, a truncated file, a
page overwritten, an error while opening it) is never a reason to stop the daemon: rate
control does not depend on it. It is moved aside, kept under a name with the time
(``records.sqlite3.bad-20260420T080000Z``, its ``-wal`` and ``-shm`` with it), named in the
log and in the ``store.replaced`` alarm, and a new store continues the ids (see ``ids``).
The same happens while running when SQLite reports the file corrupt (``RecordStore``).

The check at open is ``PRAGMA quick_check`` (every page's B-tree structure, not the indexes'
contents), up to ``QUICK_CHECK_MAX_BYTES``; a larger store would hold the start (and with it
the first metering) for seconds on an SD card, so it gets the cheap checks only (schema, ids),
and a corrupt page found later is handled while running.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from gateway.recording.id_ranges import IdRanges
from gateway.recording.store.schema import (
    SEED_COLUMNS,
    TABLES,
    load_delivered,
    max_id,
    prepare_for_writing,
    readable_seed_columns,
)

log = logging.getLogger(__name__)

QUICK_CHECK_MAX_BYTES = 64 * 1024 * 1024  # ~1.5 s of a card reading 40 MB/s
SALVAGE_CHUNK = 500  # rows read from a damaged store at a time (an unreadable chunk is skipped)
SALVAGE_MAX_ERRORS = 1000  # then the rest of a table is given up as unreadable
_ALARM_COLUMNS = "id, utc_us, code, active, severity, message"
_SIDE_FILES = ("-wal", "-shm")


@dataclass(frozen=True)
class ReplacedStore:
    """A store that failed its check and was moved aside."""

    reason: str
    moved_to: Path | None  # None: it could not be moved (then it was left where it was)
    max_ids: dict[str, int]  # what could still be read of its ids (0 where nothing could)
    salvaged: int = 0  # undelivered records copied from it into the new store

    def describe(self) -> str:
        where = f"kept as {self.moved_to}" if self.moved_to else "could not be moved aside"
        copied = f"; {self.salvaged} undelivered records copied" if self.salvaged else ""
        return (f"record store failed its check ({self.reason}); {where}{copied}; a new "
                "store continues the ids")


def is_corruption(exc: BaseException) -> bool:
    """SQLite says the file is damaged (not: full, read-only, busy)."""
    code = getattr(exc, "sqlite_errorcode", None)
    if code is not None:
        return (code & 0xFF) in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
    text = str(exc).lower()
    return "malformed" in text or "not a database" in text


def check_store(path: Path, *, quick_check: bool = True) -> str | None:
    """Why the store at ``path`` cannot be used, or None if it can (or does not exist yet)."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return None
    if size == 0:
        return "zero-length file"
    try:
        db = sqlite3.connect(path, isolation_level=None)
    except sqlite3.Error as exc:
        return f"cannot open: {exc}"
    try:
        prepare_for_writing(db, path)
        if quick_check and size <= QUICK_CHECK_MAX_BYTES:
            result = [str(r[0]) for r in db.execute("PRAGMA quick_check(5)")]
            if result != ["ok"]:
                return "quick_check: " + "; ".join(result)
        for table in TABLES:
            max_id(db, table)
    except sqlite3.Error as exc:
        return str(exc)
    finally:
        with contextlib.suppress(sqlite3.Error):
            db.close()
    return None


def salvage_max_ids(path: Path) -> dict[str, int]:
    """The highest ids a damaged store still shows (0 where it shows nothing)."""
    out = dict.fromkeys(TABLES, 0)
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error:
        return out
    try:
        for table in TABLES:
            with contextlib.suppress(sqlite3.Error):
                out[table] = max_id(db, table)
    finally:
        db.close()
    return out


def move_aside(path: Path, reason: str, now: datetime | None = None) -> ReplacedStore:
    """Rename the store (and its WAL and shared memory) out of the way, keeping them."""
    ids = salvage_max_ids(path)
    stamp = (now or datetime.now(UTC)).strftime("%Y%m%dT%H%M%SZ")
    target = path.with_name(f"{path.name}.bad-{stamp}")
    n = 1
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.bad-{stamp}-{n}")
    try:
        path.rename(target)
    except OSError as exc:
        log.error("record store %s failed its check (%s) and cannot be moved aside (%s)",
                  path, reason, exc)
        return ReplacedStore(reason, None, ids)
    for suffix in _SIDE_FILES:
        side = path.with_name(path.name + suffix)
        with contextlib.suppress(FileNotFoundError, OSError):
            side.rename(target.with_name(target.name + suffix))
    replaced = ReplacedStore(reason, target, ids)
    log.error("%s", replaced.describe())
    return replaced


def salvage_undelivered(old: Path, db: sqlite3.Connection) -> int:
    """Copy what can still be read of the records the broker had not acknowledged from the
    store moved aside into the new one ``db``, under their ids, so they are still delivered;
    the ids below them that are not copied count as delivered in the new store (nothing there
    to wait for). Returns the records copied. Never raises: a damaged store gives what it can.
    """
    try:
        src = sqlite3.connect(f"file:{old}?mode=ro", uri=True)
    except sqlite3.Error:
        return 0
    copied: dict[str, list[int]] = {t: [] for t in TABLES}
    try:
        for table in TABLES:
            _salvage_table(src, db, table, copied[table])
        for table, ids in copied.items():
            if ids:  # the ids below the last copied that were not copied: nothing to wait for
                keep = IdRanges()
                keep.add_ids(ids)
                _in_transaction(db, "INSERT INTO delivered (tbl, lo, hi) VALUES (?, ?, ?)",
                                [(table, lo, hi) for lo, hi in keep.gaps(0, max(ids))])
    except sqlite3.Error as exc:
        log.error("copying the undelivered records from %s stopped: %s", old, exc)
    finally:
        src.close()
    n = sum(len(ids) for ids in copied.values())
    if n:
        log.warning("%d records not yet delivered copied from %s into the new store", n, old)
    return n


def _salvage_table(
    src: sqlite3.Connection, db: sqlite3.Connection, table: str, copied: list[int]
) -> None:
    try:
        cols = readable_seed_columns(src) if table == "seeds" else _ALARM_COLUMNS
    except sqlite3.Error:
        return
    try:
        acked = IdRanges(load_delivered(src, table))
    except sqlite3.Error:  # not known: copy all that reads (a resend repeats the same record)
        acked = IdRanges()
    try:
        top = max_id(src, table)
    except sqlite3.Error:  # the last pages are gone: read on until nothing more comes
        top = 2**62
    into = SEED_COLUMNS if table == "seeds" else _ALARM_COLUMNS
    errors = 0
    for lo, hi in acked.gaps(0, top):
        at = lo
        while at <= hi and errors < SALVAGE_MAX_ERRORS:
            try:
                rows = src.execute(
                    f"SELECT {cols} FROM {table} WHERE id >= ? AND id <= ? ORDER BY id LIMIT ?",
                    (at, hi, SALVAGE_CHUNK),
                ).fetchall()
            except sqlite3.Error:  # an unreadable part: skip it
                errors += 1
                at += SALVAGE_CHUNK
                continue
            if not rows:
                if top == 2**62 and errors:  # past the end or in the damage: keep probing
                    errors += 1
                    at += SALVAGE_CHUNK
                    continue
                break
            marks = ",".join("?" * len(rows[0]))
            _in_transaction(db, f"INSERT OR IGNORE INTO {table} ({into}) VALUES ({marks})",
                            rows)
            if table == "seeds":
                times = [int(r[1]) for r in rows]
                _in_transaction(
                    db, "INSERT OR IGNORE INTO seed_spans (first_id, last_id, min_utc_us, "
                    "max_utc_us) VALUES (?, ?, ?, ?)",
                    [(rows[0][0], rows[-1][0], min(times), max(times))],
                )
            copied.extend(int(r[0]) for r in rows)
            at = int(rows[-1][0]) + 1


def _in_transaction(db: sqlite3.Connection, sql: str, rows: list[Any]) -> None:
    db.execute("BEGIN")
    try:
        db.executemany(sql, rows)
        db.execute("COMMIT")
    except sqlite3.Error:
        db.execute("ROLLBACK")
        raise
