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
every commit, blocking the event loop on a slow SD card). With nothing written, ``run()``
sleeps until a write opens a transaction: an idle box wakes for no store tick at all.

Ids. ``INTEGER PRIMARY KEY AUTOINCREMENT`` keeps the high-water mark in ``sqlite_sequence``, so
an id is never reused, even after pruning deleted the newest delivered rows.

Delivery. What the broker acknowledged is kept as id ranges in ``delivered`` (see
``gateway.recording.id_ranges``), not as a flag per row: marking a 500-record batch is one range
merged in memory and a few rows rewritten at the next commit, where an UPDATE of 500 rows rewrote
pages written a moment before (half the WAL traffic at 2 100 seeds/s). A store written by an
older sowgate, with a ``delivered`` column, is converted when it is opened for writing.

The outbox reads recent records from memory: ``append_rows`` keeps the last
``TAIL_MAX_ROWS`` rows it wrote, so the live link renders them straight to JSON and SQLite is
read only for a backlog older than that (after an outage or a restart). The tail is a cache
of committed rows and nothing else: rows whose commit failed are dropped from it.

Time. There is no index entry per seed (it cost every insert a second B-tree write): each
appended batch, about two a second, records its ids and its time span in ``seed_spans``, and
time-range queries and pruning read the ids from there. A store with the older per-seed index
is converted when opened for writing (one span over its rows).

Full disk. A write or a commit that fails (SQLITE_FULL: a failed COMMIT may roll the whole
transaction back) loses nothing: the store keeps every row of the open transaction until its
COMMIT succeeds, and after a failure holds them, and every row that follows, in memory under
the ids already handed out (``records_held``), up to ``max_held_records``; past it new rows
are counted in ``records_lost`` and get no id. It retries with capped backoff and writes the
held rows with their ids once there is room, so the stored ids stay contiguous. Alarm events
are held likewise; ``add_alarm`` then returns id 0 and the MQTT link publishes the event live.

Space. Nothing undelivered is ever deleted; ``prune`` only removes delivered rows older than the
retention. When the undelivered backlog passes ``backlog_alarm_records`` the ``on_backlog``
callback says so (once per crossing), so an operator learns the link is down long before the
card fills.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from itertools import chain as _chain
from operator import itemgetter
from pathlib import Path
from typing import Any

from drivers.backoff import Backoff
from drivers.ticks import sleep_to_next_tick
from gateway.core.errors import GatewayError
from gateway.core.records import (
    AlarmEvent,
    SeedDrop,
    SeedRecord,
    SeedRow,
    drop_row,
    seed_batch_json,
    us_to_utc,
    utc_to_us,
)
from gateway.recording.id_ranges import IdRanges

log = logging.getLogger(__name__)

SYNC_INTERVAL_S = 1.0  # the power-cut loss window (see module docstring)
PRUNE_INTERVAL_S = 3600.0
# Rows one pruning step deletes before the event loop gets a turn: a day of a 48-row planter
# is millions of rows, and deleting them in one statement would stall the control loop (and
# the watchdog) for seconds on an SD card.
PRUNE_CHUNK_ROWS = 5000
QUERY_CHUNK_ROWS = 5000  # rows fetched per step by query_seed_rows, so exports stream
# Rows the outbox can read from memory: about 5 s of a 48-row planter at 16 km/h (~3 MB). A
# link further behind than that reads SQLite, as after an outage.
TAIL_MAX_ROWS = 10_000
MAX_OUTBOX_LIMIT = 10_000  # one outbox read never materialises more than this many records
# Seed records kept in memory while the store cannot write them (disk full, card gone
# read-only): the rows of the failed commit and every row after them, in order, under the ids
# they were given, until a retry writes them. A held record costs about 310 bytes of memory
# (308 measured by benchmarks/bench_held_records.py), so the cap is about 74 MB, and at
# 2 000 seeds/s it rides out a full disk for 240 000 / 2 000 = 120 s. Past it, new records
# are counted in ``records_lost`` (state payload, records.lost alarm), never dropped
# silently; they take no ids, so the stored ids stay contiguous.
MAX_HELD_RECORDS = 240_000
MAX_HELD_ALARMS = 1_000  # alarm events held likewise (alarms are rare); past it: alarms_lost
# A write that failed is retried with capped exponential backoff: a full disk is not asked
# twice a second (each attempt writes up to DRAIN_CHUNK_ROWS rows before it can fail), and a
# disk that has room again is used within RETRY_MAX_S.
RETRY_INITIAL_S = 0.5
RETRY_MAX_S = 5.0
# Held rows written per transaction once space is back: ~0.1 s of the event loop a step.
DRAIN_CHUNK_ROWS = 20_000


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
    attitude TEXT NOT NULL DEFAULT 'none',
    roll_deg REAL,
    pitch_deg REAL,
    delay_ms REAL,
    offset_east_m REAL,
    offset_north_m REAL
);
-- the ids and time span of each batch of seeds appended (one a flush, ~2 a second): what
-- time-range queries and pruning look up, instead of an index entry for every seed
CREATE TABLE IF NOT EXISTS seed_spans (
    first_id INTEGER PRIMARY KEY,
    last_id INTEGER NOT NULL,
    min_utc_us INTEGER NOT NULL,
    max_utc_us INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS seed_spans_max_utc ON seed_spans(max_utc_us);
CREATE TABLE IF NOT EXISTS alarms (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    utc_us INTEGER NOT NULL,
    code TEXT NOT NULL,
    active INTEGER NOT NULL,
    severity TEXT NOT NULL,
    message TEXT NOT NULL
);
-- ids the broker acknowledged, per table, as closed ranges (see gateway.recording.id_ranges)
CREATE TABLE IF NOT EXISTS delivered (
    tbl TEXT NOT NULL,
    lo INTEGER NOT NULL,
    hi INTEGER NOT NULL,
    PRIMARY KEY (tbl, lo)
) WITHOUT ROWID;
"""

_TABLES = ("seeds", "alarms")

# Columns added after the first stores were written (terrain compensation and what
# re-positioning needs, issue 16): an older store gets them with ALTER TABLE at open (its old
# rows read attitude 'none' and NULL for the rest), and a read-only open of an older store
# reads those defaults in their place. (name, declaration, value for older rows)
_ADDED_SEED_COLUMNS = (
    ("attitude", "TEXT NOT NULL DEFAULT 'none'", "'none'"),
    ("roll_deg", "REAL", "NULL"),
    ("pitch_deg", "REAL", "NULL"),
    ("delay_ms", "REAL", "NULL"),
    ("offset_east_m", "REAL", "NULL"),
    ("offset_north_m", "REAL", "NULL"),
)
_ROW_COLUMNS = (
    "utc_us, row, lat, lon, fix, speed_kmh, heading_deg, heading_source, extrapolated, "
    "method, spacing_m, " + ", ".join(name for name, _, _ in _ADDED_SEED_COLUMNS)
)
_SEED_COLUMNS = "id, " + _ROW_COLUMNS
_ROW_PARAMS = "(" + ",".join("?" * (_ROW_COLUMNS.count(",") + 1)) + ")"
_ROW_PARAMS_WITH_ID = "(" + ",".join("?" * (_ROW_COLUMNS.count(",") + 2)) + ")"
# what query_seed_rows yields, one tuple a seed: the columns above, in that order
STORED_SEED_COLUMNS = tuple(_SEED_COLUMNS.replace(" ", "").split(","))
StoredSeedRow = tuple[Any, ...]

BacklogCallback = Callable[[int, bool], None]


class StoreError(GatewayError):
    """The record store cannot be opened or written (disk full, read-only, corrupt file)."""


# rows per INSERT: 512 rows is 8 704 parameters (SQLite allows 32 766 since 3.32), and a
# 512-row statement costs a quarter less per row than a 128-row one (the recorder stores
# ~1 050 rows a flush)
_INSERT_CHUNKS = (512, 128, 32, 8, 1)
_UTC_US = itemgetter(0)  # of a SeedRow


@functools.cache
def _insert_sql(rows: int) -> str:
    return f"INSERT INTO seeds ({_ROW_COLUMNS}) VALUES " + ",".join([_ROW_PARAMS] * rows)


@functools.cache
def _insert_with_ids_sql(rows: int) -> str:
    """For held rows written back: they keep the ids they were given when they came."""
    return f"INSERT INTO seeds ({_SEED_COLUMNS}) VALUES " + ",".join(
        [_ROW_PARAMS_WITH_ID] * rows
    )


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


@dataclass(frozen=True, slots=True)
class StoreState:
    """What the store holds and lost, for the daemon's state (``state()``): the state
    payload's ``records_held`` and ``records_lost`` come from here."""

    failing: bool  # a write failed; new rows are held in memory until a retry succeeds
    error: str | None  # the last commit error while failing
    records_held: int
    records_lost: int
    alarms_held: int
    alarms_lost: int
    retries: int
    backlog: int  # committed records the broker has not acknowledged yet


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
        commit_interval_s: float = 0.5,
        retention_days: float = 30.0,
        backlog_alarm_records: int = 200_000,
        on_backlog: BacklogCallback | None = None,
        readonly: bool = False,
        max_held_records: int = MAX_HELD_RECORDS,
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
                self._convert_delivered_columns()
                self._convert_time_index()
                self._add_seed_columns()
            self._seed_columns = self._readable_seed_columns()
            self._acked = {table: IdRanges(self._load_delivered(table)) for table in _TABLES}
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open record store {self.path}: {exc}") from exc
        self._acked_dirty: set[str] = set()
        self._in_tx = False
        # Highest ids the outbox may see: rows above them are not committed yet.
        self._visible_seed_id = self._max_id("seeds")
        self._visible_alarm_id = self._max_id("alarms")
        self._last_seed_id = self._visible_seed_id
        self._last_alarm_id = self._visible_alarm_id
        self._pending_seeds = self._count_undelivered("seeds")
        self._pending_alarms = self._count_undelivered("alarms")
        # The outbox's in-memory tail: _tail[k] is the row of id _tail_first + k.
        self._tail: list[SeedRow] = []
        self._tail_first = self._last_seed_id + 1
        # What the open transaction wrote: kept until its COMMIT succeeds, because a failed
        # COMMIT on a full disk can roll the whole transaction back; the rows then go back
        # to the front of the held rows, under the same ids.
        self._tx_rows: list[SeedRow] = []  # ids _tx_first, _tx_first + 1, ...
        self._tx_first = 0
        self._tx_alarms: list[AlarmEvent] = []
        # Written nowhere yet because the store is failing: ids _held_first, ... (seeds);
        # alarms get theirs when written.
        self._held: list[SeedRow] = []
        self._held_first = 0
        self._held_alarms: list[AlarmEvent] = []
        self.max_held_records = max_held_records
        self.records_lost = 0  # seed records past max_held_records while failing
        self.alarms_lost = 0
        self._failing = False  # a write failed: new rows are held until a retry succeeds
        self._backoff = Backoff(initial_s=RETRY_INITIAL_S, cap_s=RETRY_MAX_S)
        self._retry_at = 0.0
        self.retries = 0  # attempts to write the held records (for tests and the log)
        self._last_run_error = ""
        self._last_sync = time.monotonic()
        self._unsynced = False  # commits since the last fsync of the WAL
        self._work = asyncio.Event()  # set when a transaction opens: run() has work
        # run() checkpoints on its own connection in a worker thread, so the fsync of a
        # checkpoint never stalls the event loop (and with it the control loop).
        self._ckpt_lock = threading.Lock()
        self._ckpt_db: sqlite3.Connection | None = None
        self.checkpoints = 0  # WAL fsyncs made (an idle box makes none; for tests and the log)
        # why writing fails, None once everything held is written (read by the alarms)
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

    def _has_column(self, table: str, column: str) -> bool:
        return any(r[1] == column for r in self._db.execute(f"PRAGMA table_info({table})"))

    def _has_table(self, table: str) -> bool:
        return self._db.execute(
            "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (table,)
        ).fetchone() is not None

    def _load_delivered(self, table: str) -> list[tuple[int, int]]:
        """The acknowledged id ranges: from ``delivered``, or from an older store's flags."""
        if self._has_table("delivered"):
            ranges = self._db.execute(
                "SELECT lo, hi FROM delivered WHERE tbl = ? ORDER BY lo", (table,)
            ).fetchall()
            if ranges or not self._has_column(table, "delivered"):
                return [(int(lo), int(hi)) for lo, hi in ranges]
        if not self._has_column(table, "delivered"):
            return []
        # runs of consecutive delivered ids (gaps and islands); ids below the oldest row were
        # pruned, and only delivered rows are ever pruned
        runs = [(int(lo), int(hi)) for lo, hi in self._db.execute(
            f"SELECT MIN(id), MAX(id) FROM (SELECT id, id - ROW_NUMBER() OVER (ORDER BY id) AS g "
            f"FROM {table} WHERE delivered = 1) GROUP BY g ORDER BY 1"
        )]
        oldest = self._scalar(f"SELECT MIN(id) FROM {table}")
        if oldest > 1:
            runs.insert(0, (1, oldest - 1))
        return runs

    def _convert_delivered_columns(self) -> None:
        """Turn an older store's per-row ``delivered`` flags into ranges, in one transaction."""
        old = [t for t in _TABLES if self._has_column(t, "delivered")]
        if not old:
            return
        self._db.execute("BEGIN IMMEDIATE")
        try:
            for table in old:
                runs = self._load_delivered(table)
                self._db.execute("DELETE FROM delivered WHERE tbl = ?", (table,))
                self._db.executemany(
                    "INSERT INTO delivered (tbl, lo, hi) VALUES (?, ?, ?)",
                    [(table, lo, hi) for lo, hi in runs],
                )
                self._db.execute(f"DROP INDEX IF EXISTS {table}_pending")
                self._db.execute(f"ALTER TABLE {table} DROP COLUMN delivered")
            self._db.execute("COMMIT")
        except sqlite3.Error:
            self._db.execute("ROLLBACK")
            raise
        log.info("record store %s: delivery flags converted to id ranges", self.path)

    def _add_seed_columns(self) -> None:
        """Give an older store the columns added since it was made (no rewrite of its rows:
        SQLite's ADD COLUMN only changes the schema; old rows read the defaults)."""
        missing = [c for c in _ADDED_SEED_COLUMNS if not self._has_column("seeds", c[0])]
        if not missing:
            return
        self._db.execute("BEGIN IMMEDIATE")
        try:
            for name, declaration, _ in missing:
                self._db.execute(f"ALTER TABLE seeds ADD COLUMN {name} {declaration}")
            self._db.execute("COMMIT")
        except sqlite3.Error:
            self._db.execute("ROLLBACK")
            raise
        log.info("record store %s: seed columns added (%s)", self.path,
                 ", ".join(c[0] for c in missing))

    def _readable_seed_columns(self) -> str:
        """``_SEED_COLUMNS`` as this store can answer them: an older store opened read-only
        (``sowgate export`` next to an older daemon) reads defaults for the added ones."""
        if all(self._has_column("seeds", name) for name, _, _ in _ADDED_SEED_COLUMNS):
            return _SEED_COLUMNS
        cols = ("id, utc_us, row, lat, lon, fix, speed_kmh, heading_deg, heading_source, "
                "extrapolated, method, spacing_m")
        for name, _, default in _ADDED_SEED_COLUMNS:
            cols += f", {name}" if self._has_column("seeds", name) else f", {default}"
        return cols

    def _convert_time_index(self) -> None:
        """Replace an older store's per-seed time index by one span over its rows.

        The index cost every insert a second B-tree write (a fifth of the insert); spans
        (one row per appended batch) answer the same time-range questions. The old rows get
        one span, found through the old index before it goes, so it is quick on any size.
        """
        if self._db.execute(
            "SELECT 1 FROM sqlite_master WHERE type = 'index' AND name = 'seeds_utc'"
        ).fetchone() is None:
            return
        self._db.execute("BEGIN IMMEDIATE")
        try:
            self._db.execute(
                "INSERT OR IGNORE INTO seed_spans (first_id, last_id, min_utc_us, max_utc_us) "
                "SELECT MIN(id), MAX(id), MIN(utc_us), MAX(utc_us) FROM seeds HAVING COUNT(*) > 0"
            )
            self._db.execute("DROP INDEX seeds_utc")
            self._db.execute("COMMIT")
        except sqlite3.Error:
            self._db.execute("ROLLBACK")
            raise
        log.info("record store %s: per-seed time index replaced by spans", self.path)

    def _span_ids(self, since_us: int | None, until_us: int | None) -> tuple[int, int] | None:
        """The id range holding every seed with ``since <= utc < until`` (None: no seed).

        From the spans of appended batches; an older store opened read-only, not converted
        yet, has none and is scanned whole (it still has its time index)."""
        if not self._has_table("seed_spans"):
            return 0, self._max_id("seeds")
        row = self._db.execute(
            "SELECT MIN(first_id), MAX(last_id) FROM seed_spans "
            "WHERE max_utc_us >= ? AND min_utc_us < ?",
            (-(2**63) if since_us is None else since_us,
             2**63 - 1 if until_us is None else until_us),
        ).fetchone()
        if row is None or row[0] is None:
            return None
        return int(row[0]) - 1, int(row[1])

    def _count_undelivered(self, table: str) -> int:
        """Rows not acknowledged: a count above the fully-acknowledged prefix, less the runs."""
        acked = self._acked[table]
        through = acked.through()
        n = self._scalar(f"SELECT COUNT(*) FROM {table} WHERE id > ?", through)
        for lo, hi in acked:
            if hi > through:
                n -= self._scalar(
                    f"SELECT COUNT(*) FROM {table} WHERE id BETWEEN ? AND ?",
                    max(lo, through + 1), hi,
                )
        return n

    def _begin(self) -> None:
        if self.readonly:
            raise StoreError("record store opened read-only")
        if not self._in_tx:
            self._db.execute("BEGIN")
            self._in_tx = True
            self._work.set()  # run() has something to commit

    def add_commit_listener(self, listener: Callable[[], None]) -> None:
        """Called after each commit that made new records visible (the outbox wakes up)."""
        self._commit_listeners.append(listener)

    # -- writing -----------------------------------------------------------------------------

    def add_seeds(self, drops: Sequence[SeedDrop]) -> list[SeedRecord]:
        """Store drops and give them ids; they reach the outbox at the next ``flush``."""
        ids = self.append_seeds(drops)
        mid = self.machine_id
        kept = drops[:len(ids)]  # past the held-records cap the newest got no id (lost)
        return [
            _fast_record({**d.__dict__, "id": i, "machine_id": mid})
            for i, d in zip(ids, kept, strict=True)
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

        Never refuses rows because the disk is full: while writing fails they are held in
        memory under the ids returned here and written by a later retry; past
        ``max_held_records`` the newest are counted in ``records_lost`` and get no id (the
        returned range is then shorter than ``rows``).
        """
        if not rows:
            return range(0)
        if self.readonly:
            raise StoreError("record store opened read-only")
        if self._failing:
            return self._hold(rows)
        self._begin()
        try:
            last = self._insert(rows)
        except StoreError as exc:
            self._write_failed(exc)
            return self._hold(rows)
        first = last - len(rows) + 1
        if not self._tx_rows:
            self._tx_first = first
        self._tx_rows.extend(rows)
        self._last_seed_id = last
        self._remember(first, rows)
        return range(first, last + 1)

    def _insert(self, rows: Sequence[SeedRow], first_id: int | None = None) -> int:
        """INSERT ``rows`` (and their span) in the open transaction; returns the last id.

        With ``first_id`` the rows get ids ``first_id, first_id + 1, ...`` (held rows written
        back), otherwise the next ones AUTOINCREMENT hands out. A savepoint, so a failed
        insert (disk full) leaves no half batch behind.
        """
        self._db.execute("SAVEPOINT add_seeds")
        try:
            # Multi-row INSERTs of a few fixed sizes (so the prepared statements are reused):
            # one statement per chunk instead of one per row; ~25 % less than executemany.
            execute = self._db.execute
            i, n = 0, len(rows)
            for size in _INSERT_CHUNKS:
                while n - i >= size:
                    if first_id is None:
                        execute(_insert_sql(size), list(_chain(*rows[i:i + size])))
                    else:
                        execute(_insert_with_ids_sql(size), list(_chain.from_iterable(
                            (first_id + k, *rows[k]) for k in range(i, i + size)
                        )))
                    i += size
            if first_id is None:
                last = self._scalar("SELECT last_insert_rowid()")
            else:
                last = first_id + n - 1
            times = list(map(_UTC_US, rows))
            execute(
                "INSERT INTO seed_spans (first_id, last_id, min_utc_us, max_utc_us) "
                "VALUES (?, ?, ?, ?)", (last - n + 1, last, min(times), max(times)),
            )
            self._db.execute("RELEASE add_seeds")
        except sqlite3.Error as exc:
            if self._db.in_transaction:  # else SQLite rolled back the whole transaction
                with contextlib.suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK TO add_seeds")
                    self._db.execute("RELEASE add_seeds")
            raise StoreError(f"cannot write seed records: {exc}") from exc
        # One writer, one transaction: AUTOINCREMENT hands out a contiguous run ending at last.
        return last

    def _remember(self, first: int, rows: Sequence[SeedRow]) -> None:
        """Keep the rows in the outbox's tail (bounded by ``TAIL_MAX_ROWS``)."""
        tail = self._tail
        if first != self._tail_first + len(tail):  # not contiguous: start the tail afresh
            tail.clear()
            self._tail_first = first
        tail.extend(rows)
        excess = len(tail) - TAIL_MAX_ROWS
        if excess > 0:
            del tail[:excess]
            self._tail_first += excess

    # -- holding what cannot be written ----------------------------------------------------

    @property
    def failing(self) -> bool:
        """A write failed and records are held in memory until a retry succeeds."""
        return self._failing

    @property
    def records_held(self) -> int:
        """Seed records accepted but not written, waiting for the disk (0 when healthy)."""
        return len(self._held) + (len(self._tx_rows) if self._failing else 0)

    @property
    def alarms_held(self) -> int:
        return len(self._held_alarms) + (len(self._tx_alarms) if self._failing else 0)

    def _hold(self, rows: Sequence[SeedRow]) -> range:
        """Keep rows in memory under the next ids, up to ``max_held_records``; count the rest."""
        room = max(0, self.max_held_records - self.records_held)
        keep = rows[:room]
        lost = len(rows) - len(keep)
        if lost:
            if not self.records_lost:
                log.error(
                    "record store: %d seed records held in memory (the cap); newer ones are "
                    "lost and counted until the disk takes writes again", self.records_held,
                )
            self.records_lost += lost
        if not keep:
            return range(0)
        first = self._last_seed_id + 1
        if not self._held:
            self._held_first = first
        self._held.extend(keep)
        self._last_seed_id += len(keep)
        return range(first, first + len(keep))

    def _hold_alarm(self, event: AlarmEvent) -> AlarmEvent:
        if self.alarms_held >= MAX_HELD_ALARMS:
            self.alarms_lost += 1
        else:
            self._held_alarms.append(event)
        return event.model_copy(update={"id": 0, "machine_id": self.machine_id})

    def _write_failed(self, exc: Exception) -> None:
        """A write or a commit failed: keep everything it held and retry later, backing off."""
        if self._in_tx and not self._db.in_transaction:
            # SQLite rolled the whole transaction back: what it wrote goes back to memory,
            # in front of what is held, under the same seed ids.
            self._in_tx = False
            if self._tx_rows:
                self._held[:0] = self._tx_rows
                self._held_first = self._tx_first
            self._held_alarms[:0] = self._tx_alarms
            self._tx_rows, self._tx_alarms = [], []
            self._last_alarm_id = self._visible_alarm_id
            self._acked_dirty.update(_TABLES)
        self._forget_uncommitted_tail()
        if not self._failing:
            log.error(
                "record store: writing failed (%s); seed records are held in memory (up to "
                "%d) and written when the disk takes writes again", exc, self.max_held_records,
            )
        self._failing = True
        self.commit_error = str(exc)
        self._retry_at = time.monotonic() + self._backoff.next_delay()

    def retry(self) -> None:
        """Write everything held now, whatever the backoff says; StoreError if it still fails.

        ``flush`` and ``run`` retry a step at a time when the backoff allows; this is for a
        stop (``close``, the end of ``run``) and for tests.
        """
        while not self._drain_step():
            pass

    def _drain_step(self) -> bool:
        """Commit what is open, then write up to ``DRAIN_CHUNK_ROWS`` held rows and commit.

        Returns True once nothing is held any more (the store is healthy again).
        """
        if not self._failing:
            self._commit()
            return True
        self.retries += 1
        try:
            self._commit()  # a transaction a failed COMMIT left open, or acknowledged ranges
            if self._held or self._held_alarms:
                self._write_held_chunk()
                self._commit()
        except StoreError as exc:  # already recorded by _commit or _write_held_chunk
            raise StoreError(f"record store still cannot write: {exc}") from exc
        if self._held or self._held_alarms:
            return False
        log.info(
            "record store writes again after %d retries; every held record is stored%s",
            self.retries, f" ({self.records_lost} were lost)" if self.records_lost else "",
        )
        self._failing = False
        self.commit_error = None
        self._backoff.reset()
        return True

    def _write_held_chunk(self) -> None:
        """INSERT up to ``DRAIN_CHUNK_ROWS`` held rows (with their ids) and the held alarms."""
        try:
            self._begin()
            if self._held:
                n = min(len(self._held), DRAIN_CHUNK_ROWS)
                chunk = self._held[:n]
                first = self._held_first
                self._insert(chunk, first_id=first)
                self._tx_first, self._tx_rows = first, chunk
                self._remember(first, chunk)
                del self._held[:n]
                self._held_first += n
            while self._held_alarms:
                self._insert_alarm(self._held_alarms[0])
                self._tx_alarms.append(self._held_alarms.pop(0))
        except (StoreError, sqlite3.Error) as exc:
            self._write_failed(exc)
            raise StoreError(str(exc)) from exc

    def _insert_alarm(self, event: AlarmEvent) -> int:
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
        self._last_alarm_id = int(cur.lastrowid or 0)
        return self._last_alarm_id

    def add_alarm(self, event: AlarmEvent) -> AlarmEvent:
        """Store an alarm event and commit at once: alarms are rare and must not wait.

        Returns the event with its id, or with id 0 if it could not be committed now (the
        store is failing): it is then held and written, with an id, by a later retry.
        """
        if self.readonly:
            raise StoreError("record store opened read-only")
        if self._failing:
            return self._hold_alarm(event)
        self._begin()
        try:
            alarm_id = self._insert_alarm(event)
        except StoreError as exc:
            self._write_failed(exc)
            return self._hold_alarm(event)
        self._tx_alarms.append(event)
        try:
            self._commit()
        except StoreError:
            return event.model_copy(update={"id": 0, "machine_id": self.machine_id})
        return event.model_copy(update={"id": alarm_id, "machine_id": self.machine_id})

    def flush(self) -> None:
        """Commit: from now on the new records survive a crash and the outbox can see them.

        While the store is failing this is one retry step (``DRAIN_CHUNK_ROWS`` held rows at
        most, so a caller's burst stays short; ``run`` writes the rest) when the backoff
        allows one, and nothing otherwise; StoreError when the attempt fails.
        """
        if self._failing:
            if time.monotonic() >= self._retry_at:
                self._drain_step()
            return
        self._commit()

    def _commit(self) -> None:
        if not self._in_tx:
            return
        try:
            self._write_delivered()
            self._db.execute("COMMIT")
        except sqlite3.Error as exc:
            self._write_failed(exc)
            raise StoreError(f"cannot commit records: {exc}") from exc
        self._in_tx = False
        self._unsynced = True  # in the WAL, not yet fsynced
        seeds, alarms = len(self._tx_rows), len(self._tx_alarms)
        if seeds:
            self._visible_seed_id = self._tx_first + seeds - 1
        self._visible_alarm_id = self._last_alarm_id
        self._pending_seeds += seeds
        self._pending_alarms += alarms
        self._tx_rows, self._tx_alarms = [], []
        self._check_backlog()
        if seeds or alarms:
            for listener in self._commit_listeners:
                listener()

    def _write_delivered(self) -> None:
        """Rewrite the changed tables' acknowledged ranges (a handful of rows) in this commit."""
        for table in self._acked_dirty:
            self._db.execute("DELETE FROM delivered WHERE tbl = ?", (table,))
            self._db.executemany(
                "INSERT INTO delivered (tbl, lo, hi) VALUES (?, ?, ?)",
                [(table, lo, hi) for lo, hi in self._acked[table]],
            )
        self._acked_dirty.clear()

    def _forget_uncommitted_tail(self) -> None:
        """The tail may only hold committed rows: a failed commit may never become one.

        The forgotten rows may still be committed later (a COMMIT that failed but left the
        transaction open, or held rows written back) without passing through ``_remember``
        again, so the tail starts afresh after every id handed out: the outbox reads the
        ids below it from SQLite, never a slice of the tail that does not hold them.
        """
        keep = self._visible_seed_id - self._tail_first + 1
        if keep < len(self._tail):
            self._tail.clear()
            self._tail_first = self._last_seed_id + 1

    def sync(self) -> None:
        """fsync the WAL (via a passive checkpoint): bounds what a power cut can take back."""
        self.flush()
        self._checkpoint()
        self._last_sync = time.monotonic()
        self._unsynced = False

    def _checkpoint(self) -> None:
        """Passive checkpoint on a second connection; safe to call from a worker thread."""
        with self._ckpt_lock:
            db = self._ckpt_db
            if db is None:
                db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
                self._ckpt_db = db
            db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
            self.checkpoints += 1

    # -- outbox ------------------------------------------------------------------------------

    def _undelivered(self, limit: int, after_id: int) -> tuple[list[int], list[SeedRow]]:
        """Ids and rows of up to ``limit`` committed, undelivered seeds after ``after_id``.

        From the in-memory tail where it reaches, from SQLite below it.
        """
        limit = max(0, min(limit, MAX_OUTBOX_LIMIT))
        ids: list[int] = []
        rows: list[SeedRow] = []
        tail_first = self._tail_first
        for lo, hi in self._acked["seeds"].gaps(after_id, self._visible_seed_id):
            need = limit - len(ids)
            if need <= 0:
                break
            if lo < tail_first:
                cold = self._db.execute(
                    f"SELECT {self._seed_columns} FROM seeds WHERE id BETWEEN ? AND ? "
                    "ORDER BY id LIMIT ?",
                    (lo, min(hi, tail_first - 1), need),
                ).fetchall()
                for r in cold:
                    ids.append(r[0])
                    rows.append(r[1:])
                need -= len(cold)
                lo = tail_first
                if need <= 0 or lo > hi:
                    continue
            hi = min(hi, lo + need - 1)
            ids.extend(range(lo, hi + 1))
            rows.extend(self._tail[lo - tail_first : hi - tail_first + 1])
        return ids, rows

    def pending_seeds(self, limit: int, after_id: int = 0) -> list[SeedRecord]:
        """Committed, undelivered seed records with ``id > after_id``, oldest first."""
        ids, rows = self._undelivered(limit, after_id)
        return [self._seed((i, *r)) for i, r in zip(ids, rows, strict=True)]

    def count_pending_seeds(self, after_id: int = 0, cap: int = MAX_OUTBOX_LIMIT) -> int:
        """How many committed undelivered ids follow ``after_id``, counting at most ``cap``.

        Counted from the ranges, not the rows: in a store converted from an older version a
        pruned id can count, which at worst makes a batch go out a little smaller.
        """
        n = 0
        for lo, hi in self._acked["seeds"].gaps(after_id, self._visible_seed_id):
            n += hi - lo + 1
            if n >= cap:
                return max(0, cap)
        return n

    def pending_seed_batch(self, limit: int, after_id: int = 0) -> OutboxBatch | None:
        """Like ``pending_seeds`` but straight to ``SeedBatch`` JSON (the MQTT hot path).

        Equals ``SeedBatch(...).model_dump_json()`` value for value (tested); see
        ``seed_batch_json`` for why it builds no models.
        """
        ids, rows = self._undelivered(limit, after_id)
        if not ids:
            return None
        return OutboxBatch(ids, seed_batch_json(self.machine_id, ids, rows))

    def pending_alarms(self, limit: int, after_id: int = 0) -> list[AlarmEvent]:
        limit = max(0, min(limit, MAX_OUTBOX_LIMIT))
        rows: list[Any] = []
        for lo, hi in self._acked["alarms"].gaps(after_id, self._visible_alarm_id):
            if len(rows) >= limit:
                break
            rows.extend(self._db.execute(
                "SELECT id, utc_us, code, active, severity, message FROM alarms "
                "WHERE id BETWEEN ? AND ? ORDER BY id LIMIT ?",
                (lo, hi, limit - len(rows)),
            ).fetchall())
        return [
            AlarmEvent(
                id=r[0], machine_id=self.machine_id, utc=us_to_utc(r[1]), code=r[2],
                active=bool(r[3]), severity=r[4], message=r[5],
            )
            for r in rows
        ]

    def _mark(self, table: str, ids: Sequence[int]) -> int:
        """Merge into the acknowledged ranges; written at the next commit. Returns new ids."""
        if not ids:
            return 0
        self._begin()
        acked = self._acked[table]
        changed = acked.add_ids(ids)
        if changed:
            self._acked_dirty.add(table)
            if table == "seeds":  # the tail never needs what was acknowledged from its start
                done = acked.through() - self._tail_first + 1
                if done > 0:
                    del self._tail[:done]
                    self._tail_first += done
        return changed

    def mark_seeds_delivered(self, ids: Sequence[int]) -> None:
        """Called on PUBACK. Committed with the next flush; a crash before it means a resend."""
        self._pending_seeds -= self._mark("seeds", ids)
        self._check_backlog()

    def mark_seed_ranges_delivered(self, ranges: Sequence[tuple[int, int]]) -> int:
        """The farm server's watermark (``[mqtt] farm_server_ack``): these inclusive id ranges
        are committed farm-side. Only ids this store has handed out count (a watermark from a
        database that knew an older box with the same machine id must not mark ids to come).
        Returns how many ids were newly marked."""
        ceiling = self._visible_seed_id
        new = 0
        self._begin()
        acked = self._acked["seeds"]
        for lo, hi in ranges:
            lo, hi = max(1, lo), min(hi, ceiling)
            if lo <= hi:
                new += acked.add(lo, hi)
        if new:
            self._acked_dirty.add("seeds")
            done = acked.through() - self._tail_first + 1
            if done > 0:
                del self._tail[:done]
                self._tail_first += done
            self._pending_seeds -= new
            self._check_backlog()
        return new

    def oldest_pending_seed_id(self) -> int | None:
        """The lowest committed id not yet delivered (None when all are)."""
        for lo, _hi in self._acked["seeds"].gaps(0, self._visible_seed_id):
            return lo
        return None

    def mark_alarms_delivered(self, ids: Sequence[int]) -> None:
        self._pending_alarms -= self._mark("alarms", ids)

    def pending_alarm_count(self) -> int:
        """Committed alarm events the broker has not acknowledged."""
        return self._pending_alarms

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
            "extrapolated": bool(r[9]), "method": r[10], "spacing_m": r[11],
            "attitude": r[12], "roll_deg": r[13], "pitch_deg": r[14], "delay_ms": r[15],
            "offset_east_m": r[16], "offset_north_m": r[17], "id": r[0],
            "machine_id": self.machine_id,
        })

    def query_seeds(
        self,
        since: datetime | None = None,
        until: datetime | None = None,
        rows: Sequence[int] | None = None,
    ) -> Iterator[SeedRecord]:
        """Committed records (delivered or not) in id order, ``since <= utc < until``."""
        for chunk in self.query_seed_rows(since, until, rows):
            for r in chunk:
                yield self._seed(r)

    def query_seed_rows(
        self,
        since: datetime | None = None,
        until: datetime | None = None,
        rows: Sequence[int] | None = None,
    ) -> Iterator[list[StoredSeedRow]]:
        """``query_seeds`` as the stored tuples (``STORED_SEED_COLUMNS``), a chunk at a time.

        The one streaming reader of ``sowgate export`` and ``sowgate report``: at most
        ``QUERY_CHUNK_ROWS`` rows are in memory at once, and no model is built per seed (a
        ``SeedRecord`` costs several times the read itself, and a day of a 48-row planter is
        ~70 M records).
        """
        sql = f"SELECT {self._seed_columns} FROM seeds WHERE id > ? AND id <= ?"
        args: list[Any] = []
        since_us = None if since is None else utc_to_us(since)
        until_us = None if until is None else utc_to_us(until)
        if since_us is not None:
            sql += " AND utc_us >= ?"
            args.append(since_us)
        if until_us is not None:
            sql += " AND utc_us < ?"
            args.append(until_us)
        if rows is not None:
            wanted = sorted({int(r) for r in rows})
            if not wanted:
                return
            sql += f" AND row IN ({','.join('?' * len(wanted))})"
            args.extend(wanted)
        sql += " ORDER BY id LIMIT ?"
        ceiling = self._visible_seed_id if not self.readonly else self._max_id("seeds")
        after = 0
        if since_us is not None or until_us is not None:
            span = self._span_ids(since_us, until_us)
            if span is None:
                return
            after, ceiling = max(after, span[0]), min(ceiling, span[1])
        while True:
            chunk = self._db.execute(sql, (after, ceiling, *args, QUERY_CHUNK_ROWS)).fetchall()
            if chunk:
                yield chunk
            if len(chunk) < QUERY_CHUNK_ROWS:
                return
            after = chunk[-1][0]

    def seed_time_span(
        self, since: datetime | None = None, until: datetime | None = None
    ) -> tuple[int, int] | None:
        """First and last ``utc_us`` that seeds in the window can have (from the batch spans,
        without reading the seeds), clipped to the window; None when no batch overlaps it.

        A bound, not the exact span: a batch crossing ``since`` counts from ``since``. A store
        without spans (an older one, read-only) is read from its seeds' time index.
        """
        lo = -(2**63) if since is None else utc_to_us(since)
        hi = 2**63 - 1 if until is None else utc_to_us(until)
        if self._has_table("seed_spans"):
            row = self._db.execute(
                "SELECT MIN(min_utc_us), MAX(max_utc_us) FROM seed_spans "
                "WHERE max_utc_us >= ? AND min_utc_us < ?",
                (lo, hi),
            ).fetchone()
        else:
            row = self._db.execute(
                "SELECT MIN(utc_us), MAX(utc_us) FROM seeds WHERE utc_us >= ? AND utc_us < ?",
                (lo, hi),
            ).fetchone()
        if row is None or row[0] is None:
            return None
        return max(int(row[0]), lo), min(int(row[1]), hi - 1)

    def query_alarms(
        self, since: datetime | None = None, until: datetime | None = None
    ) -> Iterator[AlarmEvent]:
        """Stored alarm events in id order, ``since <= utc < until`` (a chunk at a time)."""
        lo = -(2**63) if since is None else utc_to_us(since)
        hi = 2**63 - 1 if until is None else utc_to_us(until)
        after = 0
        while True:
            chunk = self._db.execute(
                "SELECT id, utc_us, code, active, severity, message FROM alarms "
                "WHERE id > ? AND utc_us >= ? AND utc_us < ? ORDER BY id LIMIT ?",
                (after, lo, hi, QUERY_CHUNK_ROWS),
            ).fetchall()
            for i, us, code, active, severity, message in chunk:
                yield AlarmEvent(
                    id=i, machine_id=self.machine_id, code=code, active=bool(active),
                    severity=severity, message=message, utc=us_to_utc(us),
                )
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
        for table in _TABLES:
            # only ids in the fully acknowledged prefix; runs above it join it soon enough
            bound = self._acked[table].through()
            if table == "seeds":  # and no further than the last batch with a seed that old
                bound = min(bound, self._scalar(
                    "SELECT MAX(last_id) FROM seed_spans WHERE min_utc_us < ?", cutoff
                ))
            cur = self._db.execute(
                f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} "
                "WHERE id <= ? AND utc_us < ? ORDER BY id LIMIT ?)",
                (bound, cutoff, PRUNE_CHUNK_ROWS),
            )
            deleted += cur.rowcount
            more = more or cur.rowcount >= PRUNE_CHUNK_ROWS
        oldest = self._db.execute("SELECT MIN(id) FROM seeds").fetchone()[0]
        if oldest is None:
            self._db.execute("DELETE FROM seed_spans")
        else:
            self._db.execute("DELETE FROM seed_spans WHERE last_id < ?", (oldest,))
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

    def state(self) -> StoreState:
        """For the daemon's state and its payload: what is held, what was lost."""
        return StoreState(
            failing=self._failing,
            error=self.commit_error,
            records_held=self.records_held,
            records_lost=self.records_lost,
            alarms_held=self.alarms_held,
            alarms_lost=self.alarms_lost,
            retries=self.retries,
            backlog=self.backlog(),
        )

    def integrity_check(self) -> str:
        return str(self._db.execute("PRAGMA integrity_check").fetchone()[0])

    def close(self) -> None:
        if not self.readonly:
            try:
                self.retry()  # a last attempt for anything held, whatever the backoff says
            except StoreError:
                log.exception(
                    "record store: final commit failed; %d seed records and %d alarms held "
                    "in memory are lost with this stop", self.records_held, self.alarms_held,
                )
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

        While writing fails (``failing``) it retries with capped backoff until the held
        records are all written, ``DRAIN_CHUNK_ROWS`` a step so the event loop keeps running.
        """
        last_prune = time.monotonic() - PRUNE_INTERVAL_S
        self._check_backlog()
        # Checkpoints happen here, off the event loop; SQLite's automatic ones would run
        # inside a COMMIT on the loop thread.
        self._db.execute("PRAGMA wal_autocheckpoint=0")
        try:
            while True:
                try:
                    if self._failing:
                        await asyncio.sleep(max(0.0, self._retry_at - time.monotonic()))
                        # a step per loop turn, so control runs between the chunks
                        for _ in iter(self._drain_step, True):
                            await asyncio.sleep(0)
                        continue
                    if time.monotonic() - last_prune >= PRUNE_INTERVAL_S:
                        last_prune = time.monotonic()
                        await self._prune_in_steps(utcnow())
                    if not self._in_tx and not self._unsynced:
                        # nothing to commit or to fsync: no wake-ups until a write opens a
                        # transaction (or the next prune is due)
                        self._work.clear()
                        until_prune = last_prune + PRUNE_INTERVAL_S - time.monotonic()
                        with contextlib.suppress(TimeoutError):
                            async with asyncio.timeout(max(0.0, until_prune)):
                                await self._work.wait()
                        continue
                    # on the shared grid: the recorder's flush (which commits too) wakes
                    # with it, so this tick usually finds nothing left but the fsync
                    await sleep_to_next_tick(self.commit_interval_s)
                    self.flush()
                    now = time.monotonic()
                    if self._unsynced and now - self._last_sync >= SYNC_INTERVAL_S:
                        self._last_sync = now
                        self._unsynced = False
                        await asyncio.to_thread(self._checkpoint)
                except (StoreError, sqlite3.Error) as exc:
                    # Keep the daemon running (control must go on). A failed write has put
                    # the store in ``failing`` (its records held, retried above with
                    # backoff); anything else (a checkpoint) is retried at the next tick.
                    if not self._failing:
                        if str(exc) != self._last_run_error:
                            log.warning("record store: %s; retrying", exc)
                        self._last_run_error = str(exc)
                        await sleep_to_next_tick(self.commit_interval_s)
        finally:
            self._db.execute("PRAGMA wal_autocheckpoint=1000")
            try:  # a stop commits here, as soon as the recorder has stored its last seeds
                self.retry()
            except StoreError:
                log.exception("record store: commit on stop failed")
