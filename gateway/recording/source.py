"""Where ``sowgate report`` and ``sowgate export`` read records from: the one reading interface.

A ``RecordSource`` is what the report and every export format read: the seed records as the
store's stored tuples (``STORED_SEED_COLUMNS``), a chunk at a time, the alarm events, the
time span of the seeds and the daemon runs. Two implement it:

- the cab's record store (``RecordStore``, opened read-only), and
- the farm server's PostgreSQL (``gateway.recording.database_source.DatabaseSource``: the
  tables ``sowgate ingest`` writes, for one machine, ``--database URL --machine M``).

So the statistics, the map, the GeoJSON/CSV/ISO-XML writers are one code path whatever the
records come from, and give the same numbers for the same records (a test compares them).
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator, Sequence
from datetime import datetime
from pathlib import Path
from typing import Protocol

from gateway.core.records import AlarmEvent, SeedRecord
from gateway.recording.runs import Run
from gateway.recording.store.schema import StoredSeedRow

# a machine id as the farm server accepts one (the MQTT topic level; gateway.farm_server)
MACHINE_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")


class RecordSource(Protocol):
    """The readers ``sowgate report`` and ``sowgate export`` use (see the module doc)."""

    machine_id: str

    def query_seed_rows(
        self,
        since: datetime | None = None,
        until: datetime | None = None,
        rows: Sequence[int] | None = None,
    ) -> Iterator[list[StoredSeedRow]]:
        """Seed records in id order, ``since <= utc < until``, as stored tuples in chunks."""
        ...

    def query_seeds(
        self,
        since: datetime | None = None,
        until: datetime | None = None,
        rows: Sequence[int] | None = None,
    ) -> Iterator[SeedRecord]:
        """The same records as ``SeedRecord`` models."""
        ...

    def seed_time_span(
        self, since: datetime | None = None, until: datetime | None = None
    ) -> tuple[int, int] | None:
        """First and last ``utc_us`` of the seeds in the window (a bound), None: no seed."""
        ...

    def query_alarms(
        self, since: datetime | None = None, until: datetime | None = None
    ) -> Iterator[AlarmEvent]:
        """Alarm events in id order, ``since <= utc < until``."""
        ...

    def runs(self) -> list[Run]:
        """The daemon runs the source knows ([] when it knows none)."""
        ...


def source_text(database: str | None, machine: str | None, path: Path) -> str:
    """How messages name the source: the store's path, or the machine in the database."""
    if database is None:
        return str(path)
    return f"the farm database (machine {machine})"


@contextlib.contextmanager
def open_source(
    path: Path, machine_id: str, database: str | None = None, machine: str | None = None
) -> Iterator[RecordSource]:
    """The record store at ``path`` read-only or, with ``database``, that machine's records
    in the farm server's PostgreSQL (``machine`` defaults to ``machine_id``, the config's).

    ``StoreError`` when it cannot be opened (no store, no connection, no such schema)."""
    if database is None:
        from gateway.recording.store import RecordStore

        with RecordStore.open_readonly(path, machine_id) as store:
            yield store
        return
    from gateway.recording.database_source import DatabaseSource

    with DatabaseSource(database, machine or machine_id) as source:
        yield source
