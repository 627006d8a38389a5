"""All of the farm server's PostgreSQL I/O: schema and its migration, batched binary COPY,
and the per-machine coverage of committed seed ids that the watermark is computed from.

Exactly once. At-least-once delivery, replays and two ingest processes in a share group
all hand us records twice. Each write transaction takes a per-machine advisory lock, reads
the machine's committed id ranges (``seed_coverage``), drops every record already covered,
COPYs the rest into a temporary staging table and moves it with ``INSERT … ON CONFLICT DO
NOTHING`` (the unique key is the backstop), then merges the new ids into ``seed_coverage``
before the commit. So the coverage is what the database holds, in the same transaction, and
the watermark published after the commit is never ahead of it.

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
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, date, datetime

import psycopg
from psycopg import sql
from psycopg.rows import TupleRow

from gateway.core.records import AlarmEvent, SeedRecord
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
        self.conn.execute(
            "CREATE TEMP TABLE seed_staging (LIKE seed_records INCLUDING DEFAULTS) "
            "ON COMMIT DELETE ROWS"
        )
        self.conn.execute("ALTER TABLE seed_staging DROP COLUMN geom")
        self.conn.commit()

    def close(self) -> None:
        self.conn.close()

    def _ensure_days(self, stamps: Iterable[datetime]) -> None:
        days = {t.astimezone(UTC).date() for t in stamps} - self._days
        for day in sorted(days):
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
        unique = {r.id: r for r in records}
        self._ensure_days(r.utc for r in unique.values())
        with self.conn.transaction():
            self.conn.execute("SELECT pg_advisory_xact_lock(hashtext(%s))", (machine_id,))
            covered = self._ranges("seed_coverage", machine_id)
            void = self._ranges("seed_void", machine_id)
            fresh = [r for i, r in sorted(unique.items()) if i not in covered]
            if fresh:
                names = sql.SQL(", ").join(sql.Identifier(n) for n, _ in SEED_COLUMNS)
                with self.conn.cursor() as cur:
                    with cur.copy(sql.SQL("COPY seed_staging ({}) FROM STDIN (FORMAT BINARY)")
                                  .format(names)) as copy:
                        copy.set_types([kind for _, kind in SEED_COLUMNS])
                        for r in fresh:
                            copy.write_row((
                                machine_id, r.id, r.row, r.utc, r.lat, r.lon, r.fix,
                                r.speed_kmh, r.heading_deg, r.heading_source, r.extrapolated,
                                r.method, r.spacing_m, r.attitude, r.roll_deg, r.pitch_deg,
                            ))
                    cur.execute(sql.SQL(
                        "INSERT INTO seed_records ({names}, geom) SELECT {names}, "
                        "ST_SetSRID(ST_MakePoint(lon, lat), 4326) FROM seed_staging "
                        "ON CONFLICT DO NOTHING").format(names=names))
                    cur.execute("TRUNCATE seed_staging")
                covered.add_ids(r.id for r in fresh)
                self._store_ranges("seed_coverage", machine_id, covered)
            if pending_from > 1:
                done = IdRanges([*covered, *void])
                never = list(done.gaps(0, pending_from - 1))
                if never:
                    for lo, hi in never:
                        void.add(lo, hi)
                    self._store_ranges("seed_void", machine_id, void)
                    log.info("%s: ids %s will never come (the machine skipped them or had "
                             "them delivered before); not counted as missing", machine_id,
                             ", ".join(f"{lo}–{hi}" for lo, hi in never[:5]))
        return Committed(machine_id, list(covered), len(fresh), len(records) - len(fresh),
                         list(void))

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
        self._ensure_days(e.utc for e in events)
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
        self._ensure_days(s.utc for s in states)
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
