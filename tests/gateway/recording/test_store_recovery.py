"""Ids survive what a power cut or a bad card does to the store, and a damaged store never
stops the daemon: it is moved aside, kept, and a new store continues the ids.

The damage is real: the store's files are cut, emptied or overwritten on disk the way a lost
WAL, a card whose cache lied or a torn write leaves them.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import sqlite3
import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from gateway.core.records import SeedDrop
from gateway.recording.store import ID_BLOCK, IdReservation, RecordStore
from gateway.recording.store.ids import reservation_path
from tests.helpers import eventually

T0 = datetime(2026, 4, 20, 8, 0, tzinfo=UTC)


def drops(n: int) -> list[SeedDrop]:
    return [
        SeedDrop(row=1 + i % 4, utc=T0 + timedelta(milliseconds=10 * i), lat=52.0 + i * 1e-7,
                 lon=13.0, fix="rtk_fixed", speed_kmh=8.0)
        for i in range(n)
    ]


def committed_ids(store: RecordStore, n: int) -> list[int]:
    ids = [r.id for r in store.add_seeds(drops(n))]
    store.flush()
    return ids


def moved_aside(path: Path) -> list[Path]:
    """The store files moved aside (their -wal and -shm go with them)."""
    return sorted(p for p in path.parent.iterdir()
                  if ".bad-" in p.name and not p.name.endswith(("-wal", "-shm")))


# -- the reservation ------------------------------------------------------------------------


def test_the_reservation_is_written_once_a_block_and_read_back(tmp_path: Path) -> None:
    ids = IdReservation(tmp_path / "r.ids", block=100)
    ids.cover("seeds", 1)  # reserved through 101
    ids.cover("seeds", 51)  # half a block still ahead: no write
    assert ids.writes == 1
    ids.cover("seeds", 52)  # less than half a block ahead: renewed
    assert ids.writes == 2
    assert json.loads((tmp_path / "r.ids").read_text()) == {"seeds": 152}
    again = IdReservation(tmp_path / "r.ids", block=100)
    assert again.next_id("seeds", store_max_id=150) == 153
    assert again.next_id("seeds", store_max_id=500) == 501
    assert again.next_id("alarms", store_max_id=7) == 8
    assert not (tmp_path / "r.ids.tmp").exists()


def test_a_clean_close_lowers_the_reservation_to_what_was_committed(tmp_path: Path) -> None:
    path = tmp_path / "records.sqlite3"
    with RecordStore(path, "m") as s:
        assert committed_ids(s, 5) == [1, 2, 3, 4, 5]
        assert IdReservation(reservation_path(path)).end("seeds") == 5 + ID_BLOCK
    assert IdReservation(reservation_path(path)).end("seeds") == 5
    with RecordStore(path, "m") as s:
        assert s.unclean_stop is None
        assert committed_ids(s, 2) == [6, 7]  # an ordinary restart: no gap


def test_an_unreadable_reservation_leaves_the_store_s_own_mark(tmp_path: Path) -> None:
    path = tmp_path / "records.sqlite3"
    with RecordStore(path, "m") as s:
        committed_ids(s, 3)
    reservation_path(path).write_bytes(b"\0\0garbage")
    with RecordStore(path, "m") as s:
        assert committed_ids(s, 1) == [4]


# -- a power cut ------------------------------------------------------------------------------


def power_cut_copy(path: Path, to: Path, *, with_wal: bool) -> Path:
    """What the card holds after a power cut: the store's main file (and its WAL or not),
    and the id reservation, copied while the writer is still running (never closed)."""
    to.mkdir()
    shutil.copy(path, to / path.name)
    if with_wal:
        shutil.copy(path.with_name(path.name + "-wal"), to / (path.name + "-wal"))
    shutil.copy(reservation_path(path), reservation_path(to / path.name))
    return to / path.name


def test_a_lost_wal_never_gives_a_published_id_again(tmp_path: Path) -> None:
    """The WAL lost after a hard stop takes committed (publishable) records with it; the
    next ids start above every id handed out, and the ids skipped are not waited for."""
    path = tmp_path / "a" / "records.sqlite3"
    s = RecordStore(path, "m")
    before = committed_ids(s, 50)
    s.sync()  # checkpointed into the main file
    lost = committed_ids(s, 70)  # only in the WAL
    after_cut = power_cut_copy(path, tmp_path / "b", with_wal=False)
    s.close()
    with RecordStore(after_cut, "m") as t:
        assert t.unclean_stop is not None and "skipped" in t.unclean_stop
        assert [r.id for r in t.query_seeds()] == before
        new = committed_ids(t, 5)
        assert min(new) > max(lost)
        assert [r.id for r in t.pending_seeds(1000)] == before + new


def test_losing_the_last_seconds_of_writes_never_reuses_their_ids(tmp_path: Path) -> None:
    """A card whose cache lied: the store as it was a few commits ago."""
    path = tmp_path / "a" / "records.sqlite3"
    s = RecordStore(path, "m")
    committed_ids(s, 30)
    earlier = power_cut_copy(path, tmp_path / "b", with_wal=True)
    later = committed_ids(s, 200)
    s.close()
    with RecordStore(earlier, "m") as t:
        assert max(r.id for r in t.query_seeds()) == 30
        assert min(committed_ids(t, 3)) > max(later)


# -- a damaged store ----------------------------------------------------------------------------


def damage_zero_length(path: Path) -> None:
    path.write_bytes(b"")


def damage_truncated(path: Path) -> None:
    os.truncate(path, path.stat().st_size // 2)


def damage_one_page(path: Path) -> None:
    with path.open("r+b") as f:
        f.seek(4096 * 2)
        f.write(bytes(range(256)) * 16)


def damage_not_a_database(path: Path) -> None:
    path.write_bytes(b"this is a text file, not SQLite\n" * 200)


@pytest.mark.parametrize("damage", [damage_zero_length, damage_truncated, damage_one_page,
                                    damage_not_a_database])
def test_a_damaged_store_is_moved_aside_and_a_new_one_continues_the_ids(
    tmp_path: Path, damage: Any
) -> None:
    path = tmp_path / "records.sqlite3"
    with RecordStore(path, "m") as s:
        old = committed_ids(s, 3000)
        s.mark_seeds_delivered(old[:1000])
        s.flush()
    damage(path)
    content = path.read_bytes()
    with RecordStore(path, "m") as s:
        assert s.replaced is not None
        (kept,) = moved_aside(path)
        assert s.replaced.moved_to == kept
        assert kept.read_bytes() == content  # kept as it was, for whoever wants it
        assert "records.sqlite3.bad-" in s.state().replaced
        # what can still be read of the undelivered records is copied, under its ids
        salvaged = [r.id for r in s.pending_seeds(5000)]
        assert set(salvaged) <= set(old[1000:])
        assert s.replaced.salvaged == len(salvaged)
        if damage is damage_one_page:  # (SQLite reads nothing of a truncated file)
            assert len(salvaged) >= 500
        new = committed_ids(s, 2)
        assert min(new) > max(old)
        assert s.integrity_check() == "ok"
        # nothing waited for below them but what was copied
        assert [r.id for r in s.pending_seeds(5000)] == salvaged + new
    with RecordStore(path, "m") as s:  # the new store passes its check
        assert s.replaced is None


def test_a_healthy_store_is_left_where_it_is(tmp_path: Path) -> None:
    path = tmp_path / "records.sqlite3"
    with RecordStore(path, "m") as s:
        committed_ids(s, 10)
    with RecordStore(path, "m") as s:
        assert s.replaced is None
        assert moved_aside(path) == []


# -- a card that stalls ----------------------------------------------------------------------


class _StallingCommits:
    """The write connection, whose COMMIT blocks until released (a frozen card)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db
        self.stall = threading.Event()
        self.release = threading.Event()

    def execute(self, sql: str, *args: Any) -> Any:
        if sql == "COMMIT" and self.stall.is_set():
            self.release.wait(30)
        return self._db.execute(sql, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)


async def test_a_stalled_card_never_holds_up_the_caller(tmp_path: Path) -> None:
    """While a commit hangs, records are still accepted at once (held, counted), the store
    says it stalls, and everything is written once the card answers."""
    store = RecordStore(tmp_path / "records.sqlite3", "m", stall_s=0.2)
    stalling = _StallingCommits(store._db)  # type: ignore[arg-type]
    store._db = stalling  # type: ignore[assignment]
    task = asyncio.create_task(store.run())
    await asyncio.sleep(0)  # run() starts the writer thread
    try:
        first = list(store.append_rows(_rows(10)))
        store.commit_soon()
        await eventually(lambda: store.backlog() == 10, 10.0, "the first commit")
        stalling.stall.set()
        held = list(store.append_rows(_rows(500)))
        store.commit_soon()
        await eventually(lambda: store.stalled, 10.0, "the stall noticed")
        more = list(store.append_rows(_rows(500)))  # returns at once, the writer is stuck
        assert store.records_held == 1000
        assert store.state().stalled
        stalling.release.set()
        store.commit_soon()
        await eventually(lambda: store.backlog() == 1010, 10.0, "the held records written")
        assert not store.stalled and store.records_held == 0
    finally:
        stalling.release.set()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        store.close()
    assert first + held + more == list(range(1, 1011))


def _rows(n: int) -> list[tuple[Any, ...]]:
    from gateway.core.records import drop_row

    return [drop_row(d) for d in drops(n)]


class _CorruptOnCommit:
    """The write connection, whose next COMMIT reports the file damaged (SQLITE_CORRUPT)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def execute(self, sql: str, *args: Any) -> Any:
        if sql == "COMMIT":
            self._db.execute("ROLLBACK")
            raise sqlite3.DatabaseError("database disk image is malformed")
        return self._db.execute(sql, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)


def test_a_store_found_damaged_while_writing_is_replaced_and_nothing_queued_is_lost(
    tmp_path: Path,
) -> None:
    path = tmp_path / "records.sqlite3"
    with RecordStore(path, "m") as s:
        first = committed_ids(s, 10)
        s.mark_seeds_delivered(first)
        s._db = _CorruptOnCommit(s._db)  # type: ignore[arg-type,assignment]
        queued = [r.id for r in s.add_seeds(drops(5))]
        s.flush()  # the commit fails as corrupt: moved aside, written to a new store
        assert s.replaced is not None and s.replaced.moved_to is not None
        assert s.replaced.moved_to.exists() and not s.failing
        assert [r.id for r in s.query_seeds()] == queued
        assert [r.id for r in s.pending_seeds(100)] == queued
        assert min(committed_ids(s, 1)) > max(queued)
    with RecordStore(path, "m") as s:
        assert s.replaced is None
        assert [r.id for r in s.pending_seeds(100)][:5] == queued
