"""The daemon's seed recording component: GNSS epochs + seed edges → positioned, stored records.

Wiring (done by the daemon)::

    recorder = SeedRecorder(settings, store, on_records=view.add)
    GnssReader(..., on_epoch=recorder.on_epoch)
    SerialSeedSensors(..., on_edge=recorder.on_edge)   # or GpioSeedSensors
    tasks: recorder.run(), store.run(), reader, sensors

The driver callbacks only queue the epoch or edge. Every ``FLUSH_INTERVAL_S`` ``run`` hands
the queue to the ``SeedPositioner`` in arrival order (so the result is the same as feeding it
live), stores what it resolved as one batch (one INSERT batch instead of one per seed),
commits it, resolves seeds whose epoch never came (GNSS outage) and keeps the per-row spacing
quality.

Why one burst twice a second instead of a hundred small ones (one per serial read): on
a mostly idle core each wake-up finds cold caches and a slow clock, and the same seed path
measured 2.5 times dearer in CPU when cut into 10 ms pieces than when run in one go. The
bursts fall on the shared tick grid (``drivers.ticks``), in the same wake-up as the store's
commit tick, and the positioner holds the seeds that become ready during a burst for one
vector pass at its end (``SeedPositioner.defer_resolution``).

Records are given to ``on_records`` only after the store has accepted them and given them
ids; the store decides when the MQTT outbox sees them (after a commit), so nothing leaves the
box that a crash could take back.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from operator import attrgetter, itemgetter
from typing import Protocol

from drivers.log_limit import RateLimitedLog
from drivers.seed_sensors import SeedEdgeEvent
from drivers.ticks import sleep_to_next_tick
from gateway.config import Settings
from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop, SeedRecord, SeedRow
from gateway.recording.positioning import (
    AntennaEpoch,
    Landing,
    Method,
    SeedPositioner,
    TimeEvents,
)
from gateway.recording.seed_plausibility import SeedRatePlausibility
from gateway.recording.spacing_quality import RowQualityAccumulator, SpacingQuality

log = logging.getLogger(__name__)

# Each flush positions, stores and commits in one burst. A burst after a sleep pays a warm-up
# of about 2 ms of CPU on the bench machine (caches refilled, the clock ramping up) whatever
# its size, so fewer, larger bursts are cheaper: positioning cost 9 µs a seed in 0.2 s bursts
# and 6.5 µs in 0.5 s ones. 0.5 s keeps records well inside the 1 s a power cut may take back
# (the store fsyncs every second) and within the MQTT batch window (batch_max_ms = 500).
FLUSH_INTERVAL_S = 0.5
# Positioned seeds waiting for the next flush; far above 48 rows x 45 seeds/s x 0.5 s. If the
# store stalls beyond this, flush runs inline so memory stays bounded.
MAX_BUFFERED_DROPS = 10_000
# Epochs and edges waiting for the next flush (~1 060 at 2 100 seeds/s plus 10 Hz epochs,
# ~3 200 for a 96-row planter at 20 km/h): if the loop stalls beyond this, they are positioned
# inline so memory stays bounded (~100 bytes an event).
MAX_QUEUED_EVENTS = 8_192
_ROW, _SPACING = itemgetter(1), itemgetter(10)  # in a stored record row (gateway.core.records)
_EDGE_ROW, _EDGE_TIME = itemgetter(0), itemgetter(1)  # of a SeedEdgeEvent (a NamedTuple)
_STORED = attrgetter("stored")  # of a Landing: its SeedRow


class SeedSink(Protocol):
    """What the recorder needs from ``gateway.recording.store.RecordStore``.

    A sink may also offer ``append_rows(rows) -> ids`` (the store does, rows as in
    ``Landing.stored``); the recorder uses it when no ``on_records`` callback wants the record
    objects, so no ``SeedDrop`` is ever built for them.
    """

    def add_seeds(self, drops: Sequence[SeedDrop]) -> list[SeedRecord]: ...


RecordsCallback = Callable[[list[SeedRecord]], None]


@dataclass(frozen=True, slots=True)
class RowState:
    """One seed row so far: seeds stored, the last spacing, edges dropped as implausible, and
    the spacing quality (ISO 7256-1 indices) over what was stored."""

    seeds: int
    last_spacing_m: float | None
    implausible_edges: int
    quality: SpacingQuality


@dataclass(frozen=True, slots=True)
class RecorderState:
    """The recorder at one moment, for the live view and the state payload (``state()``)."""

    method: Method
    records_stored: int
    pending: int  # seeds waiting for the epoch after them
    buffered: int  # positioned, waiting for the next flush
    queued: int  # epochs and edges waiting for the next flush
    unpositioned: int
    extrapolated: int
    bad_edges: int
    store_errors: int
    records_lost: int
    implausible_edges: int
    last_error: str | None
    rows: Mapping[int, RowState]  # row number -> its state, in row order


class SeedRecorder:
    def __init__(
        self,
        settings: Settings,
        store: SeedSink,
        *,
        on_records: RecordsCallback | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.store = store
        self.on_records = on_records
        self._clock = clock
        # the previous flush's clock reading (see _position_due)
        self._expire_before: float | None = None
        self._log = RateLimitedLog(log, clock=clock)
        self.positioner = SeedPositioner(
            settings.positioning, baseline_offset_deg=settings.gnss.heading_offset_deg
        )
        rows = settings.machine.rows
        x_ref = settings.positioning.target_spacing_m
        self.quality = {r: RowQualityAccumulator(x_ref) for r in range(1, rows + 1)}
        self.seeds_per_row = dict.fromkeys(range(1, rows + 1), 0)
        self.last_spacing_m: dict[int, float | None] = dict.fromkeys(range(1, rows + 1))
        self._buffer: list[Landing] = []
        self._events: list[AntennaEpoch | SeedEdgeEvent] = []
        self._epochs_at: list[int] = []  # where the epochs are in _events (the rest: edges)
        self.records_stored = 0
        self.bad_edges = 0
        self.store_errors = 0
        self.store_error: str | None = None  # set while the store refuses records
        # dropped because a sink that refuses rows (not RecordStore: it holds them itself)
        # refused them longer than MAX_BUFFERED_DROPS lasts
        self.records_lost = 0
        self.last_error: str | None = None
        # edges faster than a row can drop seeds are counted there, not stored
        self.plausibility = SeedRatePlausibility(settings.seed_sensors.max_seeds_per_s_per_row)
        # row -> edges that passed the plausibility check (seeds), since start: what the row
        # monitor counts (gateway.recording.row_monitor), as soon as they are positioned
        self.edges_per_row: dict[int, int] = dict.fromkeys(range(1, rows + 1), 0)

    # ------------------------------------------------------------ driver callbacks

    def on_epoch(self, epoch: AntennaEpoch) -> None:
        self._epochs_at.append(len(self._events))
        self._queue(epoch)

    def on_edge(self, event: SeedEdgeEvent) -> None:
        # ``_queue`` inlined: this runs for every seed, and the call was a tenth of its cost
        events = self._events
        events.append(event)
        if len(events) >= MAX_QUEUED_EVENTS:
            self._position_queued()

    def recalibrate(self, positioning: PositioningSection) -> None:
        """A seed position calibration saved while running (gateway.app.live_calibration):
        new seeds are positioned with it (SeedPositioner.recalibrate)."""
        self.positioner.recalibrate(positioning)
        log.info("seed positions recalibrated: outlets %.3f m behind the antenna, delay "
                 "correction %+.1f ms", positioning.outlet_behind_antenna_m,
                 positioning.delay_correction_ms)

    def on_roll(self, t_mono: float, roll_deg: float) -> None:
        """An inclinometer roll reading (positioning.attitude_source = "inclinometer"): the
        epochs after it take it while it is fresh (SeedPositioner.add_attitude)."""
        self.positioner.add_attitude(t_mono, roll_deg)

    def _queue(self, event: AntennaEpoch | SeedEdgeEvent) -> None:
        events = self._events
        events.append(event)
        if len(events) >= MAX_QUEUED_EVENTS:
            self._position_queued()

    def _position_queued(self) -> None:
        """Hand the queued epochs and edges to the positioner, in the order they came: each
        run of edges between two epochs in one call (``SeedPositioner.add_edges``)."""
        events, self._events = self._events, []
        epochs_at, self._epochs_at = self._epochs_at, []
        positioner = self.positioner
        positioner.defer_resolution()  # one vector pass for the burst, not one per epoch
        try:
            # the runs of edges between epochs are slices (no per-seed look at each event)
            start = 0
            for at in epochs_at:
                if at > start:
                    self._edges(events[start:at])  # type: ignore[arg-type]
                self._take(positioner.add_epoch(events[at]))  # type: ignore[arg-type]
                start = at + 1
            if start < len(events):
                self._edges(events[start:])  # type: ignore[arg-type]
        finally:
            self._take(positioner.settle())

    def _edges(self, edges: list[SeedEdgeEvent]) -> None:
        dropped = self.plausibility.implausible_total
        rows, times = self.plausibility.filter(list(map(_EDGE_ROW, edges)),
                                               list(map(_EDGE_TIME, edges)))
        per_row = self.edges_per_row
        for row, count in Counter(rows).items():
            if row in per_row:
                per_row[row] += count
        if self.plausibility.implausible_total != dropped:
            self._log.warning(
                "implausible", "seed edges beyond %g/s on row(s) %s not stored (%d in all)",
                self.plausibility.max_per_s, self._implausible_rows(),
                self.plausibility.implausible_total,
            )
        try:
            landed = self.positioner.add_edges(rows, times)
        except ValueError:  # a row the config does not know: one by one, to count it alone
            for row, t_mono in zip(rows, times, strict=True):
                self._edge(SeedEdgeEvent(row, t_mono))
            return
        if landed:  # usually empty: the seeds wait for the epoch after their landing
            self._take(landed)

    def _implausible_rows(self) -> str:
        rows = sorted(self.plausibility.implausible)
        return ", ".join(map(str, rows[:8])) + (", ..." if len(rows) > 8 else "")

    def implausible_rows(self, within_s: float) -> list[int]:
        """Rows that had edges dropped as implausible in the last ``within_s`` seconds."""
        return self.plausibility.rows_implausible_since(self._clock() - within_s)

    def _edge(self, event: SeedEdgeEvent) -> None:
        try:
            landed = self.positioner.add_edge(event.row, event.t_mono)
        except ValueError as exc:  # a row the config does not know: wiring or firmware fault
            self.bad_edges += 1
            self.last_error = str(exc)
            log.warning("seed edge ignored: %s", exc)
            return
        if landed:  # usually empty: the seed waits for the epoch after its landing
            self._take(landed)

    def _take(self, landed: list[Landing]) -> None:
        self._buffer.extend(landed)
        if len(self._buffer) >= MAX_BUFFERED_DROPS:
            self._store(want_records=False)

    # ------------------------------------------------------------ batching

    def flush(self) -> list[SeedRecord]:
        """Position what is queued, resolve timed-out seeds, hand everything to the store."""
        self._position_due()
        return self._store(want_records=True)

    def _position_due(self) -> None:
        """The queued events, and the seeds whose epoch never came (GNSS outage).

        A seed is given up on (extrapolated) only if it was overdue already at the previous
        flush: a loop that stalled (a loaded box, a long GC) wakes with the seed lines and
        the receiver's epochs of the stall in its buffers, and the GNSS reader's task may
        queue its epochs after this flush has run. Judged against the time of this flush,
        the seeds of the stall were extrapolated (up to a metre off, stamped with the last
        epoch) while their epochs sat unread; judged against the previous flush, every task
        has had its turn since. A real GNSS outage costs one flush interval more of waiting.
        """
        self._position_queued()
        now = self._clock()
        expire_before, self._expire_before = self._expire_before, now
        if expire_before is not None:
            self._take_quiet(self.positioner.poll(expire_before))

    def _flush_quietly(self) -> None:
        """``flush`` for the periodic loop (nobody reads its return value), then commit."""
        self._position_due()
        stored = self.records_stored
        self._store(want_records=False)
        if self.records_stored != stored:
            self._commit()

    def _commit(self) -> None:
        """Commit now, in this burst, rather than wake again at the store's next tick.

        A failed commit is the store's to retry and to report: it holds the rows in memory
        under the ids they already have and retries with backoff (``gateway.recording.store``), and
        ``RecordingHealth`` raises records.store_failed from its ``commit_error``.
        """
        # commit_soon only wakes the store's writer thread: control never waits for the card
        commit = getattr(self.store, "commit_soon", None) or getattr(self.store, "flush", None)
        if commit is None:
            return
        try:
            commit()
        except Exception as exc:
            log.debug("commit after storing seeds failed (the store retries): %s", exc)

    def _take_quiet(self, landed: list[Landing]) -> None:
        self._buffer.extend(landed)

    def _store(self, want_records: bool) -> list[SeedRecord]:
        """Hand the buffer to the store; record objects only if someone wants them."""
        if not self._buffer:
            return []
        drops, self._buffer = self._buffer, []
        append = None
        if not want_records and self.on_records is None:
            append = getattr(self.store, "append_rows", None)
        records: list[SeedRecord] = []
        stored = list(map(_STORED, drops))  # (utc_us, row, ..., spacing_m)
        try:
            if append is not None:
                append(stored)  # ids only: no objects nobody reads
            else:
                records = self.store.add_seeds([la.drop for la in drops])
        except Exception as exc:  # keep positioning; RecordingHealth raises the alarm
            self.store_errors += 1
            self.store_error = str(exc) or type(exc).__name__
            self.last_error = f"store rejected {len(drops)} seeds: {exc}"
            log.error("%s", self.last_error)
            self._buffer = drops + self._buffer
            overflow = len(self._buffer) - MAX_BUFFERED_DROPS
            if overflow > 0:  # bounded: the oldest are lost first, and counted
                self.records_lost += overflow
                log.error("record store still failing: %d oldest seed records lost", overflow)
                del self._buffer[:overflow]
            return []
        self.store_error = None
        self.records_stored += len(drops)
        self._tally(stored)
        if self.on_records is not None and records:
            try:
                self.on_records(records)
            except Exception:
                log.exception("on_records callback failed")
        return records

    def _tally(self, stored: list[SeedRow]) -> None:
        """Per-row counts, last spacings and spacing quality for stored records, in order.

        Every seed passes here, so the counting and the last-spacing update run in C
        (``Counter``, ``dict.update``) and each row's spacings go to its accumulator in one
        ``add_many`` call."""
        rows = list(map(_ROW, stored))
        spacings = list(map(_SPACING, stored))
        seeds_per_row = self.seeds_per_row
        for row, count in Counter(rows).items():
            seeds_per_row[row] = seeds_per_row.get(row, 0) + count
        self.last_spacing_m.update(zip(rows, spacings, strict=True))
        by_row: dict[int, list[float]] = {}
        for row, spacing in zip(rows, spacings, strict=True):
            if spacing is not None:
                same_row = by_row.get(row)
                if same_row is None:
                    by_row[row] = [spacing]
                else:
                    same_row.append(spacing)
        quality = self.quality
        for row, values in by_row.items():
            if row in quality:
                quality[row].add_many(values)

    async def run(self) -> None:
        """Flush every FLUSH_INTERVAL_S; on cancellation position and store what is pending."""
        try:
            while True:
                await sleep_to_next_tick(FLUSH_INTERVAL_S)  # with the store's commit tick
                self._flush_quietly()
        finally:
            self._position_queued()
            self._take_quiet(self.positioner.flush())
            self._store(want_records=False)

    # ------------------------------------------------------------ telemetry

    @property
    def gnss_time(self) -> TimeEvents:
        """What the position model made of the receiver's time stamps (alarms read it)."""
        return self.positioner.time.events

    def state(self) -> RecorderState:
        """A copy for the view and telemetry: per row count, last spacing, quality."""
        st = self.positioner.stats
        return RecorderState(
            method=self.positioner.method,
            records_stored=self.records_stored,
            pending=self.positioner.pending,
            buffered=len(self._buffer),
            queued=len(self._events),
            unpositioned=st.unpositioned,
            extrapolated=st.extrapolated,
            bad_edges=self.bad_edges,
            store_errors=self.store_errors,
            records_lost=self.records_lost,
            implausible_edges=self.plausibility.implausible_total,
            last_error=self.last_error,
            rows={
                row: RowState(
                    seeds=self.seeds_per_row[row],
                    last_spacing_m=self.last_spacing_m[row],
                    implausible_edges=self.plausibility.implausible.get(row, 0),
                    quality=self.quality[row].result(),
                )
                for row in sorted(self.seeds_per_row)
            },
        )
