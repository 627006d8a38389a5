"""The durable record store: every seed record and alarm, and the MQTT outbox over them.

A seed record exists for the rest of the system only once it is committed here: the outbox
never returns a row the store has not committed, so nothing is published that a crash could
take back, and no id is ever handed out twice.

Modules, each owning one thing:

- ``schema``: tables, column lists, the SQL the writer reuses, conversions of older stores;
- ``ids``: the id reservation kept apart from SQLite, so ids survive a lost WAL or store;
- ``recovery``: the check at open; a damaged store is moved aside, a new one continues;
- ``record_store``: ``RecordStore``, its queue of accepted records and the writer thread;
- ``outbox``: what is committed and not acknowledged by the broker (the MQTT side);
- ``queries``: the streamed readers of exports, reports and calibration.

Control never waits for storage. The loop's side of the store touches memory only:
``append_rows`` and ``add_alarm`` queue records under the ids they hand out, ``mark_*`` merge
acknowledged ids, the outbox reads committed rows from an in-memory tail. A writer thread
commits the queue (at once when the recorder asks, else on the 0.5 s commit tick), fsyncs
the WAL, prunes. A card that stalls (a write running over ``STALL_S``) raises
``store.stalled`` and the queue counts as held, as on a full disk; rate control runs on.

Durability. SQLite runs in WAL mode with ``synchronous=NORMAL``: a commit appends to the WAL
without fsync; an application crash loses nothing committed. What a power cut can lose is what
was committed since the WAL was last fsynced; the writer forces a passive checkpoint, which
fsyncs the WAL, every ``SYNC_INTERVAL_S`` (1 s) while there are commits, so a power cut loses
about the last second of records, and an idle box makes no fsync at all.

Ids. A power cut (or a card whose cache lied) can take the store's last seconds back, a lost
WAL can take more, and a damaged store is replaced by an empty one: SQLite's own high-water
mark goes with them. So ids are reserved in blocks in a file of their own, durably, before a
commit makes them visible (``ids``); the next run starts above both the store and the
reservation. After a stop that did not close the store the ids jump by at most a block (the
ids skipped count as delivered); a clean close keeps them contiguous.

Delivery. What the broker acknowledged is kept as id ranges (``gateway.recording.id_ranges``),
rewritten with the writer's next commit.

Time. No index entry per seed: each committed batch records its ids and time span in
``seed_spans``; time-range queries and pruning read the ids from there.

Full disk. A write that fails loses nothing: records leave the queue only once committed, up
to ``max_held_records`` (past it new ones are counted in ``records_lost`` and get no id);
the writer retries with capped backoff. Alarm events are held likewise; ``add_alarm`` then
returns id 0 and the MQTT link publishes the event live.

Damage. A store that fails its check at open, or that SQLite reports corrupt while writing,
is moved aside with a timestamp (kept, named in the log and in ``store.replaced``) and a new
store continues the ids: a damaged file never stops the daemon.

Space. Nothing undelivered is ever deleted; pruning removes delivered records older than the
retention, counted back from the earlier of the host clock and the newest record's time, and
only as a prefix in id order: no single wrong clock can delete anything.
"""

from gateway.recording.store.ids import ID_BLOCK, IdReservation
from gateway.recording.store.outbox import MAX_OUTBOX_LIMIT, TAIL_MAX_ROWS, OutboxBatch
from gateway.recording.store.queries import QUERY_CHUNK_ROWS
from gateway.recording.store.record_store import (
    DRAIN_CHUNK_ROWS,
    MAX_HELD_ALARMS,
    MAX_HELD_RECORDS,
    PRUNE_CHUNK_ROWS,
    PRUNE_INTERVAL_S,
    STALL_S,
    SYNC_INTERVAL_S,
    RecordStore,
    StoreState,
)
from gateway.recording.store.recovery import ReplacedStore
from gateway.recording.store.schema import (
    _ADDED_SEED_COLUMNS,
    SCHEMA,
    STORED_SEED_COLUMNS,
    StoredSeedRow,
    StoreError,
)

__all__ = [
    "DRAIN_CHUNK_ROWS",
    "ID_BLOCK",
    "MAX_HELD_ALARMS",
    "MAX_HELD_RECORDS",
    "MAX_OUTBOX_LIMIT",
    "PRUNE_CHUNK_ROWS",
    "PRUNE_INTERVAL_S",
    "QUERY_CHUNK_ROWS",
    "SCHEMA",
    "STALL_S",
    "STORED_SEED_COLUMNS",
    "SYNC_INTERVAL_S",
    "TAIL_MAX_ROWS",
    "_ADDED_SEED_COLUMNS",
    "IdReservation",
    "OutboxBatch",
    "RecordStore",
    "ReplacedStore",
    "StoreError",
    "StoreState",
    "StoredSeedRow",
]
