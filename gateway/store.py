"""The durable record store: every seed record and alarm, and the MQTT outbox over them.

A seed record exists for the rest of the system only once it is committed here: the outbox
(``pending_seeds``/``pending_alarms``) never returns a row the store has not committed, so
nothing is published that a crash could take back, and ids are never handed out twice.

Durability. SQLite runs in WAL mode with ``synchronous=NORMAL``. In that mode a commit appends
to the WAL without fsync; an application crash (SIGKILL, OOM) loses nothing committed, and the
database is never corrupted by a crash or a power cut (WAL frames carry checksums; a torn tail
is ignored on recovery). What a *power cut* can lose is what was committed since the WAL was
last fsynced. ``run()`` bounds that window: it commits every ``commit_interval_s`` (≤ 1 s) and
forces a passive checkpoint, which fsyncs the WAL, every ``SYNC_INTERVAL_S`` (1 s). So a power
cut loses at most about the last second of records, which is the contract, while the
fsync cost stays at ~2 per second whatever the seed rate (``synchronous=FULL`` would fsync on
every commit, blocking the event loop five times a second on a slow SD card).

Ids. ``INTEGER PRIMARY KEY AUTOINCREMENT`` keeps the high-water mark in ``sqlite_sequence``, so
an id is never reused, even after pruning deleted the newest delivered rows.

Space. Nothing undelivered is ever deleted; ``prune`` only removes delivered rows older than the
retention. When the undelivered backlog passes ``backlog_alarm_records`` the ``on_backlog``
callback says so (once per crossing), so an operator learns the link is down long before the
card fills.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from itertools import chain as _chain
from pathlib import Path
from typing import Any

from gateway.errors import GatewayError
from gateway.records import (
    AlarmEvent,
    SeedDrop,
    SeedRecord,
    SeedRow,
    drop_row,
    us_to_utc,
    utc_to_us,
)

log = logging.getLogger(__name__)

SYNC_INTERVAL_S = 1.0  # the power-cut loss window (see module docstring)
PRUNE_INTERVAL_S = 3600.0
# Rows one pruning step deletes before the event loop gets a turn: a day of a 48-row planter
# is millions of rows, and deleting them in one statement would stall the control loop (and
# the watchdog) for seconds on an SD card.
PRUNE_CHUNK_ROWS = 5000
QUERY_CHUNK_ROWS = 5000  # rows fetched per step by query_seeds, so exports stream
MAX_OUTBOX_LIMIT = 10_000  # one outbox read never materialises more than this many records


SCHEMA = """
CREATE TABLE IF NOT EXISTS seeds (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    utc_us INTEGER NOT NULL,
    row INTEGER NOT NULL,
    lat REAL NOT NULL,
    lon REAL NOT NULL,
    fix TEXT NOT NULL,
    speed_kmh REAL NOT NULL,
    heading_deg REAL,
    heading_source TEXT NOT NULL,
    extrapolated INTEGER NOT NULL,
    method TEXT NOT NULL,
    spacing_m REAL,
    delivered INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS seeds_pending ON seeds(id) WHERE delivered = 0;
CREATE INDEX IF NOT EXISTS seeds_utc ON seeds(utc_us);
CREATE TABLE IF NOT EXISTS alarms (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    utc_us INTEGER NOT NULL,
    code TEXT NOT NULL,
    active INTEGER NOT NULL,
    severity TEXT NOT NULL,
    message TEXT NOT NULL,
    delivered INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS alarms_pending ON alarms(id) WHERE delivered = 0;
"""

_SEED_COLUMNS = (
    "id, utc_us, row, lat, lon, fix, speed_kmh, heading_deg, heading_source, extrapolated, "
    "method, spacing_m"
)

# One SeedRecord as JSON, field order and spelling as pydantic writes it.
_SEED_JSON = (
    "json_object('row', row, 'utc', printf('%s.%06dZ', "
    "strftime('%Y-%m-%dT%H:%M:%S', utc_us / 1000000, 'unixepoch'), utc_us % 1000000), "
    "'lat', lat, 'lon', lon, 'fix', fix, 'speed_kmh', speed_kmh, 'heading_deg', heading_deg, "
    "'heading_source', heading_source, "
    "'extrapolated', json(CASE WHEN extrapolated THEN 'true' ELSE 'false' END), "
    "'method', method, 'spacing_m', spacing_m, 'id', id, 'machine_id', ?)"
)

BacklogCallback = Callable[[int, bool], None]


class StoreError(GatewayError):
    """The record store cannot be opened or written (disk full, read-only, corrupt file)."""


_INSERT_CHUNKS = (128, 32, 8, 1)


@functools.cache
def _insert_sql(rows: int) -> str:
    return (
        "INSERT INTO seeds (utc_us, row, lat, lon, fix, speed_kmh, heading_deg, "
        "heading_source, extrapolated, method, spacing_m) VALUES "
        + ",".join(["(?,?,?,?,?,?,?,?,?,?,?)"] * rows)
    )


def _id_ranges(ids: Sequence[int]) -> list[tuple[int, int]]:
    """Contiguous runs, so marking a 500-record batch is one UPDATE, not 500."""
    out: list[tuple[int, int]] = []
    for i in sorted(set(ids)):
        if out and i == out[-1][1] + 1:
            out[-1] = (out[-1][0], i)
        else:
            out.append((i, i))
    return out


def _fast_record(fields: dict[str, Any]) -> SeedRecord:
    """Build a SeedRecord from already-validated fields without re-validating.

    ``model_construct`` costs more than validation itself (~8 µs vs ~5 µs); on the hot path
    (every seed, twice) we fill the instance the way pydantic does. A test checks the result
    equals a validated record, so a pydantic upgrade that changes internals fails loudly.
    """
    record = SeedRecord.__new__(SeedRecord)
    object.__setattr__(record, "__dict__", fields)
    object.__setattr__(record, "__pydantic_fields_set__", set(fields))
    object.__setattr__(record, "__pydantic_extra__", None)
    object.__setattr__(record, "__pydantic_private__", None)
    return record


@dataclass(frozen=True)
class OutboxBatch:
    """Ids and the ready-to-publish ``SeedBatch`` JSON for them (the MQTT hot path)."""

    ids: list[int]
    payload: bytes


class RecordStore:
    """SQLite store of seed records and alarms; also the MQTT outbox. Use from one thread."""

    def __init__(
        self,
        path: str | Path,
        machine_id: str,
        *,
        commit_interval_s: float = 0.2,
        retention_days: float = 30.0,
        backlog_alarm_records: int = 200_000,
        on_backlog: BacklogCallback | None = None,
        readonly: bool = False,
    ) -> None:
        self.path = Path(path)
        self.machine_id = machine_id
        self.commit_interval_s = commit_interval_s
        self.retention = timedelta(days=retention_days)
        self.backlog_alarm_records = backlog_alarm_records
        self.on_backlog = on_backlog
        self.readonly = readonly
        self._commit_listeners: list[Callable[[], None]] = []
        self._backlog_over = False
        try:
            if readonly:
                uri = f"file:{self.path}?mode=ro"
                self._db = sqlite3.connect(uri, uri=True, isolation_level=None)
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._db = sqlite3.connect(self.path, isolation_level=None)
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=NORMAL")
                self._db.executescript(SCHEMA)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open record store {self.path}: {exc}") from exc
        self._in_tx = False
        # Highest ids the outbox may see: rows above them are not committed yet.
        self._visible_seed_id = self._max_id("seeds")
        self._visible_alarm_id = self._max_id("alarms")
        self._last_seed_id = self._visible_seed_id
        self._pending_seeds = self._scalar("SELECT COUNT(*) FROM seeds WHERE delivered = 0")
        self._pending_alarms = self._scalar("SELECT COUNT(*) FROM alarms WHERE delivered = 0")
        self._uncommitted_seeds = 0
        self._uncommitted_alarms = 0
        self._last_sync = time.monotonic()
        # run() checkpoints on its own connection in a worker thread, so the fsync of a
        # checkpoint never stalls the event loop (and with it the control loop).
        self._ckpt_lock = threading.Lock()
        self._ckpt_db: sqlite3.Connection | None = None
        # the last periodic commit's failure, None once one succeeds (read by the alarms)
        self.commit_error: str | None = None

    @classmethod
    def open_readonly(cls, path: str | Path, machine_id: str) -> RecordStore:
        """For ``sowgate export`` next to a running daemon: WAL lets it read without blocking."""
        if not Path(path).exists():
            raise StoreError(f"no record store at {path}")
        return cls(path, machine_id, readonly=True)

    # -- helpers -----------------------------------------------------------------------------

    def _scalar(self, sql: str, *args: Any) -> int:
        row = self._db.execute(sql, args).fetchone()
        return int(row[0]) if row and row[0] is not None else 0

    def _max_id(self, table: str) -> int:
        return self._scalar(f"SELECT MAX(id) FROM {table}")

    def _begin(self) -> None:
        if self.readonly:
            raise StoreError("record store opened read-only")
        if not self._in_tx:
            self._db.execute("BEGIN")
            self._in_tx = True

    def add_commit_listener(self, listener: Callable[[], None]) -> None:
        """Called after each commit that made new records visible (the outbox wakes up)."""
        self._commit_listeners.append(listener)

    # -- writing -----------------------------------------------------------------------------

    def add_seeds(self, drops: Sequence[SeedDrop]) -> list[SeedRecord]:
        """Store drops and give them ids; they reach the outbox at the next ``flush``."""
        ids = self.append_seeds(drops)
        mid = self.machine_id
        return [
            _fast_record({**d.__dict__, "id": i, "machine_id": mid})
            for i, d in zip(ids, drops, strict=True)
        ]

    def append_seeds(self, drops: Sequence[SeedDrop]) -> range:
        """Like ``add_seeds`` but hands back only the ids, in the order of ``drops``.

        For callers that already hold the drops and need no record objects (the daemon's
        recorder): building a ``SeedRecord`` per seed is a fifth of the store's cost.
        """
        if not drops:
            return range(0)
        return self.append_rows([drop_row(d) for d in drops])

    def append_rows(self, rows: Sequence[SeedRow]) -> range:
        """``append_seeds`` for records already in column form (``Landing.stored``).

        The positioner hands the daemon's recorder rows, not ``SeedDrop`` objects; the values
        are the ones a ``SeedDrop`` would hold (the positioner checks them against its schema).
        """
        if not rows:
            return range(0)
        self._begin()
        # A savepoint so a failed insert (disk full) leaves no half batch behind ids we
        # never returned.
        self._db.execute("SAVEPOINT add_seeds")
        try:
            # Multi-row INSERTs of a few fixed sizes (so the prepared statements are reused):
            # one statement per chunk instead of one per row; ~25 % less than executemany.
            execute = self._db.execute
            i, n = 0, len(rows)
            for size in _INSERT_CHUNKS:
                while n - i >= size:
                    execute(_insert_sql(size), list(_chain(*rows[i:i + size])))
                    i += size
            last = self._scalar("SELECT last_insert_rowid()")
            self._db.execute("RELEASE add_seeds")
        except sqlite3.Error as exc:
            self._db.execute("ROLLBACK TO add_seeds")
            self._db.execute("RELEASE add_seeds")
            raise StoreError(f"cannot write seed records: {exc}") from exc
        # One writer, one transaction: AUTOINCREMENT hands out a contiguous run ending at last.
        first = last - len(rows) + 1
        self._last_seed_id = last
        self._uncommitted_seeds += len(rows)
        return range(first, last + 1)

    def add_alarm(self, event: AlarmEvent) -> AlarmEvent:
        """Store an alarm event and commit at once: alarms are rare and must not wait."""
        self._begin()
        try:
            cur = self._db.execute(
                "INSERT INTO alarms (utc_us, code, active, severity, message) VALUES (?,?,?,?,?)",
                (
                    utc_to_us(event.utc), event.code, int(event.active), event.severity,
                    event.message,
                ),
            )
        except sqlite3.Error as exc:
            raise StoreError(f"cannot write alarm: {exc}") from exc
        alarm_id = int(cur.lastrowid or 0)
        self._uncommitted_alarms += 1
        self.flush()
        return event.model_copy(update={"id": alarm_id, "machine_id": self.machine_id})

    def flush(self) -> None:
        """Commit: from now on the new records survive a crash and the outbox can see them."""
        if not self._in_tx:
            return
        try:
            self._db.execute("COMMIT")
        except sqlite3.Error as exc:
            raise StoreError(f"cannot commit records: {exc}") from exc
        self._in_tx = False
        new = self._uncommitted_seeds + self._uncommitted_alarms
        self._visible_seed_id = self._last_seed_id
        self._visible_alarm_id = self._max_id("alarms")
        self._pending_seeds += self._uncommitted_seeds
        self._pending_alarms += self._uncommitted_alarms
        self._uncommitted_seeds = self._uncommitted_alarms = 0
        self._check_backlog()
        if new:
            for listener in self._commit_listeners:
                listener()

    def sync(self) -> None:
        """fsync the WAL (via a passive checkpoint): bounds what a power cut can take back."""
        self.flush()
        self._checkpoint()
        self._last_sync = time.monotonic()

    def _checkpoint(self) -> None:
        """Passive checkpoint on a second connection; safe to call from a worker thread."""
        with self._ckpt_lock:
            db = self._ckpt_db
            if db is None:
                db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
                self._ckpt_db = db
            db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()

    # -- outbox ------------------------------------------------------------------------------

    def pending_seeds(self, limit: int, after_id: int = 0) -> list[SeedRecord]:
        """Committed, undelivered seed records with ``id > after_id``, oldest first."""
        limit = max(0, min(limit, MAX_OUTBOX_LIMIT))
        rows = self._db.execute(
            f"SELECT {_SEED_COLUMNS} FROM seeds "
            "WHERE delivered = 0 AND id > ? AND id <= ? ORDER BY id LIMIT ?",
            (after_id, self._visible_seed_id, limit),
        ).fetchall()
        return [self._seed(r) for r in rows]

    def count_pending_seeds(self, after_id: int = 0, cap: int = MAX_OUTBOX_LIMIT) -> int:
        """How many committed undelivered records follow ``after_id``, counting at most cap."""
        return self._scalar(
            "SELECT COUNT(*) FROM (SELECT 1 FROM seeds WHERE delivered = 0 AND id > ? "
            "AND id <= ? LIMIT ?)",
            after_id, self._visible_seed_id, max(0, cap),
        )

    def pending_seed_batch(self, limit: int, after_id: int = 0) -> OutboxBatch | None:
        """Like ``pending_seeds`` but straight to ``SeedBatch`` JSON, built by SQLite in C.

        The outbox reads every record once more than it writes it; building the JSON in the
        query instead of through models is what lets the link keep up (see bench_mqtt). The
        JSON equals ``SeedBatch(...).model_dump_json()`` value for value (tested), except
        that floats carry 15 significant digits (1e-13° of latitude: nanometres).
        """
        limit = max(0, min(limit, MAX_OUTBOX_LIMIT))
        rows = self._db.execute(
            f"SELECT id, {_SEED_JSON} FROM seeds "
            "WHERE delivered = 0 AND id > ? AND id <= ? ORDER BY id LIMIT ?",
            (self.machine_id, after_id, self._visible_seed_id, limit),
        ).fetchall()
        if not rows:
            return None
        head = '{"machine_id":' + json.dumps(self.machine_id) + ',"records":['
        payload = head + ",".join(r[1] for r in rows) + "]}"
        return OutboxBatch([r[0] for r in rows], payload.encode())

    def pending_alarms(self, limit: int, after_id: int = 0) -> list[AlarmEvent]:
        limit = max(0, min(limit, MAX_OUTBOX_LIMIT))
        rows = self._db.execute(
            "SELECT id, utc_us, code, active, severity, message FROM alarms "
            "WHERE delivered = 0 AND id > ? AND id <= ? ORDER BY id LIMIT ?",
            (after_id, self._visible_alarm_id, limit),
        ).fetchall()
        return [
            AlarmEvent(
                id=r[0], machine_id=self.machine_id, utc=us_to_utc(r[1]), code=r[2],
                active=bool(r[3]), severity=r[4], message=r[5],
            )
            for r in rows
        ]

    def _mark(self, table: str, ids: Sequence[int]) -> int:
        if not ids:
            return 0
        self._begin()
        changed = 0
        for lo, hi in _id_ranges(ids):
            cur = self._db.execute(
                f"UPDATE {table} SET delivered = 1 "
                "WHERE id BETWEEN ? AND ? AND delivered = 0",
                (lo, hi),
            )
            changed += cur.rowcount
        return changed

    def mark_seeds_delivered(self, ids: Sequence[int]) -> None:
        """Called on PUBACK. Committed with the next flush; a crash before it means a resend."""
        self._pending_seeds -= self._mark("seeds", ids)
        self._check_backlog()

    def mark_alarms_delivered(self, ids: Sequence[int]) -> None:
        self._pending_alarms -= self._mark("alarms", ids)

    def backlog(self) -> int:
        """Committed records (seeds and alarms) not yet acknowledged by the broker."""
        return self._pending_seeds + self._pending_alarms

    def _check_backlog(self) -> None:
        n = self.backlog()
        over = n > self.backlog_alarm_records
        if over != self._backlog_over:
            self._backlog_over = over
            if self.on_backlog is not None:
                self.on_backlog(n, over)

    # -- export and housekeeping ---------------------------------------------------------------

    def _seed(self, r: tuple[Any, ...]) -> SeedRecord:
        # Rows were validated as SeedDrops on the way in; skip re-validation on the hot path.
        return _fast_record({
            "row": r[2], "utc": us_to_utc(r[1]), "lat": r[3], "lon": r[4], "fix": r[5],
            "speed_kmh": r[6], "heading_deg": r[7], "heading_source": r[8],
            "extrapolated": bool(r[9]), "method": r[10], "spacing_m": r[11], "id": r[0],
            "machine_id": self.machine_id,
        })

    def query_seeds(
        self,
        since: datetime | None = None,
        until: datetime | None = None,
        rows: Sequence[int] | None = None,
    ) -> Iterator[SeedRecord]:
        """Committed records (delivered or not) in id order, ``since <= utc < until``."""
        sql = f"SELECT {_SEED_COLUMNS} FROM seeds WHERE id > ? AND id <= ?"
        args: list[Any] = []
        if since is not None:
            sql += " AND utc_us >= ?"
            args.append(utc_to_us(since))
        if until is not None:
            sql += " AND utc_us < ?"
            args.append(utc_to_us(until))
        if rows is not None:
            wanted = sorted({int(r) for r in rows})
            if not wanted:
                return
            sql += f" AND row IN ({','.join('?' * len(wanted))})"
            args.extend(wanted)
        sql += " ORDER BY id LIMIT ?"
        ceiling = self._visible_seed_id if not self.readonly else self._max_id("seeds")
        after = 0
        while True:
            chunk = self._db.execute(sql, (after, ceiling, *args, QUERY_CHUNK_ROWS)).fetchall()
            for r in chunk:
                yield self._seed(r)
            if len(chunk) < QUERY_CHUNK_ROWS:
                return
            after = chunk[-1][0]

    def prune(self, now: datetime) -> int:
        """Delete delivered records older than the retention; undelivered ones are kept."""
        deleted, more = self.prune_step(now)
        while more:
            step, more = self.prune_step(now)
            deleted += step
        return deleted

    def prune_step(self, now: datetime) -> tuple[int, bool]:
        """``prune`` for at most ``PRUNE_CHUNK_ROWS`` rows a table, committed.

        Returns the rows deleted and whether a table may have more to prune.
        """
        cutoff = utc_to_us(now - self.retention)
        self._begin()
        deleted, more = 0, False
        for table in ("seeds", "alarms"):
            cur = self._db.execute(
                f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} "
                "WHERE delivered = 1 AND utc_us < ? ORDER BY id LIMIT ?)",
                (cutoff, PRUNE_CHUNK_ROWS),
            )
            deleted += cur.rowcount
            more = more or cur.rowcount >= PRUNE_CHUNK_ROWS
        self.flush()
        return deleted, more

    async def _prune_in_steps(self, now: datetime) -> int:
        """``prune`` that lets the event loop (and with it control) run between chunks."""
        deleted, more = self.prune_step(now)
        while more:
            await asyncio.sleep(0)
            step, more = self.prune_step(now)
            deleted += step
        return deleted

    def integrity_check(self) -> str:
        return str(self._db.execute("PRAGMA integrity_check").fetchone()[0])

    def close(self) -> None:
        if not self.readonly:
            try:
                self.flush()
            except StoreError:
                log.exception("record store: final commit failed")
        with self._ckpt_lock:
            if self._ckpt_db is not None:
                self._ckpt_db.close()
                self._ckpt_db = None
        self._db.close()

    def __enter__(self) -> RecordStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    async def run(self, utcnow: Callable[[], datetime] = lambda: datetime.now(UTC)) -> None:
        """Commit every ``commit_interval_s``, sync every second, prune at start and hourly.

        Pruning at start too: a box switched off every evening would otherwise never run an
        hour and never prune. The backlog is checked at start as well, so a restart with a
        large unsent backlog and the broker down still raises the backlog alarm.
        """
        last_prune = time.monotonic() - PRUNE_INTERVAL_S
        self._check_backlog()
        # Checkpoints happen here, off the event loop; SQLite's automatic ones would run
        # inside a COMMIT on the loop thread.
        self._db.execute("PRAGMA wal_autocheckpoint=0")
        try:
            while True:
                await asyncio.sleep(self.commit_interval_s)
                try:
                    self.flush()
                    self.commit_error = None
                    now = time.monotonic()
                    if now - self._last_sync >= SYNC_INTERVAL_S:
                        self._last_sync = now
                        await asyncio.to_thread(self._checkpoint)
                    if now - last_prune >= PRUNE_INTERVAL_S:
                        last_prune = now
                        await self._prune_in_steps(utcnow())
                except (StoreError, sqlite3.Error) as exc:
                    # Keep the daemon running (control must go on); the records stay in the
                    # open transaction and are retried at the next tick.
                    if self.commit_error is None:
                        log.exception("record store: commit failed, retrying")
                    self.commit_error = str(exc)
        finally:
            self._db.execute("PRAGMA wal_autocheckpoint=1000")
            try:  # a stop commits here, as soon as the recorder has stored its last seeds
                self.flush()
            except StoreError:
                log.exception("record store: commit on stop failed")
