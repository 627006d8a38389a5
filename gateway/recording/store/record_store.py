"""``RecordStore``: the write path, the writer thread, holding what cannot be written, pruning.

Owns the ids handed out (through ``IdReservation``), the queue of records accepted and not yet
committed, the writer thread that commits them, and what happens when writing fails (a full
disk), stalls (a slow or frozen card) or finds the file damaged (moved aside, ``recovery``).
See the package docstring for the design; the readers are in ``queries`` and ``outbox``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from itertools import chain
from operator import itemgetter
from pathlib import Path
from typing import Any

from drivers.backoff import Backoff
from drivers.ticks import next_tick
from gateway.core.records import AlarmEvent, SeedDrop, SeedRecord, SeedRow, drop_row, utc_to_us
from gateway.recording import runs as run_markers
from gateway.recording.id_ranges import IdRanges
from gateway.recording.store.ids import ID_BLOCK, IdReservation, reservation_path
from gateway.recording.store.outbox import BacklogCallback, Outbox
from gateway.recording.store.queries import StoreQueries
from gateway.recording.store.recovery import (
    ReplacedStore,
    check_store,
    is_corruption,
    move_aside,
    salvage_undelivered,
)
from gateway.recording.store.schema import (
    INSERT_CHUNKS,
    TABLES,
    StoreError,
    fast_record,
    insert_with_ids_sql,
    load_delivered,
    max_id,
    prepare_for_writing,
    readable_seed_columns,
    scalar,
)
from gateway.recording.store.version import (
    check_schema_version,
    refuse_if_too_new,
    stamp_schema_version,
)

log = logging.getLogger(__name__)

SYNC_INTERVAL_S = 1.0  # the power-cut loss window (see the package docstring)
PRUNE_INTERVAL_S = 3600.0
# Rows one pruning step deletes in one transaction: a day of a 48-row planter is millions of
# rows, and one statement for all of them would hold the writer (and its commits) for seconds.
PRUNE_CHUNK_ROWS = 5000
# Seed records kept in memory while the store cannot write them (disk full, card gone
# read-only or stalled): every row accepted and not committed, in order, under the ids they
# were given, until a write succeeds. A held record costs about 430 bytes of memory (428
# measured by benchmarks/bench_held_records.py), so the cap is about 103 MB, and at 2 000
# seeds/s it rides out a full disk for 240 000 / 2 000 = 120 s. Past it, new records are
# counted in ``records_lost`` (state payload, records.lost alarm), never dropped silently;
# they take no ids.
MAX_HELD_RECORDS = 240_000
MAX_HELD_ALARMS = 1_000  # alarm events held likewise (alarms are rare); past it: alarms_lost
# A write that failed is retried with capped exponential backoff: a full disk is not asked
# twice a second (each attempt writes up to DRAIN_CHUNK_ROWS rows before it can fail), and a
# disk that has room again is used within RETRY_MAX_S.
RETRY_INITIAL_S = 0.5
RETRY_MAX_S = 5.0
DRAIN_CHUNK_ROWS = 20_000  # rows one transaction writes (a backlog goes in several)
# A write (or fsync) still running after this long: the card stalls. ``store.stalled`` is
# raised and the queued records count as held; the loop never waits for it.
STALL_S = 2.0
_UTC_US = itemgetter(0)  # of a SeedRow


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
    stalled: bool = False  # a write has been running longer than STALL_S
    replaced: str | None = None  # a store that failed its check was moved aside (this run)
    unclean_stop: str | None = None  # the last run did not close the store (ids skipped)


class RecordStore(StoreQueries, Outbox):
    """SQLite store of seed records and alarms; also the MQTT outbox.

    The methods are called from the event loop's thread; ``run`` starts the writer thread,
    which alone touches the write connection while it runs. Without ``run`` (tools, tests)
    ``flush`` writes on the calling thread.
    """

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
        id_block: int = ID_BLOCK,
        stall_s: float = STALL_S,
    ) -> None:
        self.path = Path(path)
        self.machine_id = machine_id
        self.commit_interval_s = commit_interval_s
        self.retention = timedelta(days=retention_days)
        self.backlog_alarm_records = backlog_alarm_records
        self.on_backlog = on_backlog
        self.readonly = readonly
        self.max_held_records = max_held_records
        self.stall_s = stall_s
        self._id_block = id_block
        self._commit_listeners: list[Callable[[], None]] = []
        self._backlog_over = False
        self._lock = threading.Lock()  # the memory the loop and the writer share
        self._write_lock = threading.RLock()  # the write connection: one writer at a time
        self._db: sqlite3.Connection | None = None
        self._old_readers: list[sqlite3.Connection] = []  # of stores moved aside while running
        self.replaced: ReplacedStore | None = None  # the last store moved aside, this run
        # set when this run started above ids the store does not have (see _continue_ids)
        self.unclean_stop: str | None = None
        self._ids: IdReservation | None = None
        self._run_id: int | None = None  # the daemon run marked by start_run
        try:
            if readonly:
                self._read_db = sqlite3.connect(
                    f"file:{self.path}?mode=ro", uri=True, isolation_level=None,
                    check_same_thread=False,
                )
                check_schema_version(self._read_db, self.path)
            else:
                self._open_for_writing()
            self._seed_columns = readable_seed_columns(self._read_db)
            self._acked = {t: IdRanges(load_delivered(self._read_db, t)) for t in TABLES}
            stored = {t: max_id(self._read_db, t) for t in TABLES}
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open record store {self.path}: {exc}") from exc
        self._acked_version = 0
        self._acked_written = 0
        # Highest ids the outbox may see: rows above them are not committed yet.
        self._visible_seed_id = stored["seeds"]
        self._visible_alarm_id = stored["alarms"]
        self._next_seed_id = stored["seeds"] + 1
        self._next_alarm_id = stored["alarms"] + 1
        if self._ids is not None:
            self._continue_ids(stored)
        self._pending_seeds = self._count_undelivered("seeds")
        self._pending_alarms = self._count_undelivered("alarms")
        # The outbox's in-memory tail of committed rows: _tail[k] is the row of id _tail_first+k.
        self._tail: list[SeedRow] = []
        self._tail_first = self._next_seed_id
        # Accepted, not committed yet: rows with ids _queue_first, _queue_first + 1, ... and
        # alarm events with their ids. Rows leave it only once their COMMIT succeeded, so a
        # failed write loses nothing and needs nothing put back.
        self._queue: list[SeedRow] = []
        self._queue_first = self._next_seed_id
        # the first id of each appended batch still queued: each batch gets its own span
        self._batch_starts: list[int] = []
        self._queue_alarms: list[tuple[int, AlarmEvent]] = []
        self.records_lost = 0  # seed records past max_held_records
        self.alarms_lost = 0
        self._failing = False  # a write failed: retried with backoff until it succeeds
        self.commit_error: str | None = None  # why writing fails, None once all is written
        self._backoff = Backoff(initial_s=RETRY_INITIAL_S, cap_s=RETRY_MAX_S)
        self._retry_at = 0.0
        self.retries = 0  # attempts to write while failing (for tests and the log)
        self._write_started: float | None = None  # monotonic start of the write under way
        self._unsynced = False  # commits since the last fsync of the WAL
        self._last_sync = time.monotonic()
        self.checkpoints = 0  # WAL fsyncs made (an idle box makes none; for tests and the log)
        # the writer thread and how to reach the loop from it (set by run())
        self._writer: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()  # something to write
        self._urgent = threading.Event()  # write now rather than at the next commit tick
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._utcnow: Callable[[], datetime] = lambda: datetime.now(UTC)

    @classmethod
    def open_readonly(cls, path: str | Path, machine_id: str) -> RecordStore:
        """For ``sowgate export`` next to a running daemon: WAL lets it read without blocking."""
        if not Path(path).exists():
            raise StoreError(f"no record store at {path}")
        return cls(path, machine_id, readonly=True)

    # -- opening -------------------------------------------------------------------------------

    @property
    def _reader(self) -> sqlite3.Connection:
        return self._read_db

    def _open_for_writing(self) -> None:
        """Check the store; a damaged one is moved aside and a new one continues the ids."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"cannot create the state directory {self.path.parent}: {exc}") \
                from exc
        if self.path.exists() and not self.path.is_file():
            raise StoreError(f"record store {self.path} is not a file")
        self._ids = IdReservation(reservation_path(self.path), self._id_block)
        refuse_if_too_new(self.path)  # exit 78: never moved aside as if it were damaged
        reason = check_store(self.path)
        if reason is not None:
            self._move_aside(reason)
        self._connect()
        if self.replaced is not None and self.replaced.moved_to is not None:
            assert self._db is not None
            self.replaced = dataclasses.replace(
                self.replaced, salvaged=salvage_undelivered(self.replaced.moved_to, self._db)
            )

    def _connect(self) -> None:
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            prepare_for_writing(db, self.path)
            stamp_schema_version(db)
            reader = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        except sqlite3.Error:
            db.close()
            raise
        self._db, self._read_db = db, reader

    def _move_aside(self, reason: str) -> None:
        self.replaced = move_aside(self.path, reason)
        assert self._ids is not None
        try:  # ids the damaged store shows are used, reserved or not
            self._ids.raise_to(self.replaced.max_ids)
        except OSError as exc:
            log.error("cannot write the id reservation %s: %s", self._ids.path, exc)

    def _continue_ids(self, stored: dict[str, int]) -> None:
        """Start above the reservation too; the ids skipped count as delivered (no record of
        this store has them, so the outbox must not wait for them)."""
        assert self._ids is not None
        for table in TABLES:
            first = self._ids.next_id(table, stored[table])
            if first - 1 > stored[table]:
                self._acked[table].add(stored[table] + 1, first - 1)
                self._acked_version += 1
                if self.replaced is None:
                    self.unclean_stop = (
                        f"the last run did not close the record store (power cut or crash): "
                        f"{table} ids {stored[table] + 1}..{first - 1} are skipped, never given "
                        "again; records of its last second may be missing from the store "
                        "(those delivered are on the broker)"
                    )
                    log.warning("record store %s: %s", self.path, self.unclean_stop)
            if table == "seeds":
                self._next_seed_id = first
            else:
                self._next_alarm_id = first

    def _count_undelivered(self, table: str) -> int:
        """Rows not acknowledged: a count above the fully-acknowledged prefix, less the runs."""
        acked = self._acked[table]
        through = acked.through()
        db = self._read_db
        n = scalar(db, f"SELECT COUNT(*) FROM {table} WHERE id > ?", through)
        for lo, hi in acked:
            if hi > through:
                n -= scalar(db, f"SELECT COUNT(*) FROM {table} WHERE id BETWEEN ? AND ?",
                            max(lo, through + 1), hi)
        return n

    def add_commit_listener(self, listener: Callable[[], None]) -> None:
        """Called (on the loop's thread) after each commit that made new records visible."""
        self._commit_listeners.append(listener)

    # -- accepting records (the loop's side: memory only) ---------------------------------------

    def add_seeds(self, drops: Sequence[SeedDrop]) -> list[SeedRecord]:
        """Store drops and give them ids; they reach the outbox once committed."""
        ids = self.append_seeds(drops)
        mid = self.machine_id
        kept = drops[:len(ids)]  # past the held-records cap the newest got no id (lost)
        return [
            fast_record({**d.__dict__, "id": i, "machine_id": mid})
            for i, d in zip(ids, kept, strict=True)
        ]

    def append_seeds(self, drops: Sequence[SeedDrop]) -> range:
        """Like ``add_seeds`` but hands back only the ids, in the order of ``drops``."""
        if not drops:
            return range(0)
        return self.append_rows([drop_row(d) for d in drops])

    def append_rows(self, rows: Sequence[SeedRow]) -> range:
        """``append_seeds`` for records already in column form (``Landing.stored``).

        Never touches the disk: the rows are queued under the ids returned here and the
        writer commits them. Past ``max_held_records`` queued (the disk full or stalled for
        minutes) the newest are counted in ``records_lost`` and get no id (the returned range
        is then shorter than ``rows``).
        """
        if not rows:
            return range(0)
        if self.readonly:
            raise StoreError("record store opened read-only")
        with self._lock:
            room = max(0, self.max_held_records - len(self._queue))
            keep = rows[:room]
            lost = len(rows) - len(keep)
            if lost:
                if not self.records_lost:
                    log.error(
                        "record store: %d seed records held in memory (the cap); newer ones "
                        "are lost and counted until the disk takes writes again",
                        len(self._queue),
                    )
                self.records_lost += lost
            first = self._next_seed_id
            if keep:
                if not self._queue:
                    self._queue_first = first
                self._queue.extend(keep)
                self._batch_starts.append(first)
                self._next_seed_id += len(keep)
        if keep:
            self._wake.set()
        return range(first, first + len(keep))

    def add_alarm(self, event: AlarmEvent) -> AlarmEvent:
        """Queue an alarm event for an immediate commit; returns it with its id.

        The id is 0 when it cannot be committed now (the store is failing or stalled): the
        MQTT link then publishes it live, and again with its id once it is written.
        """
        if self.readonly:
            raise StoreError("record store opened read-only")
        with self._lock:
            if len(self._queue_alarms) >= MAX_HELD_ALARMS:
                self.alarms_lost += 1
                alarm_id = 0
            else:
                alarm_id = self._next_alarm_id
                self._next_alarm_id += 1
                self._queue_alarms.append((alarm_id, event))
        if alarm_id and not self._failing and not self.stalled:
            self.commit_soon()
            if self._writer is None and self._failing:  # written here, and it failed
                alarm_id = 0
        else:
            self._wake.set()
            alarm_id = 0
        return event.model_copy(update={"id": alarm_id, "machine_id": self.machine_id})

    def commit_soon(self) -> None:
        """Commit what is queued now rather than at the next commit tick.

        With the writer thread running this only wakes it (the caller, the control loop's
        thread, never waits for the card); without it, it commits here (``flush``), and a
        failure is left to the store to report (``commit_error``) and retry.
        """
        if self._writer is not None:
            self._urgent.set()
            self._wake.set()
            return
        with contextlib.suppress(StoreError):
            self.flush()

    def _wake_writer(self) -> None:
        self._wake.set()

    # -- the state the alarms and the payload read ----------------------------------------------

    @property
    def failing(self) -> bool:
        """A write failed and records are held in memory until a retry succeeds."""
        return self._failing

    @property
    def stalled(self) -> bool:
        """A write (or fsync) has been running for more than ``stall_s``: the card stalls."""
        started = self._write_started
        return started is not None and time.monotonic() - started > self.stall_s

    @property
    def records_held(self) -> int:
        """Seed records accepted but not written because the disk fails or stalls (0 when
        healthy: the rows of one flush waiting for their commit are not "held")."""
        return len(self._queue) if self._failing or self.stalled else 0

    @property
    def alarms_held(self) -> int:
        return len(self._queue_alarms) if self._failing or self.stalled else 0

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
            stalled=self.stalled,
            replaced=self.replaced.describe() if self.replaced is not None else None,
            unclean_stop=self.unclean_stop,
        )

    # -- daemon runs (gateway.recording.runs) ---------------------------------------------

    def start_run(self, settings: dict[str, Any], now: datetime) -> None:
        """Mark a daemon start (and close a previous run that never marked its stop)."""
        if self.readonly or self._db is None:
            return
        with self._write_lock:
            self._run_id = run_markers.start_run(self._db, utc_to_us(now), settings)

    def stop_run(self, now: datetime) -> None:
        """Mark the clean stop of the run ``start_run`` began."""
        if self._run_id is None or self._db is None:
            return
        with self._write_lock:
            run_markers.stop_run(self._db, self._run_id, utc_to_us(now))
        self._run_id = None

    def runs(self) -> list[run_markers.Run]:
        """The daemon runs this store saw, oldest first ([] for an older store)."""
        return run_markers.read_runs(self._reader)

    # -- writing (the writer thread, or the caller of flush) --------------------------------

    def flush(self) -> None:
        """Commit everything queued, on this thread: from then on it survives a crash and the
        outbox can see it.

        While the store is failing this is one attempt when the backoff allows one, and
        nothing otherwise; StoreError when the attempt fails.
        """
        if self.readonly:
            return
        if self._failing and time.monotonic() < self._retry_at:
            return
        with self._write_lock:
            self._drain(raise_errors=True)

    def retry(self) -> None:
        """Write everything queued now, whatever the backoff says; StoreError if it fails."""
        with self._write_lock:
            self._drain(raise_errors=True)

    def _drain(self, raise_errors: bool) -> bool:
        """Commit chunks until nothing is queued; True when all is written. Write lock held."""
        replaced = False
        if self._failing:
            self.retries += 1
        while True:
            try:
                done = self._write_chunk()
            except (sqlite3.Error, OSError, StoreError) as exc:
                if is_corruption(exc) and not replaced:
                    replaced = True
                    try:
                        self._replace_while_running(str(exc))
                        continue
                    except (sqlite3.Error, OSError) as again:
                        exc = again
                self._write_failed(exc)
                if raise_errors:
                    raise StoreError(f"cannot commit records: {exc}") from exc
                return False
            if done:
                break
        if self._failing:
            log.info(
                "record store writes again after %d retries; every held record is stored%s",
                self.retries, f" ({self.records_lost} were lost)" if self.records_lost else "",
            )
            self._failing = False
            self.commit_error = None
            self._backoff.reset()
        return True

    def _write_failed(self, exc: BaseException) -> None:
        """A write or a commit failed: everything stays queued; retry later, backing off."""
        if not self._failing:
            log.error(
                "record store: writing failed (%s); seed records are held in memory (up to "
                "%d) and written when the disk takes writes again", exc, self.max_held_records,
            )
        self._failing = True
        self.commit_error = str(exc) or type(exc).__name__
        self._retry_at = time.monotonic() + self._backoff.next_delay()

    def _write_chunk(self) -> bool:
        """Write up to ``DRAIN_CHUNK_ROWS`` queued rows, the queued alarms and the changed
        acknowledged ranges in one transaction; True when nothing is left to write."""
        with self._lock:
            n = min(len(self._queue), DRAIN_CHUNK_ROWS)
            first = self._queue_first
            rows = self._queue[:n]
            starts = [b - first for b in self._batch_starts if b < first + n]
            alarms = list(self._queue_alarms)
            version = self._acked_version
            acked = (
                {t: list(self._acked[t]) for t in TABLES}
                if version != self._acked_written else None
            )
        if not rows and not alarms and acked is None:
            return True
        self._write_started = time.monotonic()
        try:
            if self._db is None:  # a replacement store could not be opened: try again
                self._connect()
            db = self._db
            assert db is not None and self._ids is not None
            if rows:  # no id is committed (and published) before it is reserved durably
                self._ids.cover("seeds", first + n - 1)
            if alarms:
                self._ids.cover("alarms", alarms[-1][0])
            db.execute("BEGIN")
            try:
                if rows:
                    self._insert(db, rows, first, starts)
                for alarm_id, event in alarms:
                    db.execute(
                        "INSERT INTO alarms (id, utc_us, code, active, severity, message) "
                        "VALUES (?,?,?,?,?,?)",
                        (alarm_id, utc_to_us(event.utc), event.code, int(event.active),
                         event.severity, event.message),
                    )
                if acked is not None:
                    self._write_acked(db, acked)
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    with contextlib.suppress(sqlite3.Error):
                        db.execute("ROLLBACK")
                raise
        finally:
            self._write_started = None
        with self._lock:
            del self._queue[:n]
            self._queue_first += n
            del self._batch_starts[:len(starts)]
            if self._queue and (not self._batch_starts or self._batch_starts[0] != first + n):
                self._batch_starts.insert(0, first + n)  # the rest of a batch cut by the chunk
            del self._queue_alarms[:len(alarms)]
            if acked is not None:
                self._acked_written = version
            if rows:
                self._visible_seed_id = first + n - 1
                self._remember(first, rows)
            if alarms:
                self._visible_alarm_id = alarms[-1][0]
            self._pending_seeds += n
            self._pending_alarms += len(alarms)
            self._unsynced = True
            done = not self._queue and not self._queue_alarms
        if rows or alarms:
            self._notify_commit()
        return done

    @staticmethod
    def _write_acked(db: sqlite3.Connection, acked: dict[str, list[tuple[int, int]]]) -> None:
        """Rewrite the acknowledged ranges (a handful of rows) in the open transaction."""
        db.execute("DELETE FROM delivered")
        db.executemany(
            "INSERT INTO delivered (tbl, lo, hi) VALUES (?, ?, ?)",
            [(t, lo, hi) for t in TABLES for lo, hi in acked[t]],
        )

    @staticmethod
    def _insert(
        db: sqlite3.Connection, rows: Sequence[SeedRow], first_id: int, starts: list[int]
    ) -> None:
        """INSERT ``rows`` with ids ``first_id, first_id + 1, ...`` and the span of each
        appended batch (``starts``: where each begins in ``rows``)."""
        # Multi-row INSERTs of a few fixed sizes (so the prepared statements are reused):
        # one statement per chunk instead of one per row; ~25 % less than executemany.
        i, n = 0, len(rows)
        for size in INSERT_CHUNKS:
            while n - i >= size:
                db.execute(insert_with_ids_sql(size),
                           [first_id + i, *chain.from_iterable(rows[i:i + size])])
                i += size
        if not starts or starts[0] != 0:
            starts = [0, *starts]
        spans = []
        for lo, hi in zip(starts, [*starts[1:], n], strict=True):
            times = list(map(_UTC_US, rows[lo:hi]))
            spans.append((first_id + lo, first_id + hi - 1, min(times), max(times)))
        db.executemany(
            "INSERT INTO seed_spans (first_id, last_id, min_utc_us, max_utc_us) "
            "VALUES (?, ?, ?, ?)", spans,
        )

    def _notify_commit(self) -> None:
        """Tell the listeners (the MQTT link) on the loop's thread."""
        loop = self._loop
        if loop is not None and threading.get_ident() != self._loop_thread:
            with contextlib.suppress(RuntimeError):  # the loop is closing
                loop.call_soon_threadsafe(self._after_commit)
            return
        self._after_commit()

    def _after_commit(self) -> None:
        self._check_backlog()
        for listener in self._commit_listeners:
            listener()

    def _replace_while_running(self, reason: str) -> None:
        """SQLite found the store damaged while writing: move it aside, continue in a new one.

        What it held and had not delivered stays in the file moved aside (logged); the queued
        records go to the new store under their ids.
        """
        if self._db is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None
        self._old_readers.append(self._read_db)
        with self._lock:
            undelivered = self._pending_seeds
            visible = {"seeds": self._visible_seed_id, "alarms": self._visible_alarm_id}
        self._move_aside(reason)
        assert self._ids is not None
        self._ids.raise_to(visible)
        self._connect()
        with self._lock:
            first_alarm = self._queue_alarms[0][0] if self._queue_alarms else self._next_alarm_id
            below = {"seeds": self._queue_first - 1, "alarms": first_alarm - 1}
            # nothing below the queue is in the new store: nothing there for the outbox
            self._acked = {t: IdRanges([(1, below[t])] if below[t] else []) for t in TABLES}
            self._acked_version += 1
            self._pending_seeds = self._pending_alarms = 0
            self._tail.clear()
            self._tail_first = self._queue_first
        self._seed_columns = readable_seed_columns(self._read_db)
        if undelivered:
            log.error("%d committed seed records not yet delivered remain only in %s",
                      undelivered, self.replaced.moved_to if self.replaced else self.path)

    def sync(self) -> None:
        """fsync the WAL (via a passive checkpoint): bounds what a power cut can take back."""
        self.flush()
        with self._write_lock:
            self._checkpoint()

    def _checkpoint(self) -> None:
        """Passive checkpoint (it fsyncs the WAL); write lock held."""
        if self._db is None:
            return
        self._write_started = time.monotonic()
        try:
            self._db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
        finally:
            self._write_started = None
        self.checkpoints += 1
        self._last_sync = time.monotonic()
        self._unsynced = False

    # -- pruning ---------------------------------------------------------------------------------

    def prune(self, now: datetime) -> int:
        """Delete delivered records older than the retention; undelivered ones are kept."""
        deleted, more = self.prune_step(now)
        while more:
            step, more = self.prune_step(now)
            deleted += step
        return deleted

    def _prune_cutoff(self, db: sqlite3.Connection, now_us: int) -> int | None:
        """Records older than this may go: the retention back from the earlier of the host
        clock and the newest record's own time. Neither clock alone can delete anything: a
        host clock years ahead, or a receiver stamping new records 1024 weeks early (the GPS
        week rollover), both leave every record where it is."""
        newest = db.execute(
            "SELECT max_utc_us FROM seed_spans ORDER BY first_id DESC LIMIT 1"
        ).fetchone()
        if newest is None:
            newest = db.execute("SELECT utc_us FROM alarms ORDER BY id DESC LIMIT 1").fetchone()
        if newest is None:
            return None
        retention_us = int(self.retention.total_seconds() * 1_000_000)
        return min(now_us, int(newest[0])) - retention_us

    def prune_step(self, now: datetime) -> tuple[int, bool]:
        """``prune`` for at most ``PRUNE_CHUNK_ROWS`` rows a table, committed.

        Only a prefix in id order goes: delivered records up to the first one (by id) that is
        not older than the cutoff, so a record stamped in the past out of turn (a bad GNSS
        date) is not deleted ahead of the ones around it. Returns the rows deleted and whether
        a table may have more to prune.
        """
        with self._write_lock:
            db = self._db
            if db is None or self.readonly:
                return 0, False
            cutoff = self._prune_cutoff(db, utc_to_us(now))
            if cutoff is None:
                return 0, False
            with self._lock:
                through = {t: self._acked[t].through() for t in TABLES}
                version = self._acked_version
                acked = {t: list(self._acked[t]) for t in TABLES}
            deleted, more = 0, False
            db.execute("BEGIN")
            try:
                # what is deleted is acknowledged in the same commit, whatever happens next
                self._write_acked(db, acked)
                for table in TABLES:
                    first_recent = scalar(
                        db, "SELECT MIN(first_id) FROM seed_spans WHERE max_utc_us >= ?", cutoff
                    ) if table == "seeds" else scalar(
                        db, "SELECT MIN(id) FROM alarms WHERE utc_us >= ?", cutoff
                    )
                    bound = through[table] if first_recent == 0 else min(
                        through[table], first_recent - 1
                    )
                    cur = db.execute(
                        f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} "
                        "WHERE id <= ? ORDER BY id LIMIT ?)",
                        (bound, PRUNE_CHUNK_ROWS),
                    )
                    deleted += cur.rowcount
                    more = more or cur.rowcount >= PRUNE_CHUNK_ROWS
                oldest = db.execute("SELECT MIN(id) FROM seeds").fetchone()[0]
                if oldest is None:
                    db.execute("DELETE FROM seed_spans")
                else:
                    db.execute("DELETE FROM seed_spans WHERE last_id < ?", (oldest,))
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    with contextlib.suppress(sqlite3.Error):
                        db.execute("ROLLBACK")
                raise
            with self._lock:
                self._acked_written = max(self._acked_written, version)
            self._unsynced = True
            return deleted, more

    # -- the writer thread --------------------------------------------------------------------

    def _has_work(self) -> bool:
        return bool(self._queue or self._queue_alarms
                    or self._acked_version != self._acked_written)

    def _writer_main(self) -> None:
        """Commit what is queued at each commit tick (at once when asked), fsync the WAL every
        ``SYNC_INTERVAL_S`` while there were commits, prune at start and hourly, retry with
        backoff while failing. Nothing here is awaited by the loop."""
        last_prune = time.monotonic() - PRUNE_INTERVAL_S
        last_error = ""
        while not self._stop.is_set():
            try:
                now = time.monotonic()
                if now - last_prune >= PRUNE_INTERVAL_S and not self._failing:
                    last_prune = now
                    while self.prune_step(self._utcnow())[1] and not self._stop.is_set():
                        pass
                if self._failing:
                    self._stop.wait(max(0.0, self._retry_at - time.monotonic()))
                    with self._write_lock:
                        self._drain(raise_errors=False)
                    continue
                if not self._has_work():
                    until_sync = SYNC_INTERVAL_S - (time.monotonic() - self._last_sync)
                    if self._unsynced and until_sync <= 0:
                        with self._write_lock:
                            self._checkpoint()
                        continue
                    timeout = last_prune + PRUNE_INTERVAL_S - time.monotonic()
                    if self._unsynced:
                        timeout = min(timeout, until_sync)
                    self._wake.wait(max(0.0, timeout))
                    self._wake.clear()
                    continue
                if not self._urgent.is_set():  # on the shared commit grid
                    now = time.monotonic()
                    self._urgent.wait(next_tick(now, self.commit_interval_s) - now)
                self._urgent.clear()
                with self._write_lock:
                    self._drain(raise_errors=False)
                    if self._unsynced and time.monotonic() - self._last_sync >= SYNC_INTERVAL_S:
                        self._checkpoint()
            except (sqlite3.Error, OSError, StoreError) as exc:  # a checkpoint, a prune
                if str(exc) != last_error:
                    log.warning("record store: %s; retrying", exc)
                last_error = str(exc)
                self._stop.wait(self.commit_interval_s)

    def _start_writer(self) -> None:
        self._stop.clear()
        self._writer = threading.Thread(
            target=self._writer_main, name="record-store-writer", daemon=True
        )
        self._writer.start()

    def _stop_writer(self) -> None:
        writer, self._writer = self._writer, None
        if writer is None:
            return
        self._stop.set()
        self._wake.set()
        self._urgent.set()
        writer.join()

    async def run(self, utcnow: Callable[[], datetime] = lambda: datetime.now(UTC)) -> None:
        """Run the writer thread until cancelled, then commit what is left.

        The backlog is checked at start, so a restart with a large unsent backlog and the
        broker down still raises the backlog alarm.
        """
        if self.readonly:
            raise StoreError("record store opened read-only")
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._utcnow = utcnow
        self._check_backlog()
        self._start_writer()
        try:
            await asyncio.Event().wait()
        finally:
            await asyncio.to_thread(self._stop_writer)
            try:  # a stop commits here, as soon as the recorder has stored its last seeds
                self.retry()
            except StoreError as exc:
                log.error("record store: commit on stop failed: %s", exc)

    # -- closing ----------------------------------------------------------------------------------

    def close(self) -> None:
        if not self.readonly:
            self._stop_writer()
            try:
                self.retry()  # a last attempt for anything held, whatever the backoff says
            except StoreError as exc:
                log.error(
                    "record store: final commit failed (%s); %d seed records and %d alarms "
                    "held in memory are lost with this stop", exc, len(self._queue),
                    len(self._queue_alarms),
                )
            if self._ids is not None:  # the next start continues without a gap
                self._ids.lower_to({"seeds": self._visible_seed_id,
                                    "alarms": self._visible_alarm_id})
            if self._db is not None:
                with contextlib.suppress(sqlite3.Error):
                    self._db.close()
                self._db = None
        for reader in (*self._old_readers, self._read_db):
            with contextlib.suppress(sqlite3.Error):
                reader.close()

    def __enter__(self) -> RecordStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

