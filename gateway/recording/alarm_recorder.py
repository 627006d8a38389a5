"""Every alarm event of the daemon into the record store, with or without MQTT.

The store used to get alarm events from the MQTT link alone, so a farm without a broker (or
with ``[mqtt]`` off) got a field report that always said "No alarm". The daemon attaches this
to its ``AlarmBoard`` as soon as it has a store; the MQTT link, when there is one, listens
here and publishes from the store's outbox (and live, when the store could not keep an event:
``stored.id == 0``, see ``RecordStore.add_alarm``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from gateway.core.alarms import AlarmBoard
from gateway.core.records import AlarmEvent
from gateway.recording.store import RecordStore, StoreError

log = logging.getLogger(__name__)


class AlarmRecorder:
    """Stores each raise and clear of ``board`` in ``store``; tells its listeners the event as
    stored (with its id, or id 0 when the store could not commit it now)."""

    def __init__(self, board: AlarmBoard, store: RecordStore) -> None:
        self.store = store
        self._listeners: list[Callable[[AlarmEvent], None]] = []
        board.subscribe(self._on_alarm)

    def subscribe(self, listener: Callable[[AlarmEvent], None]) -> None:
        self._listeners.append(listener)

    def _on_alarm(self, event: AlarmEvent) -> None:
        try:
            stored = self.store.add_alarm(event)
        except StoreError:
            log.exception("cannot store alarm %s", event.code)
            stored = event.model_copy(update={"id": 0, "machine_id": self.store.machine_id})
        for listener in self._listeners:
            listener(stored)
