"""Memory a seed record costs while the record store holds it (disk full), and with it how
long ``MAX_HELD_RECORDS`` rides out a full disk at 2 000 seeds/s.

Measured the way the daemon produces them: a synthetic 48-row field at 2 100 seeds/s goes
through the real ``SeedRecorder`` and positioner into a real ``RecordStore`` whose writes fail
(it is put in the state a full disk leaves it in), so every record ends up held by the
store's own ``_hold``. ``tracemalloc`` gives the memory still allocated once the recorder and
its positioner are gone: what the held records keep alive (the row tuples, their floats and
ints, the list slots), divided by their number.

``python -m benchmarks bench_held_records`` (or run this module) prints the figure.
"""

from __future__ import annotations

import gc
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Any

from benchmarks.bench_mqtt import NOMINAL_PER_S, SyntheticField, _planter
from gateway.config import parse_config
from gateway.recording.recorder import SeedRecorder
from gateway.recording.store import MAX_HELD_RECORDS, RecordStore, StoreError

SECONDS = 30.0  # of sowing held: ~63 000 records
RIDE_THROUGH_RATE = 2_000.0  # seeds/s the README's figure is stated for


def _held_bytes_per_record(db: Path) -> tuple[int, float]:
    settings = parse_config(_planter())
    store = RecordStore(db, "bench")
    # the state a failed commit on a full disk leaves: every new row is held in memory
    store._write_failed(StoreError("simulated full disk"))
    gc.collect()
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    t0 = time.monotonic() + 3600.0  # the recorder's clock stays there: GNSS never times out
    field = SyntheticField(t0_mono=t0)
    recorder = SeedRecorder(settings, store, clock=lambda: t0)
    t = 0.0
    while t < SECONDS:
        t += 0.5  # one recorder flush
        for event in field.until(t):
            if hasattr(event, "row"):
                recorder.on_edge(event)  # type: ignore[arg-type]
            else:
                recorder.on_epoch(event)  # type: ignore[arg-type]
        recorder.flush()
    del recorder, field
    gc.collect()
    after = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    held = store.records_held
    store._queue.clear()  # not to be written: the figure is all we wanted
    store._failing = False
    store.close()
    return held, (after - before) / max(1, held)


def run() -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        held, per_record = _held_bytes_per_record(Path(tmp) / "records.sqlite3")
    cap_mb = MAX_HELD_RECORDS * per_record / 1e6
    ride_s = MAX_HELD_RECORDS / RIDE_THROUGH_RATE
    markdown = (
        "### records held while the disk is full\n\n"
        f"{held} records from the real recorder and positioner (48 rows, "
        f"{NOMINAL_PER_S:.0f} seeds/s) held by the store: **{per_record:.0f} bytes a record** "
        f"(tracemalloc). `MAX_HELD_RECORDS` = {MAX_HELD_RECORDS} is {cap_mb:.0f} MB and rides "
        f"out a full disk for **{ride_s:.0f} s at {RIDE_THROUGH_RATE:.0f} seeds/s**.\n"
    )
    return {"held": held, "bytes_per_record": per_record, "cap_mb": cap_mb,
            "ride_through_s": ride_s, "markdown": markdown}


if __name__ == "__main__":
    print(run()["markdown"])
