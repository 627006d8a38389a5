"""The seed positioner: GNSS epochs and seed-tube edges in, positioned seeds out, in order.

Owns :class:`SeedPositioner` and its :class:`PositionerStats`: the epoch history, the
clock map, the queue of seeds waiting for the epoch after their landing instant, the
timeouts and overflow that extrapolate them instead, the per-row spacing, and the fast
paths (per-pair scalar loop, numpy vector path for long runs) that make ~2 000 seeds/s
cheap. The input it needs from a GNSS epoch is the :class:`AntennaEpoch` protocol.

Separate from the model (:mod:`.geometry`, :mod:`.clock`, :mod:`.methods`) because this is
the stateful, performance-tuned part: what it computes is defined there, when and how fast
it is computed is decided here.
"""

from __future__ import annotations

import bisect
import itertools
import logging
import math
import statistics
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Any, Literal, NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

from gateway.config.recording import PositioningSection
from gateway.core.records import AttitudeSource, FixQuality, HeadingSource
from gateway.recording.positioning.attitude import (
    EpochAttitude,
    attitude_pair,
    lerp_nan,
    nan_of,
)
from gateway.recording.positioning.clock import ClockMap
from gateway.recording.positioning.geometry import (
    FloatArray,
    LocalFrame,
    RowOffset,
    antenna_ground_shift,
    heading_diff,
    rotate_offset,
    row_offset,
    terrain_offset,
    trailed_offset,
    wrap_deg,
)
from gateway.recording.positioning.gnss_time import GnssTimeGuard
from gateway.recording.positioning.landing import (
    _DROP_MAX_ROW,
    _FIX_NAMES,
    Landing,
    _new_drop,
)
from gateway.recording.positioning.methods import (
    KMH_PER_MS,
    AntennaSample,
    AntennaState,
    choose_heading,
    extrapolate_state,
    fall_time_s,
    interpolate_state,
    paper_landing,
    worst_fix,
    worst_heading_source,
)

log = logging.getLogger(__name__)

# Epochs kept: enough to bracket any pending seed (pending timeout / 10 Hz) several times over.
EPOCH_HISTORY = 64
# Seeds waiting for their bracketing epoch; beyond this the oldest is extrapolated at once.
# Every seed waits its fall time (~0.1 s), up to an epoch period for the next epoch, and the
# receiver's output latency: ~0.25 s, so a 48-row planter at 16 km/h (2 100 seeds/s) keeps
# ~500 waiting and a 96-row one at 20 km/h (~5 000/s) ~1 300; the recorder's 0.5 s bursts
# (defer_resolution) hold up to 0.5 s more of them, ~3 800 at most. The cap only bounds memory
# (~100 bytes a seed) if epochs stop coming; pending_timeout_s extrapolates them before that.
# It was 512, which extrapolated a third of the seeds at 3 000 seeds/s and all at 6 000.
MAX_PENDING_SEEDS = 16_384
# A held seed (SeedPositioner.defer_resolution) this close to the second-oldest epoch is
# positioned before the oldest leaves the history (its bracketing pair might go with it).
HISTORY_EVICTION_MARGIN_S = 1.0
# Extrapolation never reaches further past the last epoch than this many epoch periods.
MAX_EXTRAPOLATION_EPOCHS = 1.0
DEFAULT_EPOCH_PERIOD_S = 0.1

Method = Literal["interpolated", "paper"]
IntArray = npt.NDArray[np.intp] | npt.NDArray[np.int64]
# Runs of ready seeds at least this long are positioned with numpy (_interpolate_vector);
# break-even measured at ~30 seeds (vector: ~150 us a call + ~1.3 us a seed, scalar ~7 us);
# shorter ones cost less in the scalar loop.
VECTOR_MIN_SEEDS = 32


class AntennaEpoch(Protocol):
    """What the position model needs from one GNSS epoch (``drivers.gnss_reader.GnssEpoch``)."""

    @property
    def utc(self) -> datetime: ...
    @property
    def t_mono(self) -> float: ...
    @property
    def lat(self) -> float: ...
    @property
    def lon(self) -> float: ...
    @property
    def alt_m(self) -> float | None: ...
    @property
    def fix(self) -> FixQuality: ...
    @property
    def speed_kmh(self) -> float | None: ...
    @property
    def course_deg(self) -> float | None: ...
    @property
    def heading_deg(self) -> float | None: ...
    @property
    def heading_valid(self) -> bool: ...


@dataclass
class PositionerStats:
    epochs: int = 0
    epochs_ignored: int = 0  # repeated UTC (outliers: time.events.outliers)
    seeds: int = 0
    interpolated: int = 0
    extrapolated: int = 0
    extrapolation_capped: int = 0
    unpositioned: int = 0  # edges that arrived before any epoch (held until the first one)
    pending_overflow: int = 0
    time_steps: int = 0  # receiver UTC jumped against the host clock


# A seed waiting for its bracketing epoch: (row, t_land, delay_s), delay_s = t_land − the
# host's edge stamp. A plain tuple: one is made per seed.
_Pending = tuple[int, float, float]
class _Pair(NamedTuple):
    """What interpolating between epochs i−1 and i needs, computed once per pair."""

    t0: float
    dt: float
    degenerate: bool  # t1 <= t0
    east: float
    d_east: float
    north: float
    d_north: float
    up: float
    d_up: float
    speed: float
    d_speed: float
    both_headings: bool
    h0: float
    d_heading: float
    heading: float | None  # when one side has no heading: the other's (or None)
    source: HeadingSource
    fix: FixQuality
    roll: float | None
    d_roll: float
    pitch: float | None
    d_pitch: float


# (east, north, t) of "no previous seed in this row": infinitely long ago
_NO_PREVIOUS = (0.0, 0.0, -math.inf)


class SeedPositioner:
    """Turns GNSS epochs and seed-tube edges into positioned ``SeedDrop``s, per row in order.

    Feed it from the drivers' callbacks (``add_epoch``, ``add_edge``) and call ``poll`` now
    and then so that seeds waiting for an epoch that never comes (GNSS outage) are still
    resolved. Every call returns the seeds it could position, oldest first; ``landings`` keeps
    the local-frame coordinates for tests and benchmarks.
    """

    def __init__(
        self,
        settings: PositioningSection,
        *,
        method: Method | None = None,
        history: int = EPOCH_HISTORY,
        baseline_offset_deg: float = 0.0,
    ) -> None:
        self.settings = settings
        # terrain compensation (geometry.terrain_offset); "none": records say not corrected
        self.attitude_source: AttitudeSource = settings.attitude_source
        self.antenna_height_m = settings.antenna_height_m
        self._attitude = EpochAttitude(settings, baseline_offset_deg)
        self.hitch = settings.hitch
        # which receiver time stamps to believe, on a scale that has no leap-second step
        self.time = GnssTimeGuard()
        self.method: Method = method or settings.method
        rows = len(settings.lateral_offsets())
        self.offsets = [row_offset(settings, r) for r in range(1, rows + 1)]
        self.clock = ClockMap(settings.gnss_output_latency_ms / 1000.0)
        self.frame: LocalFrame | None = None
        self._samples: deque[AntennaSample] = deque(maxlen=history)
        self._pending: deque[_Pending] = deque()
        # edges seen before the receiver's first epoch: positioned (flagged extrapolated) as
        # soon as it arrives rather than dropped, bounded like the pending queue
        self._before_fix: deque[tuple[int, float]] = deque(maxlen=MAX_PENDING_SEEDS)
        self._previous: dict[int, tuple[float, float, float]] = {}  # row → (east, north, t)
        self.stats = PositionerStats()
        # per row (−behind, right) of the lever arm, as rotate_offset multiplies them
        self._lever = [(-o.behind_m, o.right_m) for o in self.offsets]
        self._lever_nb = np.array([-o.behind_m for o in self.offsets], dtype=np.float64)
        self._lever_r = np.array([o.right_m for o in self.offsets], dtype=np.float64)
        self._fall_s = 0.0  # fall time (+ delay_correction_ms) at the speed of _fall_for
        self._fall_for: AntennaSample | None = None
        self._defer = False  # hold ready seeds until settle() (see defer_resolution)

    def recalibrate(self, settings: PositioningSection) -> None:
        """Position seeds from now on with a new calibration (``sowgate calibrate positions``
        saved while the daemon runs): the fall-time table and ``delay_correction_ms``, the
        lever arm and the hitch. Seeds whose edges came before keep the delay they were given
        at their edge (the lever arm is applied at resolution: the new one); the epoch
        history, clock and pending seeds are kept, and a changed hitch restarts the
        implement straight behind it. The row count, method, attitude and latencies are the
        configuration's and need a restart (``settings`` must have as many rows)."""
        rows = len(settings.lateral_offsets())
        if rows != self.rows:
            raise ValueError(f"the new calibration has {rows} rows, the positioner {self.rows}")
        self._attitude.set_hitch(settings.hitch)
        self.settings = settings
        self.hitch = settings.hitch
        self.offsets = [row_offset(settings, r) for r in range(1, rows + 1)]
        self._lever = [(-o.behind_m, o.right_m) for o in self.offsets]
        self._lever_nb = np.array([-o.behind_m for o in self.offsets], dtype=np.float64)
        self._lever_r = np.array([o.right_m for o in self.offsets], dtype=np.float64)
        self._fall_for = None  # the fall time is looked up again with the new correction

    @property
    def rows(self) -> int:
        return len(self.offsets)

    @property
    def pending(self) -> int:
        return len(self._pending)

    # ------------------------------------------------------------ inputs

    def add_epoch(self, epoch: AntennaEpoch) -> list[Landing]:
        check = self.time.judge(epoch.t_mono, _utc_seconds(epoch.utc),
                                getattr(epoch, "leap_second", False))
        if check.message is not None:
            log.warning("%s", check.message)
        out: list[Landing] = []
        if check.verdict == "step":
            # receiver time stepped: finish pending seeds on the old time line, then restart it
            self.stats.time_steps += 1
            out = self.flush()
            self._samples.clear()
            self.clock.reset()
        elif not check.usable:  # an outlier (counted by the guard) or a repeated epoch
            self.stats.epochs_ignored += check.verdict == "repeat"
            return [] if self._defer else self._expire(epoch.t_mono)
        utc_s = check.gnss_s
        if self.frame is None:
            alt0 = epoch.alt_m if epoch.alt_m is not None else 0.0
            self.frame = LocalFrame(epoch.lat, epoch.lon, alt0)
        east, north, up = self.frame.to_enu(epoch.lat, epoch.lon, epoch.alt_m)
        speed = epoch.speed_kmh
        course = epoch.course_deg
        if (speed is None or course is None) and self._samples:
            prev = self._samples[-1]
            dt = utc_s - prev.utc_s
            de, dn = east - prev.east, north - prev.north
            if speed is None:
                speed = math.hypot(de, dn) / dt * KMH_PER_MS
            if course is None and math.hypot(de, dn) > 0.0:
                course = wrap_deg(math.degrees(math.atan2(de, dn)))
        speed = max(0.0, speed or 0.0)
        heading, source = choose_heading(epoch.heading_valid, epoch.heading_deg, course, speed)
        attitude = self._attitude
        roll, pitch = attitude.roll_pitch(epoch)
        climb = attitude.track_pitch(east, north, up, epoch)
        if pitch is None and climb is not None and self.attitude_source != "none":
            pitch = climb
        implement = attitude.follow_hitch(east, north, heading)
        if self._defer and self._would_move_held(epoch.t_mono, utc_s):
            out += self._resolve_ready(force=True)
        self._samples.append(
            AntennaSample(
                utc_s=utc_s,
                t_arrival=epoch.t_mono,
                lat=epoch.lat,
                lon=epoch.lon,
                east=east,
                north=north,
                up=up,
                speed_kmh=speed,
                heading_deg=heading,
                heading_source=source,
                course_deg=course,
                fix=epoch.fix,
                roll_deg=roll,
                pitch_deg=pitch,
                implement_heading_deg=implement,
            )
        )
        self.clock.observe(epoch.t_mono, utc_s)
        self.stats.epochs += 1
        replayed: list[Landing] = []
        while self._before_fix:
            replayed += self.add_edge(*self._before_fix.popleft())
        # this epoch's seeds first (interpolated, not expired), in order; in a batch
        # (defer_resolution) the recorder's poll expires what is overdue once it is in
        out += replayed + self._resolve_ready()
        return out + ([] if self._defer else self._expire(epoch.t_mono))

    def add_attitude(self, t_mono: float, roll_deg: float) -> None:
        """An inclinometer roll reading (degrees, as the sensor reads it) taken at ``t_mono``;
        used by the epochs that follow while fresh (positioning.attitude_source =
        "inclinometer")."""
        self._attitude.add_roll(t_mono, roll_deg)

    def _fall_for_newest(self, newest: AntennaSample) -> float:
        if newest is not self._fall_for:
            # the fall time depends only on the newest epoch's speed: once per epoch, not seed
            self._fall_s = (
                fall_time_s(newest.speed_kmh, self.settings.fall_time_table)
                + self.settings.delay_correction_ms / 1000.0
            )
            self._fall_for = newest
        return self._fall_s

    def add_edge(self, row: int, t_mono: float) -> list[Landing]:
        """A seed passed the sensor of ``row`` at host time ``t_mono`` (already stamped)."""
        if not 1 <= row <= len(self.offsets):
            raise ValueError(f"row {row} outside 1..{self.rows}")
        samples = self._samples
        if not samples:
            if len(self._before_fix) == self._before_fix.maxlen:
                self.stats.pending_overflow += 1
                log.error("no GNSS epoch yet, %d seeds waiting: oldest dropped", MAX_PENDING_SEEDS)
            self.stats.unpositioned += 1
            self._before_fix.append((row, t_mono))
            return []
        t_edge = t_mono - self.settings.seed_edge_latency_ms / 1000.0
        if self.method == "paper":
            return [self._paper(row, t_edge)]
        newest = samples[-1]
        t_land = t_edge + self._fall_for_newest(newest)
        pending = self._pending
        pending.append((row, t_land, t_land - t_mono))
        # The bracketing epoch usually comes after the edge: nothing to resolve yet.
        out = (
            self._resolve_ready()
            if pending[0][1] <= self.clock.mono_of_utc(newest.utc_s) else []
        )
        if len(pending) > MAX_PENDING_SEEDS:
            out += self._overflow()
        # a batch (defer_resolution) may hold this edge's epochs further on: the recorder's
        # poll expires what is overdue, once the batch is in
        if pending and not self._defer and t_mono - pending[0][1] > self.settings.pending_timeout_s:
            out += self._expire(t_mono)
        return out

    def add_edges(self, rows: Sequence[int], times: Sequence[float]) -> list[Landing]:
        """``add_edge`` for a run of edges with no epoch between them, in order.

        The daemon's recorder hands over the edges it queued between two epochs in one go
        (~200 at 2 100 seeds/s): what depends only on the newest epoch (its fall time, the
        host time from which a seed can be resolved) is worked out once per run instead of
        once per seed, and the per-seed step is inlined. Same results, bit for bit, as one
        ``add_edge`` call per edge (a test replays a field both ways). Raises ``ValueError``
        before touching anything if a row is out of range, so the caller can fall back to
        ``add_edge`` one by one and account for the bad edge alone.
        """
        if len(rows) != len(times):
            raise ValueError(f"{len(rows)} rows for {len(times)} edge times")
        if not rows:
            return []
        n_rows = len(self.offsets)
        if min(rows) < 1 or max(rows) > n_rows:
            bad = next(r for r in rows if not 1 <= r <= n_rows)
            raise ValueError(f"row {bad} outside 1..{n_rows}")
        samples = self._samples
        if not samples or self.method == "paper":
            out: list[Landing] = []
            for row, t_mono in zip(rows, times, strict=True):
                out += self.add_edge(row, t_mono)
            return out
        newest = samples[-1]
        fall_s = self._fall_for_newest(newest)
        latency_s = self.settings.seed_edge_latency_ms / 1000.0
        ready_at = self.clock.mono_of_utc(newest.utc_s)
        timeout = self.settings.pending_timeout_s
        pending = self._pending
        append = pending.append
        defer = self._defer
        out = []
        for row, t_mono in zip(rows, times, strict=True):
            t_land = t_mono - latency_s + fall_s
            append((row, t_land, t_land - t_mono))
            if pending[0][1] <= ready_at and not defer:
                out += self._resolve_ready()
            if len(pending) > MAX_PENDING_SEEDS:
                out += self._overflow()
            if pending and not defer and t_mono - pending[0][1] > timeout:
                out += self._expire(t_mono)
        return out

    def poll(self, now_mono: float) -> list[Landing]:
        """Resolve seeds that waited longer than ``pending_timeout_s`` for their epoch."""
        return self._expire(now_mono)

    def flush(self) -> list[Landing]:
        """Resolve everything still pending (shutdown), by extrapolation where needed."""
        out = self._resolve_ready(force=True)
        while self._pending:
            out.append(self._extrapolate(self._pending.popleft()))
        if self._before_fix:
            log.error(
                "%d seeds sensed but never positioned: the GNSS receiver gave no epoch",
                len(self._before_fix),
            )
        return out

    # ------------------------------------------------------------ internals

    def _sample_time(self, s: AntennaSample) -> float:
        return self.clock.mono_of_utc(s.utc_s)

    def _period(self) -> float:
        if len(self._samples) < 3:
            return DEFAULT_EPOCH_PERIOD_S
        utcs = [s.utc_s for s in list(self._samples)[-8:]]
        return statistics.median(b - a for a, b in itertools.pairwise(utcs))

    def defer_resolution(self) -> None:
        """Hold the seeds that become ready instead of positioning them at each epoch, until
        ``settle``.

        The recorder hands over half a second of epochs and edges at once; one vector pass
        over its ~1 000 ready seeds costs far less than five over ~200 (numpy's cost per
        call is most of a pass). A held seed comes out as it would have at its epoch: it is
        positioned before anything that would change its result (the clock offset moving, its
        epochs leaving the history, a timeout or overflow reaching it, a time step). Only the
        choice between the vector and the per-seed path can differ, by an ulp or two.
        """
        self._defer = True

    def settle(self) -> list[Landing]:
        """End ``defer_resolution``: position every held seed, in order."""
        self._defer = False
        return self._resolve_ready()

    def _would_move_held(self, t_mono: float, utc_s: float) -> bool:
        """Would taking this epoch change how the held (ready) seeds come out?"""
        pending, samples = self._pending, self._samples
        if not pending or not samples or pending[0][1] > self._sample_time(samples[-1]):
            return False  # nothing held: only the FIFO's head can be ready first
        if self.clock.would_change(t_mono, utc_s):
            return True
        # appending evicts the oldest epoch: harmless unless a held seed needs that pair
        return len(samples) == samples.maxlen and (
            pending[0][1] - HISTORY_EVICTION_MARGIN_S <= self._sample_time(samples[1])
        )

    def _overflow(self) -> list[Landing]:
        out = self._resolve_ready(force=True) if self._defer else []
        pending = self._pending
        while len(pending) > MAX_PENDING_SEEDS:
            self.stats.pending_overflow += 1
            out.append(self._extrapolate(pending.popleft()))
        return out

    def _resolve_ready(self, *, force: bool = False) -> list[Landing]:
        if not self._samples or (self._defer and not force):
            return []
        pending = self._pending
        newest = self._sample_time(self._samples[-1])
        ready: list[_Pending] = []
        while pending and pending[0][1] <= newest:
            ready.append(pending.popleft())
        return self._interpolate_many(ready) if ready else []

    def _expire(self, now_mono: float) -> list[Landing]:
        pending = self._pending
        if not pending or now_mono - pending[0][1] <= self.settings.pending_timeout_s:
            return []
        # held seeds are positioned first, as they would have been at their epoch
        out: list[Landing] = self._resolve_ready(force=True) if self._defer else []
        timeout = self.settings.pending_timeout_s
        while pending and now_mono - pending[0][1] > timeout:
            out.append(self._extrapolate(pending.popleft()))
        return out

    def _interpolate_many(self, ready: Sequence[_Pending]) -> list[Landing]:
        """``_interpolate`` for a run of seeds at once (the ~20 an epoch releases at 2 000/s).

        Same arithmetic, operation for operation, as ``interpolate_state`` + ``_make`` +
        ``_emit`` (a test replays scenarios through both), but everything that depends only
        on the bracketing pair of epochs (their host times, differences, worst fix and
        heading source, the clock offset) is computed once per pair instead of once per seed.
        Seeds outside the newest pairs' span take the general path. Long runs go to
        ``_interpolate_vector``.
        """
        if self.hitch is not None:
            # a trailed implement: the general path (its lever arm turns apart from the
            # tractor's, which the fast paths do not model)
            return [self._interpolate(p) for p in ready]
        if len(ready) >= VECTOR_MIN_SEEDS and len(self._samples) >= 2:
            return self._interpolate_vector(ready)
        assert self.frame is not None
        samples = self._samples
        n = len(samples)
        off = self.clock.offset_s
        times: list[float] | None = None
        t_lo = samples[-2].utc_s + off if n >= 2 else math.inf
        t_hi = samples[-1].utc_s + off
        pairs: dict[int, _Pair] = {}
        lever_fallback: list[float | None] = []  # _last_known_heading(), looked up once
        offsets = self._lever
        previous = self._previous
        reset_gap = self.settings.spacing_reset_gap_s
        method = self.method
        to_geodetic = self.frame.to_geodetic
        stats = self.stats
        sin, cos, radians, hypot = math.sin, math.cos, math.radians, math.hypot
        fromtimestamp = datetime.fromtimestamp
        posix = self.time.posix_of
        out: list[Landing] = []
        terrain = self.attitude_source != "none"
        lever_of = self._lever_arm
        for p in ready:
            row, t, delay = p
            if t_lo < t <= t_hi:
                i = n - 1
            else:
                if times is None:
                    times = [s.utc_s + off for s in samples]
                i = bisect.bisect_left(times, t)
                if i == 0 or i >= n:
                    out.append(self._interpolate(p))
                    continue
            pair = pairs.get(i)
            if pair is None:
                s0, s1 = samples[i - 1], samples[i]
                t0, t1 = s0.utc_s + off, s1.utc_s + off
                h0, h1 = s0.heading_deg, s1.heading_deg
                if h0 is not None and h1 is not None:
                    both, dh = True, heading_diff(h0, h1)
                    source = worst_heading_source(s0.heading_source, s1.heading_source)
                    h_const: float | None = None
                else:
                    both, dh, source = False, 0.0, "none"
                    h_const = h0 if h0 is not None else h1
                pair = pairs[i] = _Pair(
                    t0, t1 - t0, t1 <= t0, s0.east, s1.east - s0.east, s0.north,
                    s1.north - s0.north, s0.up, s1.up - s0.up, s0.speed_kmh,
                    s1.speed_kmh - s0.speed_kmh, both, 0.0 if h0 is None else h0, dh, h_const,
                    source, worst_fix(s0.fix, s1.fix), *attitude_pair(s0, s1),
                )
            (t0, dt, degenerate, e0, d_e, n0, d_n, u0, d_u, v0, d_v, both, h0, dh, h_const,
             source, fix, roll0, d_roll, pitch0, d_pitch) = pair
            a = 0.0 if degenerate else min(1.0, max(0.0, (t - t0) / dt))
            # interpolate_heading when both epochs have one
            heading = wrap_deg(h0 + a * dh) if both else h_const
            if heading is not None:
                lever_heading: float | None = heading
            else:
                if not lever_fallback:
                    lever_fallback.append(self._last_known_heading())
                lever_heading = lever_fallback[0]
            ant_e, ant_n = e0 + a * d_e, n0 + a * d_n
            roll = None if roll0 is None else roll0 + a * d_roll
            pitch = None if pitch0 is None else pitch0 + a * d_pitch
            if lever_heading is not None:  # rotate_offset
                nb, r = lever_of(row, roll, pitch) if terrain else offsets[row - 1]
                h = radians(lever_heading)
                sh, ch = sin(h), cos(h)
                de, dn = nb * sh + r * ch, nb * ch + r * -sh
            else:
                de, dn = 0.0, 0.0
            east, north = ant_e + de, ant_n + dn
            lat, lon = to_geodetic(east, north, u0 + a * d_u)
            spacing: float | None = None
            prev = previous.get(row)
            if prev is not None and t - prev[2] <= reset_gap:
                spacing = hypot(east - prev[0], north - prev[1])
            previous[row] = (east, north, t)
            stats.seeds += 1
            stats.interpolated += 1
            speed = v0 + a * d_v
            drop = _new_drop(
                row, fromtimestamp(posix(t - off), tz=UTC), lat, lon, fix,
                max(0.0, speed), None if heading is None else wrap_deg(heading),
                source, False, method, spacing,
                *self._attitude_fields(roll, pitch), delay * 1000.0, de, dn,
            )
            out.append(Landing(drop, east, north, t))
        return out

    def _lever_arm(
        self, row: int, roll: float | None, pitch: float | None
    ) -> tuple[float, float]:
        """(−behind, right) of ``row``'s outlet from the antenna, horizontal, for the
        machine's attitude (geometry.terrain_offset; an axis not measured counts as level)."""
        o = self.offsets[row - 1]
        if roll is None and pitch is None:
            return -o.behind_m, o.right_m
        t = terrain_offset(
            o, 0.0 if roll is None else roll, 0.0 if pitch is None else pitch,
            self.antenna_height_m,
        )
        return -t.behind_m, t.right_m

    def _trailed(
        self, row: int, heading: float, implement: float, roll: float | None,
        pitch: float | None,
    ) -> tuple[float, float]:
        """Antenna → outlet of a trailed implement, with the terrain correction of the
        antenna (tractor attitude) and of the outlets' lateral offsets."""
        hitch = self.hitch
        assert hitch is not None
        right = self.offsets[row - 1].right_m
        shift_e = shift_n = 0.0
        if roll is not None or pitch is not None:
            r, p = 0.0 if roll is None else roll, 0.0 if pitch is None else pitch
            # the ground point below the antenna, then up to the hitch: the hitch leans with
            # the tractor by its own height, so the two leans differ by (H - h_hitch)
            forward, sideways = antenna_ground_shift(
                r, p, self.antenna_height_m - hitch.height_m
            )
            shift_e, shift_n = rotate_offset(RowOffset(-forward, sideways), heading)
            right *= math.cos(math.radians(r))
        de, dn = trailed_offset(
            heading, implement, hitch.behind_antenna_m, hitch.outlets_behind_hitch_m, right
        )
        return de + shift_e, dn + shift_n

    def _attitude_fields(
        self, roll: float | None, pitch: float | None
    ) -> tuple[AttitudeSource, float | None, float | None]:
        """A record's (attitude, roll_deg, pitch_deg): the source only when it measured."""
        if roll is None and pitch is None:
            return "none", None, None
        return self.attitude_source, roll, pitch

    def _interpolate_vector(self, ready: Sequence[_Pending]) -> list[Landing]:
        """``_interpolate_many`` with the arithmetic in numpy, for the ~200 seeds an epoch
        releases at 2 000 seeds/s.

        Interpolation, lever arm and the ENU→geodetic conversion run over arrays (the same
        operations as ``interpolate_state`` + ``_make``; numpy's libm may differ from
        ``math`` in the last ulp: sub-nanometre). What stays per seed, in ``ready`` order, is
        the spacing to the row's previous seed and the record row; no ``SeedDrop`` is built
        (``Landing.drop`` builds it on demand). Seeds outside the history, between epochs
        lacking a heading, or with any value outside ``SeedDrop``'s schema go through
        ``_interpolate`` one by one, in their place, exactly as before.
        """
        frame = self.frame
        assert frame is not None
        samples = self._samples
        n = len(samples)
        off = self.clock.offset_s
        k = len(ready)
        pend = np.array(ready, dtype=np.float64).reshape(k, 3)
        t = pend[:, 1]
        rows = pend[:, 0].astype(np.intp)
        delay_ms = pend[:, 2] * 1000.0
        times = np.array([s.utc_s for s in samples], dtype=np.float64) + off
        idx = np.searchsorted(times, t, side="left")
        good = (idx >= 1) & (idx < n)
        i1 = np.where(good, idx, 1)
        i0 = i1 - 1
        # per-pair constants, computed in Python for the few pairs actually used
        pair_ok: dict[int, tuple[FixQuality, HeadingSource] | None] = {}
        for i in np.unique(i1[good]).tolist():
            s0, s1 = samples[i - 1], samples[i]
            fix = worst_fix(s0.fix, s1.fix)
            if (
                s0.heading_deg is None or s1.heading_deg is None
                or type(fix) is not str or fix not in _FIX_NAMES
            ):
                pair_ok[i] = None
            else:
                pair_ok[i] = (fix, worst_heading_source(s0.heading_source, s1.heading_source))
        east_s = np.array([s.east for s in samples], dtype=np.float64)
        north_s = np.array([s.north for s in samples], dtype=np.float64)
        up_s = np.array([s.up for s in samples], dtype=np.float64)
        speed_s = np.array([s.speed_kmh for s in samples], dtype=np.float64)
        head_s = np.array(
            [math.nan if s.heading_deg is None else s.heading_deg for s in samples],
            dtype=np.float64,
        )
        t0 = times[i0]
        dt = times[i1] - t0
        degenerate = times[i1] <= t0
        a = np.where(
            degenerate, 0.0,
            np.minimum(1.0, np.maximum(0.0, (t - t0) / np.where(degenerate, 1.0, dt))),
        )
        h0 = head_s[i0]
        dh = np.mod(head_s[i1] - h0, 360.0)  # heading_diff
        dh = np.where(dh > 180.0, dh - 360.0, dh)
        heading = np.mod(h0 + a * dh, 360.0)  # wrap_deg
        heading = np.where(heading >= 360.0, 0.0, heading)
        e0, n0, u0, v0 = east_s[i0], north_s[i0], up_s[i0], speed_s[i0]
        east = e0 + a * (east_s[i1] - e0)
        north = n0 + a * (north_s[i1] - n0)
        up = u0 + a * (up_s[i1] - u0)
        speed = np.maximum(0.0, v0 + a * (speed_s[i1] - v0))
        h = np.radians(heading)
        sh, ch = np.sin(h), np.cos(h)
        lever = np.clip(rows - 1, 0, len(self.offsets) - 1)
        nb, r = self._lever_nb[lever], self._lever_r[lever]
        roll = pitch = None
        if self.attitude_source != "none":
            roll = lerp_nan(np.array([nan_of(s.roll_deg) for s in samples]), i0, i1, a)
            pitch = lerp_nan(np.array([nan_of(s.pitch_deg) for s in samples]), i0, i1, a)
            rr = np.radians(np.nan_to_num(roll))
            pr = np.radians(np.nan_to_num(pitch))
            height = self.antenna_height_m
            nb = nb * np.cos(pr) + height * np.sin(pr)  # geometry.terrain_offset
            r = r * np.cos(rr) - height * np.sin(rr)
        off_e = nb * sh + r * ch
        off_n = nb * ch + r * -sh
        east = east + off_e
        north = north + off_n
        lat, lon, geo_ok = frame.to_geodetic_many(east, north, up)
        stamps = t - off
        if self.time.has_leaps:  # a leap second seen: back from the continuous scale
            stamps = np.array([self.time.posix_of(x) for x in stamps.tolist()])
        frac, whole = np.modf(stamps)  # utc_us_of, vectorised
        utc_us = whole.astype(np.int64) * 1_000_000 + np.rint(frac * 1e6).astype(np.int64)
        with np.errstate(invalid="ignore"):
            good &= (
                geo_ok & (rows >= 1) & (rows <= _DROP_MAX_ROW)
                & (lat >= -90.0) & (lat <= 90.0) & (lon >= -180.0) & (lon <= 180.0)
                & (speed >= 0.0) & (heading >= 0.0) & (heading < 360.0)
                & np.isfinite(east) & np.isfinite(north)
            )
        extra = self._extra_columns(roll, pitch, delay_ms, off_e, off_n)
        if None not in pair_ok.values() and bool(good.all()):
            return self._landings_of_columns(
                rows, t, i1, pair_ok, east, north, lat, lon, speed, heading, utc_us, extra
            )
        previous = self._previous
        reset_gap = self.settings.spacing_reset_gap_s
        method = self.method
        hypot = math.hypot
        lazy = Landing._lazy
        interpolate = self._interpolate
        out: list[Landing] = []
        done = 0
        for p, ok, i, e, nn, la, lo, v, hd, us, ex in zip(
            ready, good.tolist(), i1.tolist(), east.tolist(), north.tolist(), lat.tolist(),
            lon.tolist(), speed.tolist(), heading.tolist(), utc_us.tolist(),
            zip(*extra, strict=True), strict=True,
        ):
            pair = pair_ok.get(i) if ok else None
            if pair is None:
                out.append(interpolate(p))
                continue
            row, tl, _delay = p
            spacing: float | None = None
            prev = previous.get(row)
            if prev is not None and tl - prev[2] <= reset_gap:
                spacing = hypot(e - prev[0], nn - prev[1])
            previous[row] = (e, nn, tl)
            out.append(lazy(
                (us, row, la, lo, pair[0], v, hd, pair[1], False, method, spacing, *ex),
                e, nn, tl,
            ))
            done += 1
        self.stats.seeds += done
        self.stats.interpolated += done
        return out

    def _landings_of_columns(
        self,
        rows: IntArray,
        t: FloatArray,
        i1: IntArray,
        pair_ok: dict[int, tuple[FixQuality, HeadingSource] | None],
        east: FloatArray,
        north: FloatArray,
        lat: FloatArray,
        lon: FloatArray,
        speed: FloatArray,
        heading: FloatArray,
        utc_us: IntArray,
        extra: tuple[Iterable[object], ...],
    ) -> list[Landing]:
        """The end of ``_interpolate_vector`` when every seed of the run is in range and every
        epoch pair has headings (the usual case): the spacings in numpy too, and the record
        rows zipped from the columns, so no Python statement runs per seed but the
        ``Landing`` itself. Same values as the per-seed loop (spacing to numpy's ``hypot``:
        an ulp at most)."""
        method = self.method
        spacing = self._spacings(rows, east, north, t)
        pairs = set(pair_ok.values())
        if len(pairs) == 1:
            fix, source = next(iter(pairs))  # type: ignore[misc]
            fixes: Iterable[FixQuality] = itertools.repeat(fix)
            sources: Iterable[HeadingSource] = itertools.repeat(source)
        else:
            per_seed = [pair_ok[i] for i in i1.tolist()]
            fixes = [p[0] for p in per_seed]  # type: ignore[index]
            sources = [p[1] for p in per_seed]  # type: ignore[index]
        stored = zip(
            utc_us.tolist(), rows.tolist(), lat.tolist(), lon.tolist(), fixes, speed.tolist(),
            heading.tolist(), sources, itertools.repeat(False), itertools.repeat(method),
            spacing, *extra,
        )
        out = list(map(Landing._lazy, stored, east.tolist(), north.tolist(), t.tolist()))
        self.stats.seeds += len(out)
        self.stats.interpolated += len(out)
        return out

    def _extra_columns(
        self,
        roll: FloatArray | None,
        pitch: FloatArray | None,
        delay_ms: FloatArray,
        off_e: FloatArray,
        off_n: FloatArray,
    ) -> tuple[list[Any], ...]:
        """The record columns after ``spacing_m`` (attitude, roll_deg, pitch_deg, delay_ms,
        offset_east_m, offset_north_m) for a run, as lists in seed order."""
        k = len(delay_ms)
        if roll is None or pitch is None:
            none: list[Any] = [None] * k
            attitude: list[Any] = ["none"] * k
            rolls: list[Any] = none
            pitches: list[Any] = none
        else:
            rolls = [None if x != x else x for x in roll.tolist()]  # NaN: not measured
            pitches = [None if x != x else x for x in pitch.tolist()]
            src = self.attitude_source
            attitude = [
                "none" if ro is None and pi is None else src
                for ro, pi in zip(rolls, pitches, strict=True)
            ]
        return attitude, rolls, pitches, delay_ms.tolist(), off_e.tolist(), off_n.tolist()

    def _spacings(
        self, rows: IntArray, east: FloatArray, north: FloatArray, t: FloatArray
    ) -> list[float | None]:
        """Each seed's distance to the previous seed of its row, for a run in arrival order:
        None for a row's first seed or after a gap over ``spacing_reset_gap_s``, as in the
        per-seed loop. Updates ``_previous`` with each row's last seed."""
        k = len(rows)
        order = np.argsort(rows, kind="stable")  # by row, arrival order kept within a row
        r, e, n, tt = rows[order], east[order], north[order], t[order]
        prev_e, prev_n, prev_t = np.empty(k), np.empty(k), np.empty(k)
        prev_e[1:], prev_n[1:], prev_t[1:] = e[:-1], n[:-1], tt[:-1]
        starts = np.flatnonzero(np.concatenate(([True], r[1:] != r[:-1])))
        ends = np.append(starts[1:], k) - 1
        group_rows = r[starts].tolist()
        previous = self._previous
        # each row's seed before this run, if any (none: too long ago for any spacing)
        before = [previous.get(row, _NO_PREVIOUS) for row in group_rows]
        prev_e[starts], prev_n[starts], prev_t[starts] = zip(*before, strict=True)
        keep = (tt - prev_t) <= self.settings.spacing_reset_gap_s
        spacing = np.empty(k)
        spacing[order] = np.where(keep, np.hypot(e - prev_e, n - prev_n), math.nan)
        previous.update(zip(
            group_rows, zip(e[ends].tolist(), n[ends].tolist(), tt[ends].tolist(), strict=True),
            strict=True,
        ))
        return [None if x != x else x for x in spacing.tolist()]  # x != x: NaN, no spacing

    def _interpolate(self, p: _Pending) -> Landing:
        row, t_land, delay = p
        samples = self._samples
        n = len(samples)
        # Usually the seed lands between the two newest epochs; otherwise bisect with a key,
        # so only the ~log2(history) sample times it looks at are computed.
        if n >= 2 and self._sample_time(samples[-2]) < t_land <= self._sample_time(samples[-1]):
            i = n - 1
        else:
            i = bisect.bisect_left(samples, t_land, key=self._sample_time)
        if i == 0:
            # older than the history: use the oldest epoch as is (only after long stalls)
            t0 = self._sample_time(samples[0])
            state = interpolate_state(samples[0], t0, samples[0], t0, t_land)
            state = replace(state, extrapolated=True)
        elif i >= len(samples):
            return self._extrapolate(p)
        else:
            state = interpolate_state(
                samples[i - 1], self._sample_time(samples[i - 1]),
                samples[i], self._sample_time(samples[i]), t_land,
            )
        self.stats.interpolated += 0 if state.extrapolated else 1
        return self._make(row, t_land, state, delay)

    def _extrapolate(self, p: _Pending) -> Landing:
        row, t_land, delay = p
        last = self._samples[-1]
        prev = self._samples[-2] if len(self._samples) > 1 else None
        last_t = self._sample_time(last)
        prev_t = self._sample_time(prev) if prev is not None else last_t
        if t_land <= last_t:
            return self._interpolate(p)
        horizon = MAX_EXTRAPOLATION_EPOCHS * self._period()
        state, capped = extrapolate_state(prev, prev_t, last, last_t, t_land, horizon)
        self.stats.extrapolated += 1
        if capped:
            # the receiver has been silent too long: the position is a guess, say so
            self.stats.extrapolation_capped += 1
            state = replace(state, fix="none")
        return self._make(row, t_land, state, delay)

    def _make(self, row: int, t_land: float, state: AntennaState, delay: float) -> Landing:
        assert self.frame is not None
        heading = state.heading_deg
        lever_heading = heading if heading is not None else self._last_known_heading()
        roll, pitch = state.roll_deg, state.pitch_deg
        implement = state.implement_heading_deg
        hitch = self.hitch
        if lever_heading is not None and hitch is not None and implement is not None:
            de, dn = self._trailed(row, lever_heading, implement, roll, pitch)
        elif lever_heading is not None:
            nb, r = self._lever_arm(row, roll, pitch)
            de, dn = rotate_offset(RowOffset(-nb, r), lever_heading)
        else:
            de, dn = 0.0, 0.0
        east, north = state.east + de, state.north + dn
        lat, lon = self.frame.to_geodetic(east, north, state.up)
        return self._emit(
            row,
            t_land,
            east,
            north,
            lat,
            lon,
            state.fix,
            state.speed_kmh,
            heading,
            state.heading_source,
            state.extrapolated,
            (*self._attitude_fields(roll, pitch), delay * 1000.0, de, dn),
        )

    def _paper(self, row: int, t_edge: float) -> Landing:
        assert self.frame is not None
        s = self._samples[-1]
        heading = s.heading_deg if s.heading_deg is not None else self._last_known_heading()
        if heading is None:
            lat, lon = s.lat, s.lon
        else:
            lat, lon = paper_landing(
                s.lat, s.lon, heading, s.speed_kmh, self.offsets[row - 1], self.settings
            )
        east, north, _ = self.frame.to_enu(lat, lon)
        t_land = t_edge + self.settings.paper_fall_ms / 1000.0
        return self._emit(
            row, t_land, east, north, lat, lon, s.fix, s.speed_kmh, s.heading_deg,
            s.heading_source, False,
        )

    def _last_known_heading(self) -> float | None:
        for s in reversed(self._samples):
            if s.heading_deg is not None:
                return s.heading_deg
        return None

    def _emit(
        self,
        row: int,
        t_land: float,
        east: float,
        north: float,
        lat: float,
        lon: float,
        fix: FixQuality,
        speed_kmh: float,
        heading: float | None,
        source: HeadingSource,
        extrapolated: bool,
        extra: tuple[AttitudeSource, float | None, float | None, float | None, float | None,
                     float | None] = ("none", None, None, None, None, None),
    ) -> Landing:
        spacing: float | None = None
        prev = self._previous.get(row)
        if prev is not None and t_land - prev[2] <= self.settings.spacing_reset_gap_s:
            spacing = math.hypot(east - prev[0], north - prev[1])
        self._previous[row] = (east, north, t_land)
        self.stats.seeds += 1
        utc = datetime.fromtimestamp(self.time.posix_of(self.clock.utc_of_mono(t_land)), tz=UTC)
        drop = _new_drop(
            row, utc, lat, lon, fix, max(0.0, speed_kmh),
            None if heading is None else wrap_deg(heading), source, extrapolated, self.method,
            spacing, *extra,
        )
        return Landing(drop, east, north, t_land)


def _utc_seconds(utc: datetime) -> float:
    if utc.tzinfo is None:
        utc = utc.replace(tzinfo=UTC)  # receivers speak UTC; a naive stamp is UTC, not local
    return utc.timestamp()
