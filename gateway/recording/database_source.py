"""One machine's records in the farm server's PostgreSQL, read as a ``RecordSource``.

``sowgate report|export --database URL --machine M [--since] [--until]`` read the tables
``sowgate ingest`` writes (``seed_records``, ``alarm_events``; docs/farm-server.md) through
this class, and the report and export code cannot tell it from the cab's record store: the
rows come back as the store's tuples (``STORED_SEED_COLUMNS``), in id order, a chunk at a
time from a server-side cursor (a day of a planter never sits in memory).

Everything is read in one read-only REPEATABLE READ transaction: the report's two passes
(statistics, then the map) and the export's (quality, then the features) see the same rows
even while ingest keeps committing. Every value reaches PostgreSQL as a bound parameter.

What the database does not hold: the fields the cab keeps for re-positioning only
(``delay_ms``, the offsets: never published), so ``--reposition`` needs the record store;
and the daemon's runs (start/stop markers), so ``runs()`` is empty: an alarm still active
when the daemon stopped reads as open to the end of the window, and without a configured
``positioning.target_spacing_m`` each row's median is the reference.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from datetime import datetime
from types import TracebackType
from typing import Any

import psycopg
from psycopg.rows import TupleRow

from gateway.core.records import AlarmEvent, SeedRecord
from gateway.recording.runs import Run
from gateway.recording.store.queries import QUERY_CHUNK_ROWS, seed_from_stored
from gateway.recording.store.schema import StoredSeedRow, StoreError

# The store's STORED_SEED_COLUMNS, from the farm server's seed_records (its MQTT names):
# the three re-positioning fields are not published, so NULL here as in an older store.
_SELECT = (
    'SELECT id, (extract(epoch FROM utc) * 1000000)::bigint, "row", lat, lon, fix, '
    "speed_kmh, heading_deg, heading_source, extrapolated, method, spacing_m, attitude, "
    "roll_deg, pitch_deg, NULL::float8, NULL::float8, NULL::float8 FROM seed_records "
    "WHERE machine_id = %(machine)s "
    "AND (%(since)s::timestamptz IS NULL OR utc >= %(since)s) "
    "AND (%(until)s::timestamptz IS NULL OR utc < %(until)s) "
    'AND (%(rows)s::int[] IS NULL OR "row" = ANY(%(rows)s)) ORDER BY id'
)
_names = itertools.count(1)


class DatabaseSource:
    """The ``RecordSource`` of machine ``machine_id`` in the farm database at ``url``."""

    def __init__(self, url: str, machine_id: str) -> None:
        self.url = url
        self.machine_id = machine_id
        self.readonly = True
        try:
            self.conn: psycopg.Connection[TupleRow] = psycopg.connect(
                url, connect_timeout=10, options="-c TimeZone=UTC")
        except psycopg.Error as exc:
            raise StoreError(f"--database: cannot connect: {str(exc).strip()}") from None
        self.conn.isolation_level = psycopg.IsolationLevel.REPEATABLE_READ
        self.conn.read_only = True
        try:
            self.conn.execute("SELECT 1 FROM seed_records LIMIT 0")
        except psycopg.errors.UndefinedTable:
            self.conn.close()
            raise StoreError("--database: no sowgate farm-server tables in this database "
                             "(`sowgate ingest` creates them)") from None

    def __enter__(self) -> DatabaseSource:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        self.conn.close()

    def _stream(self, sql: str, params: dict[str, Any]) -> Iterator[list[tuple[Any, ...]]]:
        try:
            with self.conn.cursor(name=f"sowgate_read_{next(_names)}") as cur:
                cur.itersize = QUERY_CHUNK_ROWS
                cur.execute(sql.encode(), params)
                while chunk := cur.fetchmany(QUERY_CHUNK_ROWS):
                    yield chunk
        except psycopg.Error as exc:
            raise StoreError(f"cannot read the farm database: {str(exc).strip()}") from None

    def _params(self, since: datetime | None, until: datetime | None,
                rows: Sequence[int] | None = None) -> dict[str, Any]:
        return {"machine": self.machine_id, "since": since, "until": until,
                "rows": None if rows is None else sorted({int(r) for r in rows})}

    def query_seed_rows(
        self,
        since: datetime | None = None,
        until: datetime | None = None,
        rows: Sequence[int] | None = None,
    ) -> Iterator[list[StoredSeedRow]]:
        if rows is not None and not rows:
            return
        yield from self._stream(_SELECT, self._params(since, until, rows))

    def query_seeds(
        self,
        since: datetime | None = None,
        until: datetime | None = None,
        rows: Sequence[int] | None = None,
    ) -> Iterator[SeedRecord]:
        for chunk in self.query_seed_rows(since, until, rows):
            for r in chunk:
                yield seed_from_stored(r, self.machine_id)

    def seed_time_span(
        self, since: datetime | None = None, until: datetime | None = None
    ) -> tuple[int, int] | None:
        try:
            row = self.conn.execute(
                b"SELECT (extract(epoch FROM min(utc)) * 1000000)::bigint, "
                b"(extract(epoch FROM max(utc)) * 1000000)::bigint FROM seed_records "
                b"WHERE machine_id = %(machine)s "
                b"AND (%(since)s::timestamptz IS NULL OR utc >= %(since)s) "
                b"AND (%(until)s::timestamptz IS NULL OR utc < %(until)s)",
                self._params(since, until),
            ).fetchone()
        except psycopg.Error as exc:
            raise StoreError(f"cannot read the farm database: {str(exc).strip()}") from None
        if row is None or row[0] is None:
            return None
        return int(row[0]), int(row[1])

    def query_alarms(
        self, since: datetime | None = None, until: datetime | None = None
    ) -> Iterator[AlarmEvent]:
        sql = ("SELECT id, utc, code, active, severity, message FROM alarm_events "
               "WHERE machine_id = %(machine)s "
               "AND (%(since)s::timestamptz IS NULL OR utc >= %(since)s) "
               "AND (%(until)s::timestamptz IS NULL OR utc < %(until)s) ORDER BY id")
        for chunk in self._stream(sql, self._params(since, until)):
            for i, utc, code, active, severity, message in chunk:
                yield AlarmEvent(id=i, machine_id=self.machine_id, code=code, active=active,
                                 severity=severity, message=message, utc=utc)

    def runs(self) -> list[Run]:
        return []  # the database keeps no daemon runs (see the module doc)
