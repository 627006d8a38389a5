"""The MQTT outbox over the store: what is committed and not yet acknowledged by the broker.

Owns the acknowledged id ranges (``delivered``, merged in memory and written by the writer at
its next commit), the in-memory tail of recently committed rows (the live link renders them
straight to JSON; SQLite is read only for a backlog older than the tail, after an outage or a
restart) and the backlog alarm. Only committed rows are ever returned, so nothing leaves the
box that a crash could take back.

Everything here runs on the event loop's thread and touches memory only, except the cold read
of a backlog older than the tail (on the read connection; a writer stalled on the card never
holds it).
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from gateway.core.records import AlarmEvent, SeedRecord, SeedRow, seed_batch_json, us_to_utc
from gateway.recording.id_ranges import IdRanges

# Rows the outbox can read from memory: about 5 s of a 48-row planter at 16 km/h (~3 MB). A
# link further behind than that reads SQLite, as after an outage.
TAIL_MAX_ROWS = 10_000
MAX_OUTBOX_LIMIT = 10_000  # one outbox read never materialises more than this many records

BacklogCallback = Callable[[int, bool], None]


@dataclass(frozen=True)
class OutboxBatch:
    """Ids and the ready-to-publish ``SeedBatch`` JSON for them (the MQTT hot path)."""

    ids: list[int]
    payload: bytes


class Outbox:
    """The outbox side of ``RecordStore`` (a mixin over the store's state)."""

    machine_id: str
    backlog_alarm_records: int
    on_backlog: BacklogCallback | None
    _lock: threading.Lock
    _acked: dict[str, IdRanges]
    _acked_version: int  # bumped by every change of _acked (the writer writes what changed)
    _visible_seed_id: int
    _visible_alarm_id: int
    _tail: list[SeedRow]
    _tail_first: int
    _pending_seeds: int
    _pending_alarms: int
    _backlog_over: bool
    _seed_columns: str

    @property
    def _reader(self) -> sqlite3.Connection:
        raise NotImplementedError

    def _seed(self, r: tuple[Any, ...]) -> SeedRecord:
        raise NotImplementedError

    def _wake_writer(self) -> None:
        raise NotImplementedError

    def _remember(self, first: int, rows: Sequence[SeedRow]) -> None:
        """Keep committed rows in the tail (bounded by ``TAIL_MAX_ROWS``); under the lock."""
        tail = self._tail
        if first != self._tail_first + len(tail):  # not contiguous: start the tail afresh
            tail.clear()
            self._tail_first = first
        tail.extend(rows)
        excess = len(tail) - TAIL_MAX_ROWS
        if excess > 0:
            del tail[:excess]
            self._tail_first += excess

    def _undelivered(self, limit: int, after_id: int) -> tuple[list[int], list[SeedRow]]:
        """Ids and rows of up to ``limit`` committed, undelivered seeds after ``after_id``.

        From the in-memory tail where it reaches, from SQLite below it.
        """
        limit = max(0, min(limit, MAX_OUTBOX_LIMIT))
        ids: list[int] = []
        rows: list[SeedRow] = []
        with self._lock:
            gaps = list(self._acked["seeds"].gaps(after_id, self._visible_seed_id))
            tail_first, tail = self._tail_first, list(self._tail)
        for lo, hi in gaps:
            need = limit - len(ids)
            if need <= 0:
                break
            if lo < tail_first:
                cold = self._reader.execute(
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
            rows.extend(tail[lo - tail_first : hi - tail_first + 1])
        return ids, rows

    def seeds_on_disk(self, after_id: int = 0) -> bool:
        """Whether the next read after ``after_id`` reads SQLite (a backlog older than the
        in-memory tail): the MQTT link then reads on a worker thread, so a card that stalls
        never holds up the event loop (and with it the control loop)."""
        with self._lock:
            for lo, _ in self._acked["seeds"].gaps(after_id, self._visible_seed_id):
                return lo < self._tail_first
        return False

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
        with self._lock:
            gaps = list(self._acked["seeds"].gaps(after_id, self._visible_seed_id))
        for lo, hi in gaps:
            n += hi - lo + 1
            if n >= cap:
                return max(0, cap)
        return n

    def pending_seed_batch(self, limit: int, after_id: int = 0) -> OutboxBatch | None:
        """Like ``pending_seeds`` but straight to ``SeedBatch`` JSON (the MQTT hot path).

        Equals ``SeedBatch(...).model_dump_json()`` value for value (tested); see
        ``seed_batch_json`` for why it builds no models.
        """
        oldest = self.oldest_pending_seed_id()  # first: a watermark may only raise it
        ids, rows = self._undelivered(limit, after_id)
        if not ids:
            return None
        # the farm server learns which ids it will never get (SeedBatch.pending_from)
        pending_from = ids[0] if oldest is None else min(oldest, ids[0])
        return OutboxBatch(ids, seed_batch_json(self.machine_id, ids, rows, pending_from))

    def pending_alarms(self, limit: int, after_id: int = 0) -> list[AlarmEvent]:
        limit = max(0, min(limit, MAX_OUTBOX_LIMIT))
        rows: list[Any] = []
        with self._lock:
            gaps = list(self._acked["alarms"].gaps(after_id, self._visible_alarm_id))
        for lo, hi in gaps:
            if len(rows) >= limit:
                break
            rows.extend(self._reader.execute(
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
        with self._lock:
            acked = self._acked[table]
            changed = acked.add_ids(ids)
            if changed:
                self._acked_version += 1
                if table == "seeds":  # the tail never needs what was acknowledged from its start
                    done = acked.through() - self._tail_first + 1
                    if done > 0:
                        del self._tail[:done]
                        self._tail_first += done
        if changed:
            self._wake_writer()
        return changed

    def mark_seeds_delivered(self, ids: Sequence[int]) -> None:
        """Called on PUBACK. Committed with the next write; a crash before it means a resend."""
        changed = self._mark("seeds", ids)
        with self._lock:
            self._pending_seeds -= changed
        self._check_backlog()

    def mark_seed_ranges_delivered(self, ranges: Sequence[tuple[int, int]]) -> int:
        """The farm server's watermark (``[mqtt] farm_server_ack``): these inclusive id ranges
        are committed farm-side. Only ids this store has handed out count (a watermark from a
        database that knew an older box with the same machine id must not mark ids to come).
        Returns how many ids were newly marked."""
        new = 0
        with self._lock:
            ceiling, acked = self._visible_seed_id, self._acked["seeds"]
            for lo, hi in ranges:
                lo, hi = max(1, lo), min(hi, ceiling)
                if lo <= hi:
                    new += acked.add(lo, hi)
            if new:
                self._acked_version += 1
                done = acked.through() - self._tail_first + 1
                if done > 0:
                    del self._tail[:done]
                    self._tail_first += done
                self._pending_seeds -= new
        if new:
            self._wake_writer()
            self._check_backlog()
        return new

    def oldest_pending_seed_id(self) -> int | None:
        """The lowest committed id not yet delivered (None when all are)."""
        with self._lock:
            for lo, _hi in self._acked["seeds"].gaps(0, self._visible_seed_id):
                return lo
        return None

    def mark_alarms_delivered(self, ids: Sequence[int]) -> None:
        changed = self._mark("alarms", ids)
        with self._lock:
            self._pending_alarms -= changed

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
