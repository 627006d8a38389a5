"""The store's SQLite schema, the SQL the write path reuses, and the conversions of stores
written by older sowgate versions (run when a store is opened for writing).

Owns: table layout, column lists (``STORED_SEED_COLUMNS`` is what the readers get), and every
migration. Nothing here holds state; the functions take the connection.
"""

from __future__ import annotations

import functools
import logging
import sqlite3
from pathlib import Path
from typing import Any

from gateway.core.errors import GatewayError
from gateway.core.records import SeedRecord
from gateway.recording import runs as run_markers

log = logging.getLogger(__name__)


# Every seed row binds a bool (``extrapolated``) and usually a None or two (no spacing yet, no
# attitude). Python's sqlite3 binds only exact int, float, str and bytearray directly; any other
# value goes through its adapter lookup, and with no adapter registered that lookup fails
# through two attribute look-ups on the protocol type, each raising and clearing an
# AttributeError with a formatted message: about 1 µs per value, 3 µs of a seed's 20 on the
# bench machine (callgrind: a tenth of the seed path's instructions). With adapters
# registered the lookup hits at once and binds the same thing: None as NULL (``{}.get``
# returns None for any key, in C), a bool as the integer SQLite stored for it anyway.
_NO_KEYS: dict[None, None] = {}
sqlite3.register_adapter(type(None), _NO_KEYS.get)
sqlite3.register_adapter(bool, int)


class StoreError(GatewayError):
    """The record store cannot be opened or written (disk full, read-only, corrupt file)."""


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

TABLES = ("seeds", "alarms")

# Columns added after the first stores were written (terrain compensation and what
# re-positioning needs, issue 16): an older store gets them with ALTER TABLE at open (its old
# rows read attitude 'none' and NULL for the rest), and a read-only open of an older store
# reads those defaults in their place. (name, declaration, value for older rows)
ADDED_SEED_COLUMNS = (
    ("attitude", "TEXT NOT NULL DEFAULT 'none'", "'none'"),
    ("roll_deg", "REAL", "NULL"),
    ("pitch_deg", "REAL", "NULL"),
    ("delay_ms", "REAL", "NULL"),
    ("offset_east_m", "REAL", "NULL"),
    ("offset_north_m", "REAL", "NULL"),
)
_ADDED_SEED_COLUMNS = ADDED_SEED_COLUMNS  # the name older tests import
ROW_COLUMNS = (
    "utc_us, row, lat, lon, fix, speed_kmh, heading_deg, heading_source, extrapolated, "
    "method, spacing_m, " + ", ".join(name for name, _, _ in ADDED_SEED_COLUMNS)
)
SEED_COLUMNS = "id, " + ROW_COLUMNS
# what query_seed_rows yields, one tuple a seed: the columns above, in that order
STORED_SEED_COLUMNS = tuple(SEED_COLUMNS.replace(" ", "").split(","))
StoredSeedRow = tuple[Any, ...]

# rows per INSERT: 512 rows is 8 704 parameters (SQLite allows 32 766 since 3.32), and a
# 512-row statement costs a quarter less per row than a 128-row one (the recorder stores
# ~1 050 rows a flush)
INSERT_CHUNKS = (512, 128, 32, 8, 1)


@functools.cache
def insert_with_ids_sql(rows: int) -> str:
    """Every row is written with the id it was given when it came (``RecordStore`` hands
    ids out itself, from ``IdReservation``; see the package docstring).

    The ids are consecutive, so the statement takes the first one alone (``?1``) and numbers
    the others from it (``?1+k``): the parameters are then ``[first_id, *row_0, *row_1,
    ...]``, the rows flattened as they are (in C), with no tuple built per row to prepend
    its id. The other parameters are plain ``?`` (each the next number after the highest so
    far, so ``?2``.. in order): spelling them ``?NNN`` made SQLite take 115 ms to prepare the
    512-row statement, against 6 ms."""
    values = "," + ",".join("?" * (ROW_COLUMNS.count(",") + 1)) + ")"
    return f"INSERT INTO seeds ({SEED_COLUMNS}) VALUES " + ",".join(
        f"(?1{f'+{k}' if k else ''}{values}" for k in range(rows)
    )


def fast_record(fields: dict[str, Any]) -> SeedRecord:
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


# -- small queries -------------------------------------------------------------------------------


def scalar(db: sqlite3.Connection, sql: str, *args: Any) -> int:
    row = db.execute(sql, args).fetchone()
    return int(row[0]) if row and row[0] is not None else 0


def max_id(db: sqlite3.Connection, table: str) -> int:
    return scalar(db, f"SELECT MAX(id) FROM {table}")


def has_column(db: sqlite3.Connection, table: str, column: str) -> bool:
    return any(r[1] == column for r in db.execute(f"PRAGMA table_info({table})"))


def has_table(db: sqlite3.Connection, table: str) -> bool:
    return db.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (table,)
    ).fetchone() is not None


def load_delivered(db: sqlite3.Connection, table: str) -> list[tuple[int, int]]:
    """The acknowledged id ranges: from ``delivered``, or from an older store's flags."""
    if has_table(db, "delivered"):
        ranges = db.execute(
            "SELECT lo, hi FROM delivered WHERE tbl = ? ORDER BY lo", (table,)
        ).fetchall()
        if ranges or not has_column(db, table, "delivered"):
            return [(int(lo), int(hi)) for lo, hi in ranges]
    if not has_column(db, table, "delivered"):
        return []
    # runs of consecutive delivered ids (gaps and islands); ids below the oldest row were
    # pruned, and only delivered rows are ever pruned
    runs = [(int(lo), int(hi)) for lo, hi in db.execute(
        f"SELECT MIN(id), MAX(id) FROM (SELECT id, id - ROW_NUMBER() OVER (ORDER BY id) AS g "
        f"FROM {table} WHERE delivered = 1) GROUP BY g ORDER BY 1"
    )]
    oldest = scalar(db, f"SELECT MIN(id) FROM {table}")
    if oldest > 1:
        runs.insert(0, (1, oldest - 1))
    return runs


def readable_seed_columns(db: sqlite3.Connection) -> str:
    """``SEED_COLUMNS`` as this store can answer them: an older store opened read-only
    (``sowgate export`` next to an older daemon) reads defaults for the added ones."""
    if all(has_column(db, "seeds", name) for name, _, _ in ADDED_SEED_COLUMNS):
        return SEED_COLUMNS
    cols = ("id, utc_us, row, lat, lon, fix, speed_kmh, heading_deg, heading_source, "
            "extrapolated, method, spacing_m")
    for name, _, default in ADDED_SEED_COLUMNS:
        cols += f", {name}" if has_column(db, "seeds", name) else f", {default}"
    return cols


# -- opening for writing: the schema and the conversions of older stores --------------------------


def prepare_for_writing(db: sqlite3.Connection, path: Path) -> None:
    """WAL mode, the schema, and every conversion an older store needs."""
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=NORMAL")
    db.executescript(SCHEMA)
    db.executescript(run_markers.SCHEMA)  # the daemon's start and stop markers
    _convert_delivered_columns(db, path)
    _convert_time_index(db, path)
    _add_seed_columns(db, path)


def _in_one_transaction(db: sqlite3.Connection, statements: list[tuple[str, Any]]) -> None:
    db.execute("BEGIN IMMEDIATE")
    try:
        for sql, args in statements:
            if isinstance(args, list):
                db.executemany(sql, args)
            else:
                db.execute(sql, args)
        db.execute("COMMIT")
    except sqlite3.Error:
        db.execute("ROLLBACK")
        raise


def _convert_delivered_columns(db: sqlite3.Connection, path: Path) -> None:
    """Turn an older store's per-row ``delivered`` flags into ranges, in one transaction."""
    old = [t for t in TABLES if has_column(db, t, "delivered")]
    if not old:
        return
    statements: list[tuple[str, Any]] = []
    for table in old:
        runs = load_delivered(db, table)
        statements += [
            ("DELETE FROM delivered WHERE tbl = ?", (table,)),
            ("INSERT INTO delivered (tbl, lo, hi) VALUES (?, ?, ?)",
             [(table, lo, hi) for lo, hi in runs]),
            (f"DROP INDEX IF EXISTS {table}_pending", ()),
            (f"ALTER TABLE {table} DROP COLUMN delivered", ()),
        ]
    _in_one_transaction(db, statements)
    log.info("record store %s: delivery flags converted to id ranges", path)


def _add_seed_columns(db: sqlite3.Connection, path: Path) -> None:
    """Give an older store the columns added since it was made (no rewrite of its rows:
    SQLite's ADD COLUMN only changes the schema; old rows read the defaults)."""
    missing = [c for c in ADDED_SEED_COLUMNS if not has_column(db, "seeds", c[0])]
    if not missing:
        return
    _in_one_transaction(db, [
        (f"ALTER TABLE seeds ADD COLUMN {name} {declaration}", ())
        for name, declaration, _ in missing
    ])
    log.info("record store %s: seed columns added (%s)", path, ", ".join(c[0] for c in missing))


def _convert_time_index(db: sqlite3.Connection, path: Path) -> None:
    """Replace an older store's per-seed time index by one span over its rows.

    The index cost every insert a second B-tree write (a fifth of the insert); spans
    (one row per appended batch) answer the same time-range questions. The old rows get
    one span, found through the old index before it goes, so it is quick on any size.
    """
    if db.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'index' AND name = 'seeds_utc'"
    ).fetchone() is None:
        return
    _in_one_transaction(db, [
        ("INSERT OR IGNORE INTO seed_spans (first_id, last_id, min_utc_us, max_utc_us) "
         "SELECT MIN(id), MAX(id), MIN(utc_us), MAX(utc_us) FROM seeds HAVING COUNT(*) > 0", ()),
        ("DROP INDEX seeds_utc", ()),
    ])
    log.info("record store %s: per-seed time index replaced by spans", path)
