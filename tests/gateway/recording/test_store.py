"""The record store keeps every seed and alarm, hands out ids once, and feeds the outbox."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from gateway.core.records import AlarmEvent, SeedDrop, SeedRecord, utc_to_us
from gateway.link.payloads import SeedBatch
from gateway.recording.store import ID_BLOCK, MAX_OUTBOX_LIMIT, RecordStore, StoreError
from tests.helpers import eventually

T0 = datetime(2026, 4, 20, 8, 0, tzinfo=UTC)
REPO = Path(__file__).resolve().parents[3]


def drops(n: int, start: datetime = T0, row: int = 1) -> list[SeedDrop]:
    return [
        SeedDrop(
            row=row, utc=start + timedelta(milliseconds=10 * i), lat=52.0 + i * 1e-7,
            lon=13.0, fix="rtk_fixed", speed_kmh=8.0, heading_deg=90.0,
            heading_source="dual_antenna", spacing_m=0.05,
        )
        for i in range(n)
    ]


def alarm(code: str = "radar.lost", active: bool = True) -> AlarmEvent:
    return AlarmEvent(code=code, active=active, message="radar not answering", utc=T0)


def sql(store: RecordStore, query: str) -> list[tuple[Any, ...]]:
    """What SQLite holds for ``store``, read on a connection of its own (as an export does)."""
    with contextlib.closing(sqlite3.connect(store.path)) as db:
        return db.execute(query).fetchall()


@pytest.fixture
def store(tmp_path: Path) -> RecordStore:
    s = RecordStore(tmp_path / "records.sqlite3", "seeder-01", retention_days=1,
                    backlog_alarm_records=10)
    yield s
    s.close()


def test_ids_are_assigned_in_order_and_records_round_trip(store: RecordStore) -> None:
    """Stored records come back field for field, with ids 1..n and the machine id."""
    recs = store.add_seeds(drops(3))
    assert [r.id for r in recs] == [1, 2, 3]
    store.flush()
    back = list(store.query_seeds())
    assert back == recs
    assert back[0].machine_id == "seeder-01"
    assert back[1].utc == T0 + timedelta(milliseconds=10)


def test_uncommitted_records_are_invisible_to_the_outbox(store: RecordStore) -> None:
    """Nothing reaches MQTT before it is committed: a crash could take it back."""
    store.add_seeds(drops(5))
    assert store.pending_seeds(100) == []
    assert store.backlog() == 0
    store.flush()
    assert [r.id for r in store.pending_seeds(100)] == [1, 2, 3, 4, 5]
    assert store.backlog() == 5


def test_outbox_pages_by_cursor_and_forgets_delivered(store: RecordStore) -> None:
    store.add_seeds(drops(10))
    store.flush()
    first = store.pending_seeds(4)
    second = store.pending_seeds(4, after_id=first[-1].id)
    assert [r.id for r in second] == [5, 6, 7, 8]
    store.mark_seeds_delivered([r.id for r in second])
    assert [r.id for r in store.pending_seeds(100)] == [1, 2, 3, 4, 9, 10]
    assert store.backlog() == 6
    store.mark_seeds_delivered([5, 6])  # a duplicate PUBACK changes nothing
    assert store.backlog() == 6


def test_delivery_marks_survive_a_reopen(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite3"
    with RecordStore(path, "m") as s:
        s.add_seeds(drops(4))
        s.flush()
        s.mark_seeds_delivered([1, 3])
    with RecordStore(path, "m") as s:
        assert [r.id for r in s.pending_seeds(10)] == [2, 4]
        assert s.backlog() == 2


def test_ids_never_repeat_after_the_records_are_gone(tmp_path: Path) -> None:
    """A pruned id is gone for good, even across a restart, and so is every id of a store
    whose rows were all deleted (the id reservation is kept apart from the store)."""
    path = tmp_path / "r.sqlite3"
    with RecordStore(path, "m", retention_days=1) as s:
        recs = s.add_seeds(drops(3)) + s.add_seeds(drops(1, start=T0 + timedelta(days=2)))
        s.flush()
        s.mark_seeds_delivered([r.id for r in recs])
        assert s.prune(T0 + timedelta(days=2)) == 3
        assert [r.id for r in s.query_seeds()] == [4]
    with RecordStore(path, "m") as s:
        assert [r.id for r in s.add_seeds(drops(2))] == [5, 6]
        s.flush()
    sql_do(path, "DELETE FROM seeds")
    with RecordStore(path, "m") as s:
        assert [r.id for r in s.add_seeds(drops(1))] == [7]


def sql_do(path: Path, statement: str) -> None:
    with contextlib.closing(sqlite3.connect(path)) as db:
        db.execute(statement)
        db.commit()


def test_prune_keeps_undelivered_and_recent_records(store: RecordStore) -> None:
    """Nothing is dropped to save space: only delivered records past retention go."""
    old = store.add_seeds(drops(3, start=T0))
    new = store.add_seeds(drops(2, start=T0 + timedelta(days=3)))
    store.flush()
    store.mark_seeds_delivered([old[0].id, old[1].id, new[0].id])
    store.prune(T0 + timedelta(days=3, hours=1))
    assert [r.id for r in store.query_seeds()] == [old[2].id, new[0].id, new[1].id]


def test_query_filters_by_time_and_row(store: RecordStore) -> None:
    store.add_seeds(drops(5, row=1))
    store.add_seeds(drops(5, row=2))
    store.flush()
    since = T0 + timedelta(milliseconds=20)
    until = T0 + timedelta(milliseconds=40)
    got = list(store.query_seeds(since=since, until=until, rows=[2]))
    assert [(r.row, r.utc) for r in got] == [(2, since), (2, since + timedelta(milliseconds=10))]
    assert list(store.query_seeds(rows=[])) == []


def test_alarms_get_ids_and_are_committed_at_once(store: RecordStore) -> None:
    stored = store.add_alarm(alarm())
    assert stored.id == 1 and stored.machine_id == "seeder-01"
    pending = store.pending_alarms(10)
    assert pending == [stored]
    store.mark_alarms_delivered([1])
    assert store.pending_alarms(10) == []


def test_backlog_callback_fires_once_per_crossing(store: RecordStore) -> None:
    """The operator hears about a growing backlog once, and again when it drains."""
    calls: list[tuple[int, bool]] = []
    store.on_backlog = lambda n, over: calls.append((n, over))
    store.add_seeds(drops(8))
    store.flush()
    assert calls == []
    store.add_seeds(drops(5))
    store.flush()
    store.add_seeds(drops(5))
    store.flush()
    assert calls == [(13, True)]
    store.mark_seeds_delivered(list(range(1, 15)))
    assert calls == [(13, True), (4, False)]
    assert len(list(store.query_seeds())) == 18  # nothing was dropped


def test_readonly_store_reads_while_the_writer_is_open(store: RecordStore) -> None:
    store.add_seeds(drops(3))
    store.flush()
    with RecordStore.open_readonly(store.path, "seeder-01") as ro:
        assert [r.id for r in ro.query_seeds()] == [1, 2, 3]
        with pytest.raises(StoreError, match="read-only"):
            ro.add_seeds(drops(1))


def test_readonly_open_of_a_missing_store_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="no record store"):
        RecordStore.open_readonly(tmp_path / "nope.sqlite3", "m")


async def test_run_commits_periodically(store: RecordStore) -> None:
    """The daemon only appends; the run() loop makes records visible within the interval."""
    store.commit_interval_s = 0.05
    committed = asyncio.Event()
    store.add_commit_listener(committed.set)
    task = asyncio.create_task(store.run(), name="store-run")
    try:
        store.add_seeds(drops(2))
        assert store.pending_seeds(10) == []
        await asyncio.wait_for(committed.wait(), 5)
        assert len(store.pending_seeds(10)) == 2
    finally:
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task


async def test_run_sleeps_while_nothing_is_written_and_fsyncs_only_after_writes(
    store: RecordStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An idle box must not wake for store ticks; once records come they are committed and
    the WAL fsynced within the sync interval, and then the loop goes quiet again."""
    import gateway.recording.store as store_module

    monkeypatch.setattr(store_module, "SYNC_INTERVAL_S", 0.05)
    store.commit_interval_s = 0.05
    task = asyncio.create_task(store.run(), name="store-run")
    try:
        await asyncio.sleep(0.3)  # the prune at start commits, and is fsynced, once
        idle = store.checkpoints
        assert idle <= 1
        await asyncio.sleep(0.3)
        assert store.checkpoints == idle  # nothing written since: no commit, no fsync
        store.add_seeds(drops(2))
        await eventually(lambda: store.checkpoints > idle, 1.0, "the fsync after the commit",
                         interval=0.01)
        assert len(store.pending_seeds(10)) == 2  # committed
        assert store.checkpoints == idle + 1  # and fsynced
        await asyncio.sleep(0.3)
        assert store.checkpoints == idle + 1  # quiet again
    finally:
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task


WRITER = textwrap.dedent(
    """
    import sys
    from datetime import UTC, datetime, timedelta
    from gateway.core.records import SeedDrop
    from gateway.recording.store import RecordStore
    store = RecordStore(sys.argv[1], "m")
    t0 = datetime(2026, 4, 20, tzinfo=UTC)
    batch = [SeedDrop(row=1 + i % 6, utc=t0 + timedelta(milliseconds=i), lat=52.0, lon=13.0,
                      fix="rtk_fixed", speed_kmh=8.0) for i in range(50)]
    while True:
        for _ in range(4):
            records = store.add_seeds(batch)
        store.flush()
        print(records[-1].id, flush=True)
    """
)


def test_sigkill_during_writes_leaves_an_intact_contiguous_store(tmp_path: Path) -> None:
    """A crash mid-write loses only uncommitted records; ids stay contiguous and unique."""
    path = tmp_path / "crash.sqlite3"
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.stdout is not None
    committed = 0
    try:
        deadline = time.monotonic() + 15
        while committed < 20_000 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line, "writer died"
            committed = int(line)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
    assert committed >= 20_000
    with RecordStore(path, "m") as s:
        assert s.integrity_check() == "ok"
        ids = [r.id for r in s.query_seeds()]
        assert ids == list(range(1, len(ids) + 1))  # strictly increasing, no gap
        assert len(ids) >= committed  # everything reported committed survived
        assert s.backlog() == len(ids)
        # the run did not close the store: the next ids start above its id reservation,
        # at most a block ahead (the ids between may have been published; none is reused)
        (new,) = [r.id for r in s.add_seeds(drops(1))]
        assert len(ids) < new <= len(ids) + ID_BLOCK + 1


def test_fast_records_equal_validated_ones(store: RecordStore) -> None:
    """The store skips re-validation for speed; the records must still be exact models."""
    recs = store.add_seeds(drops(2))
    store.flush()
    for rec in [*recs, *store.pending_seeds(10)]:
        validated = SeedRecord.model_validate(dict(rec))  # store-only fields included
        assert rec == validated
        assert rec.model_dump_json() == validated.model_dump_json()


def test_outbox_json_matches_the_seed_batch_model(store: RecordStore) -> None:
    """The SQL-built MQTT payload parses to exactly the records the models describe."""
    odd = SeedDrop(row=48, utc=T0 + timedelta(microseconds=123), lat=-33.8688197, lon=151.2092955,
                   fix="rtk_float", speed_kmh=11.25, heading_deg=None, heading_source="course",
                   extrapolated=True, method="paper", spacing_m=None)
    store.add_seeds([*drops(3), odd])
    store.flush()
    batch = store.pending_seed_batch(10, after_id=1)
    assert batch is not None and batch.ids == [2, 3, 4]
    parsed = SeedBatch.model_validate_json(batch.payload)
    written = [*drops(3), odd][1:]
    assert parsed == SeedBatch(machine_id="seeder-01", records=[
        SeedRecord(**d.model_dump(), id=i, machine_id="seeder-01")
        for i, d in zip([2, 3, 4], written, strict=True)
    ], pending_from=1)  # id 1 is not delivered yet: the farm server may still get it
    assert store.count_pending_seeds(after_id=1, cap=2) == 2
    assert store.pending_seed_batch(10, after_id=4) is None


def test_append_seeds_hands_out_the_same_ids_as_add_seeds(store: RecordStore) -> None:
    """The ids-only append continues the one id sequence and stores the same rows."""
    first = store.add_seeds(drops(2))
    ids = store.append_seeds(drops(3, row=7))
    assert [r.id for r in first] == [1, 2] and list(ids) == [3, 4, 5]
    assert store.append_seeds([]) == range(0)
    assert store.pending_seeds(10) == []  # not committed yet: invisible to the outbox
    store.flush()
    stored = store.pending_seeds(10)
    assert [r.id for r in stored] == [1, 2, 3, 4, 5]
    assert [r.row for r in stored[2:]] == [7, 7, 7]
    assert stored[2:] == [
        SeedRecord(**d.model_dump(), id=i, machine_id="seeder-01")
        for i, d in zip(ids, drops(3, row=7), strict=True)
    ]


def test_pruning_goes_in_bounded_steps(
    store: RecordStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A day of records is millions of rows: each step deletes a bounded chunk, so the
    control loop gets the event loop back between steps."""
    monkeypatch.setattr("gateway.recording.store.record_store.PRUNE_CHUNK_ROWS", 5)
    recs = store.add_seeds(drops(12))
    store.add_seeds(drops(1, start=T0 + timedelta(days=2)))
    store.flush()
    store.mark_seeds_delivered([r.id for r in recs])
    later = T0 + timedelta(days=2)
    assert store.prune_step(later) == (5, True)
    assert len(list(store.query_seeds())) == 8
    assert store.prune(later) == 7
    assert [r.id for r in store.query_seeds()] == [13]


async def test_run_prunes_at_start_and_raises_an_old_backlog(tmp_path: Path) -> None:
    """A box that never runs an hour still prunes; a restart with a large unsent backlog
    and no new seeds (broker down) still tells the operator about it."""
    path = tmp_path / "r.sqlite3"
    with RecordStore(path, "m") as s:
        old = s.add_seeds(drops(3))
        s.add_seeds(drops(12, start=T0 + timedelta(days=40)))
        s.flush()
        s.mark_seeds_delivered([r.id for r in old])
        s.flush()
    calls: list[tuple[int, bool]] = []
    store = RecordStore(path, "m", retention_days=30, backlog_alarm_records=10,
                        on_backlog=lambda n, over: calls.append((n, over)))
    task = asyncio.create_task(
        store.run(utcnow=lambda: T0 + timedelta(days=41)), name="store-run"
    )
    try:
        await eventually(lambda: calls and len(list(store.query_seeds())) == 12, 2.0,
                         "the backlog call after the prune", interval=0.02)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        store.close()
    assert calls == [(12, True)]
    with RecordStore(path, "m") as s:
        assert [r.id for r in s.query_seeds()] == list(range(4, 16))


@pytest.mark.parametrize(
    "sizes", [[1], [7, 9], [128], [129, 33], [300, 2, 161], [1_050, 513]]
)
def test_batches_of_any_size_keep_ids_and_values(store: RecordStore, sizes: list[int]) -> None:
    """Rows go in as multi-row INSERTs of a few fixed sizes: no row lost, reordered or
    renumbered, whatever the batch size."""
    written: list[SeedDrop] = []
    ids: list[int] = []
    for k, n in enumerate(sizes):
        batch = drops(n, start=T0 + timedelta(seconds=10 * k), row=1 + k)
        ids += store.append_seeds(batch)
        written += batch
    store.flush()
    assert ids == list(range(1, len(written) + 1))
    assert store.pending_seeds(MAX_OUTBOX_LIMIT) == [
        SeedRecord(**d.model_dump(), id=i, machine_id="seeder-01")
        for i, d in zip(ids, written, strict=True)
    ]


def _payloads(store: RecordStore, limit: int = MAX_OUTBOX_LIMIT) -> tuple[list[int], bytes]:
    batch = store.pending_seed_batch(limit)
    assert batch is not None
    return batch.ids, batch.payload


def test_the_outbox_reads_the_same_records_from_memory_and_from_disk(tmp_path: Path) -> None:
    """The live link reads recent rows from memory; after a restart they come from SQLite.
    Both give the same bytes."""
    path = tmp_path / "r.sqlite3"
    odd = SeedDrop(row=3, utc=T0 + timedelta(seconds=1), lat=-0.000001, lon=-179.999999999,
                   fix="none", speed_kmh=0.0, heading_deg=359.999, extrapolated=True,
                   spacing_m=1e-9)
    with RecordStore(path, "m") as s:
        s.append_seeds([*drops(5), odd])
        s.flush()
        hot = _payloads(s)
    with RecordStore(path, "m") as s:
        cold = _payloads(s)
    assert hot == cold
    assert SeedBatch.model_validate_json(hot[1]).records[-1] == SeedRecord(
        **odd.model_dump(), id=6, machine_id="m")


def test_a_link_behind_the_memory_tail_reads_the_older_rows_from_disk(
    store: RecordStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only the newest rows stay in memory; a batch spanning the edge joins both, skipping
    what the broker already acknowledged."""
    monkeypatch.setattr("gateway.recording.store.outbox.TAIL_MAX_ROWS", 5)
    written = drops(12)
    for i in range(0, 12, 4):
        store.append_seeds(written[i:i + 4])
    store.flush()
    store.mark_seeds_delivered([3, 4, 9])
    # the link reads on a worker thread when SQLite is read, at once from the tail
    assert store.seeds_on_disk(after_id=0) and not store.seeds_on_disk(after_id=7)
    ids, payload = _payloads(store)
    assert ids == [1, 2, 5, 6, 7, 8, 10, 11, 12]
    assert SeedBatch.model_validate_json(payload).records == [
        SeedRecord(**written[i - 1].model_dump(), id=i, machine_id="seeder-01") for i in ids
    ]
    assert store.pending_seed_batch(4, after_id=6) is not None
    assert store.pending_seed_batch(4, after_id=6).ids == [7, 8, 10, 11]  # type: ignore[union-attr]
    assert store.count_pending_seeds(after_id=6) == 5


def test_acknowledgements_in_any_order_are_kept_as_a_few_ranges(tmp_path: Path) -> None:
    """Batches acknowledged out of order merge; what is on disk is a handful of ranges."""
    path = tmp_path / "r.sqlite3"
    with RecordStore(path, "m") as s:
        s.append_seeds(drops(10))
        s.flush()
        s.mark_seeds_delivered([5, 6, 7, 8])
        assert s.backlog() == 6
        s.mark_seeds_delivered([1, 2, 3, 4])
        s.mark_seeds_delivered([4, 5])  # a duplicate PUBACK changes nothing
        assert s.backlog() == 2
    with RecordStore(path, "m") as s:
        assert [r.id for r in s.pending_seeds(10)] == [9, 10]
        assert s.backlog() == 2
        assert sql(s, "SELECT tbl, lo, hi FROM delivered") == [("seeds", 1, 8)]


OLD_SCHEMA = """
CREATE TABLE seeds (
    id INTEGER PRIMARY KEY AUTOINCREMENT, utc_us INTEGER NOT NULL, row INTEGER NOT NULL,
    lat REAL NOT NULL, lon REAL NOT NULL, fix TEXT NOT NULL, speed_kmh REAL NOT NULL,
    heading_deg REAL, heading_source TEXT NOT NULL, extrapolated INTEGER NOT NULL,
    method TEXT NOT NULL, spacing_m REAL, delivered INTEGER NOT NULL DEFAULT 0);
CREATE INDEX seeds_pending ON seeds(id) WHERE delivered = 0;
CREATE INDEX seeds_utc ON seeds(utc_us);
CREATE TABLE alarms (
    id INTEGER PRIMARY KEY AUTOINCREMENT, utc_us INTEGER NOT NULL, code TEXT NOT NULL,
    active INTEGER NOT NULL, severity TEXT NOT NULL, message TEXT NOT NULL,
    delivered INTEGER NOT NULL DEFAULT 0);
CREATE INDEX alarms_pending ON alarms(id) WHERE delivered = 0;
"""


def test_a_store_from_an_older_version_keeps_its_delivery_marks(tmp_path: Path) -> None:
    """An upgrade on a box with a backlog neither resends what was delivered nor loses what
    was not: the per-row flags become ranges (ids 1-2 were pruned, so delivered)."""
    path = tmp_path / "r.sqlite3"
    db = sqlite3.connect(path)
    db.executescript(OLD_SCHEMA)
    for i in range(3, 11):
        db.execute(
            "INSERT INTO seeds VALUES (?, ?, 1, 52.0, 13.0, 'rtk_fixed', 8.0, NULL, 'none', 0, "
            "'interpolated', NULL, ?)", (i, i * 1_000_000, int(i in (3, 4, 7))),
        )
    for i, done in ((1, 1), (2, 0)):
        db.execute("INSERT INTO alarms VALUES (?, 0, 'radar.lost', 1, 'warning', 'x', ?)",
                   (i, done))
    db.commit()
    db.close()
    with RecordStore(path, "m", retention_days=1) as s:
        assert [r.id for r in s.pending_seeds(100)] == [5, 6, 8, 9, 10]
        assert [a.id for a in s.pending_alarms(10)] == [2]
        assert s.backlog() == 6
        assert "delivered" not in [c[1] for c in sql(s, "PRAGMA table_info(seeds)")]
        s.mark_seeds_delivered([5, 6])
        assert list(s.append_seeds(drops(1))) == [11]
        s.flush()
        assert s.prune(T0 + timedelta(hours=1)) == 5 + 1  # seeds 3-7, alarm 1
        assert [r.id for r in s.query_seeds()] == [8, 9, 10, 11]
    with RecordStore(path, "m") as s:
        assert [r.id for r in s.pending_seeds(100)] == [8, 9, 10, 11]
        assert sql(s, "SELECT name FROM sqlite_master WHERE name LIKE '%pending'") == []


class _CommitFailsAndRollsBack:
    """A connection whose COMMIT fails the way a full disk can: SQLite rolls the whole
    transaction back and reports the error. Everything else goes to the real connection."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db
        self.fail = True

    def execute(self, sql: str, *args: Any) -> Any:
        if sql == "COMMIT" and self.fail:
            self._db.execute("ROLLBACK")
            raise sqlite3.OperationalError("database or disk is full")
        return self._db.execute(sql, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)


def test_rows_of_a_rolled_back_commit_are_kept_and_published_only_once_committed(
    store: RecordStore,
) -> None:
    """The outbox's memory holds committed rows only: after a rolled-back commit the rows are
    held (not published, not lost) and written by the retry under the ids they were given,
    ahead of the rows that came after them."""
    real = store._db
    failing = _CommitFailsAndRollsBack(real)
    store._db = failing  # type: ignore[assignment]
    first = store.append_seeds(drops(3, row=1))
    with pytest.raises(StoreError, match="disk is full"):
        store.flush()
    assert store.pending_seeds(10) == [] and store.backlog() == 0
    assert store.records_held == 3 and store.failing
    again = store.append_seeds(drops(3, row=7))  # held too, behind them
    assert list(first) == [1, 2, 3] and list(again) == [4, 5, 6]
    failing.fail = False
    store.retry()
    assert [(r.id, r.row) for r in store.pending_seeds(10)] == [
        (1, 1), (2, 1), (3, 1), (4, 7), (5, 7), (6, 7)
    ]
    assert store.backlog() == 6 and store.records_held == 0 and not store.failing
    assert store.commit_error is None
    store._db = real


class _CommitFailsAndKeepsTheTransaction(_CommitFailsAndRollsBack):
    """A COMMIT that fails but leaves the transaction open (SQLite may do either)."""

    def execute(self, sql: str, *args: Any) -> Any:
        if sql == "COMMIT" and self.fail:
            raise sqlite3.OperationalError("database or disk is full")
        return self._db.execute(sql, *args)


def test_rows_of_a_commit_that_failed_but_stayed_open_reach_the_outbox_intact(
    store: RecordStore,
) -> None:
    """Rows the outbox had in memory, dropped when their commit failed, are read back from
    SQLite once the commit succeeds: every id comes with its own row."""
    store.append_seeds(drops(4, row=2))
    store.flush()
    real = store._db
    failing = _CommitFailsAndKeepsTheTransaction(real)
    store._db = failing  # type: ignore[assignment]
    store.append_seeds(drops(3, row=5))  # ids 5-7, in the transaction that cannot commit
    with pytest.raises(StoreError, match="disk is full"):
        store.flush()
    assert store.records_held == 3
    failing.fail = False
    store.retry()
    assert [(r.id, r.row) for r in store.pending_seeds(100)][4:] == [(5, 5), (6, 5), (7, 5)]
    failing.fail = True
    store.append_seeds(drops(2, row=9))  # ids 8-9: fail to commit again, then held
    with pytest.raises(StoreError, match="disk is full"):
        store.flush()
    failing.fail = False
    store.retry()
    got = [(r.id, r.row) for r in store.pending_seeds(100)]
    assert got == [(1, 2), (2, 2), (3, 2), (4, 2), (5, 5), (6, 5), (7, 5), (8, 9), (9, 9)]
    batch = store.pending_seed_batch(100)
    assert batch is not None and batch.ids == list(range(1, 10))
    assert [r.row for r in SeedBatch.model_validate_json(batch.payload).records] == [
        2, 2, 2, 2, 5, 5, 5, 9, 9
    ]
    store._db = real


def test_time_queries_find_seeds_through_the_spans_of_their_batches(store: RecordStore) -> None:
    """No index entry per seed: each appended batch records its id and time span, and a
    time-range query reads only the batches that overlap it, even when the receiver's time
    went backwards between batches (a time step)."""
    store.append_seeds(drops(5, start=T0))  # ids 1-5, T0 .. T0+40 ms
    store.append_seeds(drops(5, start=T0 + timedelta(hours=1)))  # ids 6-10
    store.append_seeds(drops(5, start=T0 - timedelta(hours=1)))  # ids 11-15: time stepped back
    store.flush()
    assert not sql(store, "SELECT 1 FROM sqlite_master WHERE type = 'index' AND tbl_name = 'seeds'")
    assert sql(store, "SELECT * FROM seed_spans ORDER BY first_id") == [
        (1, 5, utc_to_us(T0), utc_to_us(T0) + 40_000),
        (6, 10, utc_to_us(T0) + 3_600_000_000, utc_to_us(T0) + 3_600_040_000),
        (11, 15, utc_to_us(T0) - 3_600_000_000, utc_to_us(T0) - 3_599_960_000),
    ]

    def ids(since: datetime | None, until: datetime | None) -> list[int]:
        return [r.id for r in store.query_seeds(since, until)]

    assert ids(T0 + timedelta(milliseconds=20), T0 + timedelta(minutes=1)) == [3, 4, 5]
    assert ids(T0 + timedelta(minutes=59), None) == [6, 7, 8, 9, 10]
    assert ids(None, T0) == [11, 12, 13, 14, 15]
    assert ids(T0 + timedelta(hours=2), None) == []


def test_a_store_with_the_older_per_seed_time_index_gets_one_span_for_its_rows(
    tmp_path: Path,
) -> None:
    path = tmp_path / "r.sqlite3"
    with RecordStore(path, "m") as s:
        s.append_seeds(drops(6, start=T0))
        s.flush()
    db = sqlite3.connect(path)  # as an older sowgate left it: an index, no spans
    db.execute("DELETE FROM seed_spans")
    db.execute("CREATE INDEX seeds_utc ON seeds(utc_us)")
    db.commit()
    db.close()
    with RecordStore(path, "m") as s:
        assert sql(s, "SELECT * FROM seed_spans") == [
            (1, 6, utc_to_us(T0), utc_to_us(T0) + 50_000)
        ]
        assert sql(s, "SELECT 1 FROM sqlite_master WHERE name = 'seeds_utc'") == []
        s.append_seeds(drops(2, start=T0 + timedelta(seconds=1)))
        s.flush()
        got = [r.id for r in s.query_seeds(T0 + timedelta(milliseconds=30), None)]
        assert got == [4, 5, 6, 7, 8]


def test_pruning_drops_the_spans_of_batches_it_removed(tmp_path: Path) -> None:
    with RecordStore(tmp_path / "r.sqlite3", "m", retention_days=1) as s:
        old = s.append_seeds(drops(4, start=T0))
        s.append_seeds(drops(3, start=T0 + timedelta(days=3)))
        s.flush()
        s.mark_seeds_delivered(list(old))
        s.flush()
        assert s.prune(T0 + timedelta(days=3)) == 4
        assert sql(s, "SELECT first_id, last_id FROM seed_spans") == [(5, 7)]
        assert [r.id for r in s.query_seeds(T0 + timedelta(days=2), None)] == [5, 6, 7]


def _pre_terrain_schema() -> str:
    """The store's schema before records kept their attitude and re-positioning data."""
    from gateway.recording.store import _ADDED_SEED_COLUMNS, SCHEMA

    schema = SCHEMA.replace("spacing_m REAL,", "spacing_m REAL")
    for name, declaration, _ in _ADDED_SEED_COLUMNS:
        schema = schema.replace(f"    {name} {declaration},\n", "").replace(
            f"    {name} {declaration}\n", "")
    assert "roll_deg" not in schema and "offset_north_m" not in schema
    return schema


def _pre_terrain_store(path: Path) -> None:
    db = sqlite3.connect(path)
    db.executescript(_pre_terrain_schema())
    for i in range(1, 4):
        db.execute("INSERT INTO seeds VALUES (?, ?, 1, 52.0, 13.0, 'rtk_fixed', 8.0, 90.0, "
                   "'dual_antenna', 0, 'interpolated', NULL)", (i, i * 1_000_000))
    db.commit()
    db.close()


def test_an_older_store_read_only_reads_its_seeds_as_not_terrain_corrected(
    tmp_path: Path,
) -> None:
    path = tmp_path / "r.sqlite3"
    _pre_terrain_store(path)
    with RecordStore.open_readonly(path, "m") as s:
        records = list(s.query_seeds())
    assert [r.id for r in records] == [1, 2, 3]
    assert {(r.attitude, r.roll_deg, r.delay_ms, r.offset_east_m) for r in records} == {
        ("none", None, None, None)
    }


def test_an_older_store_gets_the_new_columns_and_keeps_its_seeds(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite3"
    _pre_terrain_store(path)
    new = drops(1)[0].model_copy(update={
        "attitude": "dual_antenna", "roll_deg": 3.0, "delay_ms": 105.0,
        "offset_east_m": -1.2, "offset_north_m": 0.4,
    })
    with RecordStore(path, "m") as s:
        assert list(s.append_seeds([new])) == [4]
        s.flush()
        records = list(s.query_seeds())
    assert [r.attitude for r in records] == ["none"] * 3 + ["dual_antenna"]
    last = records[-1]
    assert (last.roll_deg, last.delay_ms, last.offset_east_m, last.offset_north_m) == (
        3.0, 105.0, -1.2, 0.4)
    # the published payload carries the attitude, not the store-only raw data
    assert "delay_ms" not in last.model_dump() and last.model_dump()["roll_deg"] == 3.0


def test_no_single_wrong_clock_makes_pruning_delete_anything(store: RecordStore) -> None:
    """Age is counted back from the earlier of the host clock and the newest record's own
    time: a receiver past a GPS week rollover (new records 1024 weeks early) or a host clock
    years ahead leaves every record where it is (issue 20 item 4: 1 599 of 1 717 delivered
    records were deleted)."""
    recent = store.add_seeds(drops(3))
    early = store.add_seeds(drops(3, start=T0 - timedelta(weeks=1024)))
    store.flush()
    store.mark_seeds_delivered([r.id for r in recent + early])
    assert store.prune(T0 + timedelta(days=40)) == 0
    assert store.prune(T0 + timedelta(days=3650)) == 0
    assert len(list(store.query_seeds())) == 6


def test_a_record_stamped_in_the_past_out_of_turn_waits_for_those_before_it(
    store: RecordStore,
) -> None:
    """Only a prefix in id order is pruned: one batch with a bad old date among recent ones
    is not deleted ahead of its neighbours."""
    first = store.add_seeds(drops(2, start=T0))
    bad = store.add_seeds(drops(2, start=T0 - timedelta(days=400)))
    last = store.add_seeds(drops(2, start=T0 + timedelta(hours=1)))
    store.flush()
    store.mark_seeds_delivered([r.id for r in first + bad + last])
    assert store.prune(T0 + timedelta(hours=2)) == 0
    assert [r.id for r in store.query_seeds()] == [r.id for r in first + bad + last]
