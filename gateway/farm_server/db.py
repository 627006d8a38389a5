"""All of the farm server's PostgreSQL I/O: schema and its migration, batched binary COPY,
and the per-machine coverage of committed seed ids that the watermark is computed from.

Exactly once. At-least-once delivery, replays and two ingest processes in a share group
all hand us records twice. A flush is one write transaction for every machine in it: it
takes the machines' advisory locks (in key order, so two ingest processes never deadlock),
reads their committed id ranges (``seed_coverage``), drops every record already covered,
binary-COPYs the rest straight into ``seed_records`` (the PostGIS point sent as EWKB), then
merges the new ids into ``seed_coverage`` before the one commit. So the coverage is what the
database holds, in the same transaction, and the watermark published after the commit is
never ahead of it. The unique key is the backstop: should the table ever hold a row the
coverage does not list, the COPY fails on it and the transaction is done again through a
temporary staging table and ``INSERT … ON CONFLICT DO NOTHING``.

Partitions. ``seed_records``, ``alarm_events`` and ``state_samples`` are partitioned by day
(native range partitioning on ``utc``, BRIN on ``utc``). Days are created on demand through
``sowgate_ensure_day(date)``, a SECURITY DEFINER function owned by the schema owner, so the
ingest user needs no CREATE privilege (docs/farm-server.md lists its GRANTs). A partitioned
table's unique key must contain the partition key: it is ``(machine_id, id, utc)``; ids are
never reused and a record's time never changes, and the coverage check above refuses a
replayed id whatever its time, so no id is stored twice.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, date, datetime

import psycopg
from psycopg import sql
from psycopg.rows import TupleRow

from gateway.core.records import AlarmEvent, SeedRecord
from gateway.farm_server.rows import COPY_SIGNATURE, COPY_TRAILER, SeedRows, rows_of_records
from gateway.link.payloads import StatePayload
from gateway.recording.id_ranges import IdRanges

log = logging.getLogger(__name__)

SCHEMA_VERSION = 2


class SchemaError(Exception):
    """The database's schema is one this ingest cannot write (newer, or not ours)."""


# (MQTT name, PostgreSQL type): seed_records has a column per published field, in this order,
# but for ``accuracy_m``: the receiver's stated accuracy is a function of ``fix`` and
# ``extrapolated`` (``gateway.core.records.stated_accuracy_m``), derived again on reading, as
# the cab's own store does
SEED_COLUMNS: tuple[tuple[str, str], ...] = (
    ("machine_id", "text"), ("id", "bigint"), ("row", "smallint"), ("utc", "timestamptz"),
    ("lat", "double precision"), ("lon", "double precision"), ("fix", "text"),
    # double precision, as published (JSON) and stored on the cab: a report or export read
    # from the database gives the cab's numbers to the last digit (float4 would not)
    ("speed_kmh", "double precision"), ("heading_deg", "double precision"),
    ("heading_source", "text"), ("extrapolated", "boolean"), ("method", "text"),
    ("spacing_m", "double precision"), ("attitude", "text"),
    ("roll_deg", "double precision"), ("pitch_deg", "double precision"),
)
_NOT_NULL = {"machine_id", "id", "row", "utc", "lat", "lon", "fix", "speed_kmh",
             "heading_source", "extrapolated", "method", "attitude"}
ALARM_COLUMNS: tuple[tuple[str, str], ...] = (
    ("machine_id", "text"), ("id", "bigint"), ("utc", "timestamptz"), ("code", "text"),
    ("active", "boolean"), ("severity", "text"), ("message", "text"),
)
PARTITIONED = ("seed_records", "alarm_events", "state_samples")


# what the seed COPY sends: every published field, then the point as EWKB; the rows come
# ready in binary COPY format (``gateway.farm_server.rows``)
_SEED_NAMES = sql.SQL(", ").join(sql.Identifier(n) for n, _ in SEED_COLUMNS)
_COPY_SEEDS = sql.SQL("COPY seed_records ({}, geom) FROM STDIN (FORMAT BINARY)").format(
    _SEED_NAMES)
_COPY_STAGING = sql.SQL("COPY seed_staging ({}, geom) FROM STDIN (FORMAT BINARY)").format(
    _SEED_NAMES)
_INSERT_FROM_STAGING = sql.SQL(
    "INSERT INTO seed_records ({names}, geom) SELECT {names}, geom FROM seed_staging "
    "ON CONFLICT DO NOTHING").format(names=_SEED_NAMES)


def _seed_table_sql() -> str:
    cols = ",\n  ".join(
        f'"{name}" {kind}' + (" NOT NULL" if name in _NOT_NULL else "")
        for name, kind in SEED_COLUMNS
    )
    return (
        f"CREATE TABLE seed_records (\n  {cols},\n"
        "  geom geometry(Point, 4326) NOT NULL,\n"
        "  ingested_at timestamptz NOT NULL DEFAULT now(),\n"
        "  UNIQUE (machine_id, id, utc)\n) PARTITION BY RANGE (utc)"
    )


MIGRATIONS: dict[int, list[str]] = {
    1: [
        "CREATE EXTENSION IF NOT EXISTS postgis",
        _seed_table_sql(),
        "CREATE INDEX seed_records_utc_brin ON seed_records USING brin (utc)",
        "CREATE TABLE alarm_events (machine_id text NOT NULL, id bigint NOT NULL, "
        "utc timestamptz NOT NULL, code text NOT NULL, active boolean NOT NULL, "
        "severity text NOT NULL, message text NOT NULL, "
        "ingested_at timestamptz NOT NULL DEFAULT now(), UNIQUE (machine_id, id, utc)) "
        "PARTITION BY RANGE (utc)",
        "CREATE INDEX alarm_events_utc_brin ON alarm_events USING brin (utc)",
        "CREATE TABLE state_samples (machine_id text NOT NULL, utc timestamptz NOT NULL, "
        "work_state text NOT NULL, speed_kmh real, target_rate_kg_ha real, "
        "commanded_rate_kg_ha real, area_ha double precision, seed_mass_kg double precision, "
        "gnss_fix text, payload jsonb NOT NULL, UNIQUE (machine_id, utc)) "
        "PARTITION BY RANGE (utc)",
        "CREATE INDEX state_samples_utc_brin ON state_samples USING brin (utc)",
        "CREATE TABLE seed_coverage (machine_id text NOT NULL, lo bigint NOT NULL, "
        "hi bigint NOT NULL, PRIMARY KEY (machine_id, lo), CHECK (lo <= hi))",
        "CREATE TABLE machine_status (machine_id text PRIMARY KEY, status text NOT NULL, "
        "utc timestamptz NOT NULL DEFAULT now())",
        # days are created on demand by the ingest user, which owns nothing: this function
        # runs as its owner (the migrating user) and creates only day partitions
        """CREATE FUNCTION sowgate_ensure_day(day date) RETURNS void
LANGUAGE plpgsql SECURITY DEFINER SET search_path = public AS $fn$
DECLARE t text;
BEGIN
  PERFORM pg_advisory_xact_lock(hashtext('sowgate_ensure_day'));
  FOREACH t IN ARRAY ARRAY['seed_records', 'alarm_events', 'state_samples'] LOOP
    IF to_regclass(format('%s_%s', t, to_char(day, 'YYYYMMDD'))) IS NULL THEN
      EXECUTE format('CREATE TABLE %I PARTITION OF %I FOR VALUES FROM (%L) TO (%L)',
                     format('%s_%s', t, to_char(day, 'YYYYMMDD')), t,
                     day::timestamp AT TIME ZONE 'UTC', (day + 1)::timestamp AT TIME ZONE 'UTC');
    END IF;
  END LOOP;
END $fn$""",
    ],
    # 2: a GiST index on the point (map queries of a field: "which seeds are in this
    # polygon"), and ``seed_void``: per machine, the id ranges the cab declared it will never
    # send (its ``pending_from``: ids skipped by its id reservation after an unclean stop, or
    # delivered before this farm server knew it). ``committed_through`` counts them as done,
    # so a machine whose ids do not start at 1 or jump by a block does not hold the watermark
    # (and the gap list) back for ever; ``seed_coverage`` stays what is really committed.
    2: [
        "CREATE INDEX seed_records_geom_gist ON seed_records USING gist (geom)",
        # version 1 databases made before the float columns were widened: float4 lost the
        # cab's last digits (a no-op where they are double precision already)
        "ALTER TABLE seed_records ALTER COLUMN speed_kmh TYPE double precision, "
        "ALTER COLUMN heading_deg TYPE double precision, "
        "ALTER COLUMN spacing_m TYPE double precision, "
        "ALTER COLUMN roll_deg TYPE double precision, "
        "ALTER COLUMN pitch_deg TYPE double precision",
        "CREATE TABLE seed_void (machine_id text NOT NULL, lo bigint NOT NULL, "
        "hi bigint NOT NULL, PRIMARY KEY (machine_id, lo), CHECK (lo <= hi))",
    ],
}


def migrate(url: str) -> int:
    """Bring the schema to ``SCHEMA_VERSION`` (run as the owner); returns the version found.

    A newer schema is refused: an older ingest must not write tables whose meaning it does
    not know (``SchemaError`` says which versions)."""
    with psycopg.connect(url, autocommit=False) as conn:
        conn.execute("SELECT pg_advisory_xact_lock(hashtext('sowgate_migrate'))")
        conn.execute("CREATE TABLE IF NOT EXISTS sowgate_schema (version integer NOT NULL, "
                     "migrated_at timestamptz NOT NULL DEFAULT now())")
        row = conn.execute("SELECT max(version) FROM sowgate_schema").fetchone()
        found = int(row[0]) if row and row[0] is not None else 0
        if found > SCHEMA_VERSION:
            raise SchemaError(
                f"the database has sowgate schema version {found}, this ingest knows up to "
                f"{SCHEMA_VERSION}: upgrade sowgate before running ingest on it"
            )
        for version in range(found + 1, SCHEMA_VERSION + 1):
            for statement in MIGRATIONS[version]:
                conn.execute(statement.encode())
            conn.execute("INSERT INTO sowgate_schema (version) VALUES (%s)", (version,))
            log.info("farm server schema migrated to version %d", version)
        conn.commit()
        return found


def schema_version(url: str) -> int:
    """The sowgate schema version in this database (0: none yet)."""
    with psycopg.connect(url) as conn:
        try:
            row = conn.execute("SELECT max(version) FROM sowgate_schema").fetchone()
        except psycopg.errors.UndefinedTable:
            return 0
        return int(row[0]) if row and row[0] is not None else 0


def ensure_schema(url: str) -> int:
    """At ingest's start: migrate the schema itself when it is missing or older (possible when
    ingest connects as the owner), refuse a newer one. With an ingest user that owns
    nothing, a missing schema is a ``SchemaError`` telling to run ``--migrate`` as the owner.
    Returns the version found before."""
    found = schema_version(url)
    if found == SCHEMA_VERSION:
        return found
    if found > SCHEMA_VERSION:
        raise SchemaError(
            f"the database has sowgate schema version {found}, this ingest knows up to "
            f"{SCHEMA_VERSION}: upgrade sowgate before running ingest on it")
    try:
        return migrate(url)
    except psycopg.errors.InsufficientPrivilege as exc:
        raise SchemaError(
            f"the database has sowgate schema version {found}, this ingest writes version "
            f"{SCHEMA_VERSION}, and this user may not migrate it ({str(exc).strip()}): run "
            "`sowgate ingest --migrate --database-url <the owner's URL>` once") from None


def check_schema(conn: psycopg.Connection[TupleRow]) -> None:
    """The ingest user's check at start: the schema is there and not newer than ours."""
    try:
        row = conn.execute("SELECT max(version) FROM sowgate_schema").fetchone()
    except psycopg.errors.UndefinedTable:
        raise SchemaError("no sowgate schema in this database: run `sowgate ingest --migrate` "
                          "as the database owner first") from None
    found = int(row[0]) if row and row[0] is not None else 0
    if found != SCHEMA_VERSION:
        raise SchemaError(
            f"the database has sowgate schema version {found}, this ingest writes version "
            f"{SCHEMA_VERSION}" + (": upgrade sowgate" if found > SCHEMA_VERSION else
                                   ": run `sowgate ingest --migrate` as the owner")
        )


@dataclass(frozen=True)
class Committed:
    """What a write transaction left committed for one machine."""

    machine_id: str
    coverage: list[tuple[int, int]]  # merged id ranges of its seed records
    new_seeds: int
    duplicate_seeds: int
    # id ranges the machine declared it will never send (``seed_void``)
    void: list[tuple[int, int]] = field(default_factory=list)

    def _done(self) -> IdRanges:
        return IdRanges([*self.coverage, *self.void])

    @property
    def through(self) -> int:
        """Every id up to this one is committed or declared never to come."""
        return self._done().through()

    def gaps(self) -> list[tuple[int, int]]:
        """Ids missing below the highest committed one, as inclusive runs (the ids the
        machine declared it will never send are not missing)."""
        if not self.coverage:
            return []
        return list(self._done().gaps(0, self.coverage[-1][1]))


class IngestDatabase:
    """One connection of the ingest user. Every method is one transaction."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.conn: psycopg.Connection[TupleRow] = psycopg.connect(url, autocommit=False)
        check_schema(self.conn)
        self.conn.commit()
        self._days: set[date] = set()

    def close(self) -> None:
        self.conn.close()

    def _ensure_days(self, days: Iterable[date]) -> None:
        for day in sorted(set(days) - self._days):
            self.conn.execute("SELECT sowgate_ensure_day(%s)", (day,))
            self.conn.commit()
            self._days.add(day)

    def _ranges(self, table: str, machine_id: str) -> IdRanges:
        return IdRanges((int(lo), int(hi)) for lo, hi in self.conn.execute(
            sql.SQL("SELECT lo, hi FROM {} WHERE machine_id = %s ORDER BY lo")
            .format(sql.Identifier(table)), (machine_id,)).fetchall())

    def _store_ranges(self, table: str, machine_id: str, ranges: IdRanges) -> None:
        self.conn.execute(sql.SQL("DELETE FROM {} WHERE machine_id = %s")
                          .format(sql.Identifier(table)), (machine_id,))
        with self.conn.cursor() as cur:
            cur.executemany(
                sql.SQL("INSERT INTO {} (machine_id, lo, hi) VALUES (%s, %s, %s)")
                .format(sql.Identifier(table)),
                [(machine_id, lo, hi) for lo, hi in ranges],
            )

    def write_seeds(self, machine_id: str, records: Sequence[SeedRecord],
                    pending_from: int = 0) -> Committed:
        """Commit the records this machine's coverage lacks; return its coverage after.

        ``pending_from``: the machine said it will send no id below this one again; the ids
        below it that are not committed are recorded in ``seed_void`` (not missing)."""
        return self.write_seed_batches({machine_id: records}, {machine_id: pending_from})[0]

    def write_seed_batches(self, batches: Mapping[str, Sequence[SeedRecord]],
                           pending_from: Mapping[str, int] | None = None) -> list[Committed]:
        """``write_seed_rows`` for validated records."""
        return self.write_seed_rows({m: rows_of_records(m, records)
                                     for m, records in batches.items()}, pending_from)

    def write_seed_rows(self, batches: Mapping[str, SeedRows],
                        pending_from: Mapping[str, int] | None = None) -> list[Committed]:
        """Commit, in one transaction, the records each machine's coverage lacks; return each
        machine's coverage after (in machine id order). All or nothing.

        ``pending_from`` (per machine): it will send no id below this one again; the ids below
        it that are not committed are recorded in ``seed_void``, so they do not hold its
        watermark back."""
        machines = sorted(batches)
        if not machines:
            return []
        uniques = {m: dict(zip(batches[m].ids, batches[m].rows, strict=True)) for m in machines}
        pending = {m: (pending_from or {}).get(m, 0) for m in machines}
        self._ensure_days(d for m in machines for d in batches[m].days)
        try:
            covered, void, fresh = self._write_seeds(machines, uniques, pending, staging=False)
        except psycopg.errors.UniqueViolation:
            # a row the coverage does not list (it cannot happen through this class, the
            # key says so): again, through the staging table's ON CONFLICT DO NOTHING
            log.warning("seed_records holds rows seed_coverage does not list; written "
                        "through ON CONFLICT DO NOTHING")
            covered, void, fresh = self._write_seeds(machines, uniques, pending, staging=True)
        return [Committed(m, list(covered[m]), fresh[m], len(batches[m]) - fresh[m],
                          list(void[m])) for m in machines]

    def _write_seeds(self, machines: list[str], uniques: dict[str, dict[int, bytes]],
                     pending: dict[str, int], *, staging: bool,
                     ) -> tuple[dict[str, IdRanges], dict[str, IdRanges], dict[str, int]]:
        """One transaction: lock the machines (advisory, in key order, so two ingest
        processes never deadlock), read their coverage, COPY what it lacks, merge the new
        ids into it, and declare void what a machine will never send (``pending``).
        Returns (coverage after, void after, new records) per machine."""
        with self.conn.transaction(), self.conn.cursor() as cur:
            cur.execute(
                "SELECT pg_advisory_xact_lock(h) FROM (SELECT DISTINCT hashtext(m) AS h "
                "FROM unnest(%s::text[]) AS m ORDER BY h) AS keys", (machines,))
            ranges: dict[str, list[tuple[int, int]]] = {m: [] for m in machines}
            for m, lo, hi in cur.execute(
                "SELECT machine_id, lo, hi FROM seed_coverage WHERE machine_id = ANY(%s) "
                "ORDER BY machine_id, lo", (machines,),
            ).fetchall():
                ranges[m].append((int(lo), int(hi)))
            covered = {m: IdRanges(ranges[m]) for m in machines}
            fresh: dict[str, list[bytes]] = {}
            for m in machines:
                ids = sorted(uniques[m])
                top = ranges[m][-1][1] if ranges[m] else 0
                if ids and ids[0] <= top:  # some may be covered (a replay); else all new
                    ids = [i for i in ids if i not in covered[m]]
                fresh[m] = [uniques[m][i] for i in ids]
                covered[m].add_ids(ids)
            changed = [m for m in machines if fresh[m]]
            if changed:
                if staging:
                    self._insert_through_staging(cur, fresh)
                else:
                    self._copy_seeds(cur, fresh)
                cur.execute("DELETE FROM seed_coverage WHERE machine_id = ANY(%s)", (changed,))
                cur.executemany(
                    "INSERT INTO seed_coverage (machine_id, lo, hi) VALUES (%s, %s, %s)",
                    [(m, lo, hi) for m in changed for lo, hi in covered[m]])
            void = {m: IdRanges() for m in machines}
            for m, lo, hi in cur.execute(
                "SELECT machine_id, lo, hi FROM seed_void WHERE machine_id = ANY(%s) "
                "ORDER BY machine_id, lo", (machines,),
            ).fetchall():
                void[m].add(int(lo), int(hi))
            for m in machines:
                if pending[m] > 1:
                    never = list(IdRanges([*covered[m], *void[m]]).gaps(0, pending[m] - 1))
                    if never:
                        for lo, hi in never:
                            void[m].add(lo, hi)
                        self._store_ranges("seed_void", m, void[m])
                        log.info("%s: ids %s will never come (the machine skipped them or "
                                 "had them delivered before); not counted as missing", m,
                                 ", ".join(f"{lo}–{hi}" for lo, hi in never[:5]))
        return covered, void, {m: len(fresh[m]) for m in machines}

    def _copy_seeds(self, cur: psycopg.Cursor[TupleRow],
                    fresh: Mapping[str, Sequence[bytes]]) -> None:
        """Binary COPY straight into ``seed_records``: one COPY for every machine, its rows
        already in COPY format (the point as EWKB, what ``ST_SetSRID(ST_MakePoint(lon, lat),
        4326)`` makes)."""
        with cur.copy(_COPY_SEEDS) as copy:
            _write_rows(copy, fresh)

    def _insert_through_staging(self, cur: psycopg.Cursor[TupleRow],
                                fresh: Mapping[str, Sequence[bytes]]) -> None:
        cur.execute("CREATE TEMP TABLE IF NOT EXISTS seed_staging "
                    "(LIKE seed_records INCLUDING DEFAULTS) ON COMMIT DELETE ROWS")
        with cur.copy(_COPY_STAGING) as copy:
            _write_rows(copy, fresh)
        cur.execute(_INSERT_FROM_STAGING)

    def coverage(self, machine_id: str) -> Committed:
        covered = self._ranges("seed_coverage", machine_id)
        void = self._ranges("seed_void", machine_id)
        self.conn.commit()
        return Committed(machine_id, list(covered), 0, 0, list(void))

    def coverage_of(self, machines: Iterable[str] | None = None) -> list[Committed]:
        """The committed coverage of these machines (None: of every machine there is)."""
        out: dict[str, dict[str, list[tuple[int, int]]]] = {}
        for table in ("seed_coverage", "seed_void"):
            query = sql.SQL("SELECT machine_id, lo, hi FROM {}").format(sql.Identifier(table))
            if machines is None:
                rows = self.conn.execute(query + sql.SQL(" ORDER BY machine_id, lo")).fetchall()
            else:
                rows = self.conn.execute(
                    query + sql.SQL(" WHERE machine_id = ANY(%s) ORDER BY machine_id, lo"),
                    (sorted(machines),)).fetchall()
            for machine_id, lo, hi in rows:
                out.setdefault(str(machine_id), {}).setdefault(table, []).append(
                    (int(lo), int(hi)))
        self.conn.commit()
        return [Committed(m, t.get("seed_coverage", []), 0, 0, t.get("seed_void", []))
                for m, t in out.items()]

    def write_alarms(self, events: Sequence[AlarmEvent]) -> int:
        """Insert alarm events (unique per machine and id); returns how many were new."""
        if not events:
            return 0
        self._ensure_days(_day(e.utc) for e in events)
        with self.conn.transaction(), self.conn.cursor() as cur:
            cur.executemany(
                "INSERT INTO alarm_events (machine_id, id, utc, code, active, severity, "
                "message) VALUES (%s, %s, %s, %s, %s, %s, %s) ON CONFLICT DO NOTHING",
                [(e.machine_id, e.id, e.utc, e.code, e.active, e.severity, e.message)
                 for e in events],
            )
            return max(0, cur.rowcount)

    def write_states(self, states: Sequence[StatePayload]) -> None:
        if not states:
            return
        self._ensure_days(_day(s.utc) for s in states)
        with self.conn.transaction(), self.conn.cursor() as cur:
            cur.executemany(
                "INSERT INTO state_samples (machine_id, utc, work_state, speed_kmh, "
                "target_rate_kg_ha, commanded_rate_kg_ha, area_ha, seed_mass_kg, gnss_fix, "
                "payload) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s::jsonb) "
                "ON CONFLICT DO NOTHING",
                [(s.machine_id, s.utc, s.work_state, s.speed_kmh, s.target_rate_kg_ha,
                  s.commanded_rate_kg_ha, s.area_ha, s.seed_mass_kg, s.gnss_fix,
                  s.model_dump_json()) for s in states],
            )

    def write_status(self, machine_id: str, status: str) -> None:
        with self.conn.transaction():
            self.conn.execute(
                "INSERT INTO machine_status (machine_id, status) VALUES (%s, %s) "
                "ON CONFLICT (machine_id) DO UPDATE SET status = EXCLUDED.status, utc = now()",
                (machine_id, status),
            )


def _write_rows(copy: psycopg.Copy, fresh: Mapping[str, Sequence[bytes]]) -> None:
    copy.write(COPY_SIGNATURE)
    for rows in fresh.values():
        if rows:
            copy.write(b"".join(rows))
    copy.write(COPY_TRAILER)


def _day(t: datetime) -> date:
    return t.astimezone(UTC).date()
