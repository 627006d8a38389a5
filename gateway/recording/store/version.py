"""The record store's schema version: an older sowgate refuses a store a newer one wrote.

After an upgrade and a rollback (install.sh --rollback) the older daemon meets a store whose
tables a newer version may have changed. Reading it anyway could misread rows or, worse, write
rows the newer version then misreads. The store therefore carries its schema version in
SQLite's ``user_version``: a store above ``SCHEMA_VERSION`` is refused with a config error
(exit 78, no restart loop) that says what to do. Stores from before the version existed read 0
and are upgraded by the store's own column migrations, then stamped.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from gateway.core.errors import ConfigError

# Raise it with every change of the store's tables that an older version would misread.
SCHEMA_VERSION = 1


class StoreTooNewError(ConfigError):
    """The store was written by a newer sowgate (its schema version is above ours)."""


def check_schema_version(db: sqlite3.Connection, path: Path) -> None:
    """Refuse (and close) a store written by a newer schema, before anything reads or writes."""
    found = int(db.execute("PRAGMA user_version").fetchone()[0])
    if found > SCHEMA_VERSION:
        db.close()
        raise StoreTooNewError([
            f"store.path: the record store {path} has schema version {found}, written by a "
            f"newer sowgate; this version reads up to {SCHEMA_VERSION}. Go back to the newer "
            "version (install.sh --rollback), or move the store aside after exporting it with "
            "the newer version"
        ])


def refuse_if_too_new(path: Path) -> None:
    """The check at open, before a damaged-store check could move a newer store aside: a file
    SQLite cannot read is left to ``recovery`` (this is not the place to judge damage)."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error:
        return
    try:
        check_schema_version(db, path)
    except sqlite3.Error:
        pass
    finally:
        db.close()


def stamp_schema_version(db: sqlite3.Connection) -> None:
    """Mark a store this version has created or migrated as ours."""
    if int(db.execute("PRAGMA user_version").fetchone()[0]) < SCHEMA_VERSION:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
