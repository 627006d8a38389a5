"""Reading the store back: exports, reports and calibration (``sowgate export``, ``report``,
``calibrate-positions``), usually on a read-only store next to a running daemon.

Owns the time-range lookups through ``seed_spans`` and the streamed, chunked readers; writes
nothing.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator, Sequence
from datetime import datetime
from typing import Any

from gateway.core.records import (
    AlarmEvent,
    SeedRecord,
    stated_accuracy_m,
    us_to_utc,
    utc_to_us,
)
from gateway.recording.store.schema import StoredSeedRow, fast_record, has_table, max_id

QUERY_CHUNK_ROWS = 5000  # rows fetched per step by query_seed_rows, so exports stream
_ALL = (-(2**63), 2**63 - 1)


class StoreQueries:
    """The readers of ``RecordStore`` (a mixin: it reads the store's read connection)."""

    machine_id: str
    readonly: bool
    _seed_columns: str
    _visible_seed_id: int

    @property
    def _reader(self) -> sqlite3.Connection:
        raise NotImplementedError

    def _seed(self, r: tuple[Any, ...]) -> SeedRecord:
        return seed_from_stored(r, self.machine_id)

    def _span_ids(self, since_us: int | None, until_us: int | None) -> tuple[int, int] | None:
        """The id range holding every seed with ``since <= utc < until`` (None: no seed).

        From the spans of appended batches; an older store opened read-only, not converted
        yet, has none and is scanned whole (it still has its time index)."""
        db = self._reader
        if not has_table(db, "seed_spans"):
            return 0, max_id(db, "seeds")
        row = db.execute(
            "SELECT MIN(first_id), MAX(last_id) FROM seed_spans "
            "WHERE max_utc_us >= ? AND min_utc_us < ?",
            (_ALL[0] if since_us is None else since_us, _ALL[1] if until_us is None else until_us),
        ).fetchone()
        if row is None or row[0] is None:
            return None
        return int(row[0]) - 1, int(row[1])

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
        db = self._reader
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
        ceiling = self._visible_seed_id if not self.readonly else max_id(db, "seeds")
        after = 0
        if since_us is not None or until_us is not None:
            span = self._span_ids(since_us, until_us)
            if span is None:
                return
            after, ceiling = max(after, span[0]), min(ceiling, span[1])
        while True:
            chunk = db.execute(sql, (after, ceiling, *args, QUERY_CHUNK_ROWS)).fetchall()
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
        db = self._reader
        lo = _ALL[0] if since is None else utc_to_us(since)
        hi = _ALL[1] if until is None else utc_to_us(until)
        if has_table(db, "seed_spans"):
            row = db.execute(
                "SELECT MIN(min_utc_us), MAX(max_utc_us) FROM seed_spans "
                "WHERE max_utc_us >= ? AND min_utc_us < ?",
                (lo, hi),
            ).fetchone()
        else:
            row = db.execute(
                "SELECT MIN(utc_us), MAX(utc_us) FROM seeds WHERE utc_us >= ? AND utc_us < ?",
                (lo, hi),
            ).fetchone()
        if row is None or row[0] is None:
            return None
        first, last = int(row[0]), int(row[1])
        if has_table(db, "seed_spans") and (first < lo or last >= hi):
            # a batch crosses a bound: read that batch's seeds for the exact first or last
            # time (a few hundred rows), so the span, and the report's time bins built on
            # it, are the records' own whatever source holds them (the farm database too)
            first, last = self._exact_edge(first, lo, hi, True), \
                self._exact_edge(last, lo, hi, False)
            if first > last:
                return None
        return max(first, lo), min(last, hi - 1)

    def _exact_edge(self, bound: int, lo: int, hi: int, low: bool) -> int:
        db = self._reader
        edge = lo if low else hi
        if (low and bound >= lo) or (not low and bound < hi):
            return bound
        # the other batches' own extremes inside the window, and the crossing ones read
        inside = db.execute(
            "SELECT MIN(min_utc_us) FROM seed_spans WHERE min_utc_us >= ? AND min_utc_us < ?"
            if low else
            "SELECT MAX(max_utc_us) FROM seed_spans WHERE max_utc_us >= ? AND max_utc_us < ?",
            (lo, hi)).fetchone()[0]
        ids = db.execute(
            "SELECT MIN(first_id), MAX(last_id) FROM seed_spans "
            "WHERE min_utc_us < ? AND max_utc_us >= ?", (edge, edge)).fetchone()
        crossing = db.execute(
            f"SELECT {'MIN' if low else 'MAX'}(utc_us) FROM seeds "
            "WHERE id >= ? AND id <= ? AND utc_us >= ? AND utc_us < ?",
            (ids[0], ids[1], lo, hi)).fetchone()[0] if ids[0] is not None else None
        found = [int(v) for v in (inside, crossing) if v is not None]
        if not found:
            return hi if low else lo - 1  # no seed in the window at all: first > last
        return min(found) if low else max(found)

    def query_alarms(
        self, since: datetime | None = None, until: datetime | None = None
    ) -> Iterator[AlarmEvent]:
        """Stored alarm events in id order, ``since <= utc < until`` (a chunk at a time)."""
        db = self._reader
        lo = _ALL[0] if since is None else utc_to_us(since)
        hi = _ALL[1] if until is None else utc_to_us(until)
        after = 0
        while True:
            chunk = db.execute(
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

    def integrity_check(self) -> str:
        return str(self._reader.execute("PRAGMA integrity_check").fetchone()[0])


def seed_from_stored(r: StoredSeedRow, machine_id: str) -> SeedRecord:
    """A ``SeedRecord`` from a stored tuple (``STORED_SEED_COLUMNS``), whichever reader made it
    (the cab's store or the farm database): one mapping, so both give the same record.

    Rows were validated as SeedDrops on the way in; no re-validation on the hot path."""
    return fast_record({
        "row": r[2], "utc": us_to_utc(r[1]), "lat": r[3], "lon": r[4], "fix": r[5],
        "speed_kmh": r[6], "heading_deg": r[7], "heading_source": r[8],
        "extrapolated": bool(r[9]), "method": r[10], "spacing_m": r[11],
        "attitude": r[12], "roll_deg": r[13], "pitch_deg": r[14], "delay_ms": r[15],
        "offset_east_m": r[16], "offset_north_m": r[17],
        "accuracy_m": stated_accuracy_m(r[5], bool(r[9])), "id": r[0],
        "machine_id": machine_id,
    })
