"""Where each seed landed: outlet geometry, fall time, timing, and the two prediction methods.

Conventions used throughout (and by the simulator's ground truth):

- local ENU metres (east, north) around a fixed origin, WGS84 via pymap3d;
- heading clockwise from north, so the machine's forward unit vector is (sin ψ, cos ψ) and its
  right-hand unit vector is (cos ψ, −sin ψ). A single rotation replaces paper C's four
  quadrant sign tables;
- a row outlet sits ``behind_m`` behind and ``right_m`` right of the main antenna
  (``positioning.outlet_behind_antenna_m`` and ``positioning.row_lateral_m[row-1]``);
- all times are host ``time.monotonic()`` seconds unless named ``utc``.

Methods:

``paper`` — paper C exactly, the baseline: at the sensor edge take the latest fix, assume the
fix is ``t2 + t3`` old and the seed falls for ``t1``, move the outlet forward by
``S_lag = v·(t1+t2+t3)/3600`` and convert millimetres to degrees with 1.112e8 mm/°. Its error
grows with speed because the true fix age is uniform in 0…T, not T/2.

``interpolated`` (default) — put the antenna epochs on the host clock (see :class:`ClockMap`),
compute the instant the seed reaches the furrow (edge + fall time at the current speed), and
interpolate the antenna position and heading at that instant between the two epochs that
bracket it. Because the bracketing epoch usually arrives *after* the edge, the seed waits in a
short pending queue; only when the next epoch does not come in time is it extrapolated, at most
one epoch period ahead, and flagged.

``oracle`` (benchmarks only, :func:`oracle_landing`) — the best any method could do with the
same receiver: it knows the true trajectory and the true landing instant, and adds exactly the
GNSS error the receiver made (position and heading noise of the bracketing epochs, linearly
interpolated to the landing instant). Its error is the receiver's noise through the lever arm,
nothing else.
"""

from __future__ import annotations

import bisect
import itertools
import logging
import math
import statistics
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any, Literal, NamedTuple, Protocol, overload

import numpy as np
import numpy.typing as npt
import pymap3d

from gateway.config.recording import PositioningSection
from gateway.core.records import (
    FixQuality,
    HeadingSource,
    PositionMethod,
    SeedDrop,
    SeedRow,
    drop_row,
    us_to_utc,
)

log = logging.getLogger(__name__)

# Paper C's metres↔degrees constant: 1° of latitude taken as 1.112e8 mm everywhere.
PAPER_MM_PER_DEG = 1.112e8
KMH_PER_MS = 3.6
# Below this speed the course over ground is noise, so it cannot stand in for the heading.
MIN_COURSE_SPEED_KMH = 1.0
# Epochs kept: enough to bracket any pending seed (pending timeout / 10 Hz) several times over.
EPOCH_HISTORY = 64
# Epochs over which the UTC↔monotonic offset is estimated (10 s at 10 Hz; drift ≪ 1 ms).
CLOCK_WINDOW_EPOCHS = 100
# A change of (arrival − UTC) this large is not jitter but a time step (receiver restart, a
# wrong date): the clock mapping and the epoch history start again.
CLOCK_STEP_S = 2.0
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
FIX_RANK: dict[FixQuality, int] = {
    "none": 0, "single": 1, "dgps": 2, "rtk_float": 3, "rtk_fixed": 4,
}
HEADING_RANK: dict[HeadingSource, int] = {"none": 0, "course": 1, "dual_antenna": 2}

Method = Literal["interpolated", "paper"]
FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
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


class PoseLike(Protocol):
    """A true antenna pose in local ENU (``simulator.plant.Pose``)."""

    @property
    def east(self) -> float: ...
    @property
    def north(self) -> float: ...
    @property
    def heading_deg(self) -> float: ...


# ---------------------------------------------------------------- geometry


@dataclass(frozen=True)
class RowOffset:
    """A row outlet relative to the main antenna, in the machine frame."""

    behind_m: float
    right_m: float


def row_offset(settings: PositioningSection, row: int) -> RowOffset:
    lateral = settings.lateral_offsets()
    if not 1 <= row <= len(lateral):
        raise ValueError(f"row {row} outside 1..{len(lateral)} (positioning.row_lateral_m)")
    return RowOffset(settings.outlet_behind_antenna_m, lateral[row - 1])


def rotate_offset(offset: RowOffset, heading_deg: float) -> tuple[float, float]:
    """(east, north) displacement from the antenna to the outlet for a machine heading."""
    h = math.radians(heading_deg)
    fwd_e, fwd_n = math.sin(h), math.cos(h)
    right_e, right_n = math.cos(h), -math.sin(h)
    return (
        -offset.behind_m * fwd_e + offset.right_m * right_e,
        -offset.behind_m * fwd_n + offset.right_m * right_n,
    )


def fall_time_s(speed_kmh: float, table: Sequence[tuple[float, float]]) -> float:
    """Sensor-to-furrow fall time: linear in the (km/h, ms) table, clamped at its ends."""
    if not table:
        raise ValueError("fall time table is empty")
    speeds = [s for s, _ in table]
    if speed_kmh <= speeds[0]:
        return table[0][1] / 1000.0
    if speed_kmh >= speeds[-1]:
        return table[-1][1] / 1000.0
    i = bisect.bisect_right(speeds, speed_kmh)
    (s0, t0), (s1, t1) = table[i - 1], table[i]
    a = (speed_kmh - s0) / (s1 - s0)
    return (t0 + a * (t1 - t0)) / 1000.0


def wrap_deg(angle: float) -> float:
    """Angle in [0, 360); guards the float case where ``x % 360`` returns 360.0."""
    a = angle % 360.0
    return 0.0 if a >= 360.0 else a


def heading_diff(h0: float, h1: float) -> float:
    """Signed shortest turn from h0 to h1, in (−180, 180]."""
    d = (h1 - h0) % 360.0
    return d - 360.0 if d > 180.0 else d


def interpolate_heading(h0: float, h1: float, a: float) -> float:
    """Heading a fraction ``a`` of the way from h0 to h1 along the short arc (359 → 1 via 0)."""
    return wrap_deg(h0 + a * heading_diff(h0, h1))


# WGS84, as pymap3d's Ellipsoid.from_name("wgs84") defines it.
_WGS84_A = 6378137.0
_WGS84_B = 6356752.31424518
_WGS84_E2 = _WGS84_A**2 - _WGS84_B**2  # E² of You (2000)
# Below this |u| or distance from the polar axis (m) You's formula divides by ~0: use pymap3d.
_GEODETIC_FAST_MIN_M = 1000.0


@dataclass(frozen=True)
class LocalFrame:
    """A WGS84 ↔ local ENU tangent frame (pymap3d) around a fixed origin."""

    lat0: float
    lon0: float
    alt0: float = 0.0
    # origin in ECEF and the ENU→ECEF rotation, computed once (see to_geodetic)
    _origin: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        x0, y0, z0 = pymap3d.geodetic2ecef(self.lat0, self.lon0, self.alt0)
        la, lo = math.radians(self.lat0), math.radians(self.lon0)
        origin = (float(x0), float(y0), float(z0),
                  math.sin(la), math.cos(la), math.sin(lo), math.cos(lo))
        object.__setattr__(self, "_origin", origin)

    def to_enu(
        self, lat: float, lon: float, alt: float | None = None
    ) -> tuple[float, float, float]:
        e, n, u = pymap3d.geodetic2enu(
            lat, lon, self.alt0 if alt is None else alt, self.lat0, self.lon0, self.alt0
        )
        return float(e), float(n), float(u)

    @overload
    def _ecef(self, east: float, north: float, up: float) -> tuple[float, float, float]: ...
    @overload
    def _ecef(
        self, east: FloatArray, north: FloatArray, up: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    def _ecef(self, east: Any, north: Any, up: Any) -> tuple[Any, Any, Any]:
        """Local ENU → ECEF: the rotation both geodesy paths share (floats or arrays)."""
        x0, y0, z0, sin_la, cos_la, sin_lo, cos_lo = self._origin
        t = cos_la * up - sin_la * north
        z = z0 + sin_la * up + cos_la * north
        x = x0 + cos_lo * t - sin_lo * east
        y = y0 + sin_lo * t + cos_lo * east
        return x, y, z

    def to_geodetic(self, east: float, north: float, up: float = 0.0) -> tuple[float, float]:
        """pymap3d's ``enu2geodetic`` (You 2000, non-iterative) in scalar ``math``.

        Called once per seed: pymap3d on scalars goes through numpy (~150 µs a call, most
        of the daemon's CPU at 2 000 seeds/s); these are the same formulas on plain floats
        (~3 µs) and agree with pymap3d to ~1e-12° (tested). Near the poles, where the
        formula's special cases apply, pymap3d itself answers.
        """
        x, y, z = self._ecef(east, north, up)
        r2 = x * x + y * y + z * z
        e2 = _WGS84_E2
        u = math.sqrt(0.5 * (r2 - e2) + 0.5 * math.hypot(r2 - e2, 2.0 * math.sqrt(e2) * z))
        hxy = math.hypot(x, y)
        if u < _GEODETIC_FAST_MIN_M or hxy < _GEODETIC_FAST_MIN_M:
            lat, lon, _h = pymap3d.enu2geodetic(
                east, north, up, self.lat0, self.lon0, self.alt0
            )
            return float(lat), float(lon)
        hue = math.hypot(u, math.sqrt(e2))
        beta = math.atan(hue / u * z / hxy)
        beta += ((_WGS84_B * u - _WGS84_A * hue + e2) * math.sin(beta)) / (
            _WGS84_A * hue * 1 / math.cos(beta) - e2 * math.cos(beta)
        )
        lat = math.atan(_WGS84_A / _WGS84_B * math.tan(beta))
        return math.degrees(lat), math.degrees(math.atan2(y, x))

    def to_geodetic_many(
        self, east: FloatArray, north: FloatArray, up: FloatArray
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """``to_geodetic`` over arrays, in numpy: (lat, lon, ok).

        The same formulas, operation for operation, so results agree with the scalar path to
        an ulp or two of numpy's libm (≪ 1e-12°). Where ``ok`` is False (near the poles or
        the Earth's centre) the values are meaningless: use the scalar ``to_geodetic``.
        """
        x, y, z = self._ecef(east, north, up)
        r2 = x * x + y * y + z * z
        e2 = _WGS84_E2
        u = np.sqrt(0.5 * (r2 - e2) + 0.5 * np.hypot(r2 - e2, 2.0 * math.sqrt(e2) * z))
        hxy = np.hypot(x, y)
        ok = (u >= _GEODETIC_FAST_MIN_M) & (hxy >= _GEODETIC_FAST_MIN_M)
        if not ok.all():
            u = np.where(ok, u, _GEODETIC_FAST_MIN_M)
            hxy = np.where(ok, hxy, _GEODETIC_FAST_MIN_M)
        hue = np.hypot(u, math.sqrt(e2))
        beta = np.arctan(hue / u * z / hxy)
        beta += ((_WGS84_B * u - _WGS84_A * hue + e2) * np.sin(beta)) / (
            _WGS84_A * hue * 1 / np.cos(beta) - e2 * np.cos(beta)
        )
        lat = np.arctan(_WGS84_A / _WGS84_B * np.tan(beta))
        return np.degrees(lat), np.degrees(np.arctan2(y, x)), ok


# ---------------------------------------------------------------- paper C


def paper_lag_m(speed_kmh: float, settings: PositioningSection) -> float:
    """``S_lag = v·(t1 + t2 + t3)/3600`` in metres (v in km/h, t in ms)."""
    total_ms = settings.paper_fall_ms + settings.paper_fix_age_ms + settings.paper_transmission_ms
    return speed_kmh * total_ms / 3600.0


def paper_landing(
    lat: float,
    lon: float,
    heading_deg: float,
    speed_kmh: float,
    offset: RowOffset,
    settings: PositioningSection,
) -> tuple[float, float]:
    """Paper C's landing point from the latest fix: lag-shortened lever arm, 1.112e8 mm/°."""
    shortened = RowOffset(offset.behind_m - paper_lag_m(speed_kmh, settings), offset.right_m)
    de_m, dn_m = rotate_offset(shortened, heading_deg)
    d_lat = dn_m * 1000.0 / PAPER_MM_PER_DEG
    d_lon = de_m * 1000.0 / (PAPER_MM_PER_DEG * math.cos(math.radians(lat)))
    return lat + d_lat, lon + d_lon


# ---------------------------------------------------------------- timing


class ClockMap:
    """Maps receiver UTC to the host monotonic clock: ``t_mono = utc + offset``.

    Each epoch's first sentence reaches the host at ``instant + L + J``: ``L`` is the receiver's
    fixed output latency (solution computation plus the serial transmission of the first
    sentence, from config — it cannot be observed from the host side alone) and ``J ≥ 0`` is
    jitter (UART/USB polling, scheduler wake-ups, the occasional burst). The arrival time of
    any single epoch is therefore late by an unknown J, up to tens of ms, which at 12 km/h is
    tens of mm. The UTC stamp, on the other hand, is exact to the receiver's PPS.

    So the offset is estimated as ``min over recent epochs of (t_mono − utc) − L``. Because J
    is one-sided, the minimum is the right statistic: it converges to ``offset + min J`` within
    a few epochs, ignores heavy tails, whereas a mean would be biased by E[J] and dragged
    around by bursts. The window (:data:`CLOCK_WINDOW_EPOCHS`) is short enough that crystal
    drift between host and receiver (≤ 50 ppm → 0.5 ms per 10 s) does not accumulate, and long
    enough to contain some near-zero-jitter epochs. The result is timing good to about 1 ms
    instead of the whole fix-age uncertainty that paper C has to absorb as a constant T/2.
    """

    def __init__(self, latency_s: float, window: int = CLOCK_WINDOW_EPOCHS) -> None:
        self.latency_s = latency_s
        self._samples: deque[float] = deque(maxlen=window)
        # min(self._samples), kept up to date by observe(): every seed maps several times
        # and the window only changes once per epoch
        self._min_raw = 0.0

    def observe(self, t_mono: float, utc_s: float) -> None:
        raw = t_mono - utc_s
        if self._samples and abs(raw - self._min_raw) > CLOCK_STEP_S:
            self._samples.clear()  # a time step: the old offsets describe another clock
        self._samples.append(raw)
        self._min_raw = min(self._samples)

    def would_change(self, t_mono: float, utc_s: float) -> bool:
        """Would ``observe(t_mono, utc_s)`` move the offset (a new minimum, the minimum
        leaving the window, or a step)?"""
        samples = self._samples
        if not samples:
            return True
        raw = t_mono - utc_s
        if raw < self._min_raw or abs(raw - self._min_raw) > CLOCK_STEP_S:
            return True
        if len(samples) == samples.maxlen and samples[0] == self._min_raw:
            return min(min(itertools.islice(samples, 1, None)), raw) != self._min_raw
        return False

    def is_step(self, t_mono: float, utc_s: float) -> bool:
        """Would this epoch be a time step rather than jitter?"""
        return bool(self._samples) and abs(t_mono - utc_s - self._min_raw) > CLOCK_STEP_S

    @property
    def ready(self) -> bool:
        return bool(self._samples)

    @property
    def offset_s(self) -> float:
        if not self._samples:
            raise ValueError("no epoch observed yet")
        return self._min_raw - self.latency_s

    def mono_of_utc(self, utc_s: float) -> float:
        return utc_s + self.offset_s

    def utc_of_mono(self, t_mono: float) -> float:
        return t_mono - self.offset_s


# ---------------------------------------------------------------- antenna samples


@dataclass(frozen=True)
class AntennaSample:
    """One epoch in the local frame, with the heading already chosen (dual antenna/course)."""

    utc_s: float
    t_arrival: float
    lat: float
    lon: float
    east: float
    north: float
    up: float
    speed_kmh: float
    heading_deg: float | None
    heading_source: HeadingSource
    course_deg: float | None
    fix: FixQuality


def choose_heading(
    heading_valid: bool,
    heading_deg: float | None,
    course_deg: float | None,
    speed_kmh: float,
) -> tuple[float | None, HeadingSource]:
    """Dual-antenna heading when valid; else course over ground while moving; else none."""
    if heading_valid and heading_deg is not None:
        return wrap_deg(heading_deg), "dual_antenna"
    if course_deg is not None and speed_kmh >= MIN_COURSE_SPEED_KMH:
        return wrap_deg(course_deg), "course"
    return None, "none"


@dataclass(frozen=True)
class AntennaState:
    """The antenna at one instant, interpolated or extrapolated from samples."""

    east: float
    north: float
    up: float
    speed_kmh: float
    heading_deg: float | None
    heading_source: HeadingSource
    fix: FixQuality
    extrapolated: bool


def worst_fix(a: FixQuality, b: FixQuality) -> FixQuality:
    return a if FIX_RANK[a] <= FIX_RANK[b] else b


def worst_heading_source(a: HeadingSource, b: HeadingSource) -> HeadingSource:
    return a if HEADING_RANK[a] <= HEADING_RANK[b] else b


def interpolate_state(
    s0: AntennaSample, t0: float, s1: AntennaSample, t1: float, t: float
) -> AntennaState:
    """Linear in position and speed, short-arc in heading, between two epochs (t0 ≤ t ≤ t1)."""
    a = 0.0 if t1 <= t0 else min(1.0, max(0.0, (t - t0) / (t1 - t0)))
    if s0.heading_deg is not None and s1.heading_deg is not None:
        heading: float | None = interpolate_heading(s0.heading_deg, s1.heading_deg, a)
        source = worst_heading_source(s0.heading_source, s1.heading_source)
    else:
        # one side lacks a heading: use the other one's, flagged as no better than "none"
        heading = s0.heading_deg if s0.heading_deg is not None else s1.heading_deg
        source = "none"
    return AntennaState(
        east=s0.east + a * (s1.east - s0.east),
        north=s0.north + a * (s1.north - s0.north),
        up=s0.up + a * (s1.up - s0.up),
        speed_kmh=s0.speed_kmh + a * (s1.speed_kmh - s0.speed_kmh),
        heading_deg=heading,
        heading_source=source,
        fix=worst_fix(s0.fix, s1.fix),
        extrapolated=False,
    )


def extrapolate_state(
    prev: AntennaSample | None,
    prev_t: float,
    last: AntennaSample,
    last_t: float,
    t: float,
    horizon_s: float,
) -> tuple[AntennaState, bool]:
    """Dead-reckon from the last epoch to ``t``, capped at ``horizon_s`` past it.

    Velocity comes from the Doppler speed along the course (or heading): the receiver's speed
    is far less noisy than a difference of two 10 mm-noise positions 0.1 s apart. The heading
    turns at the rate seen between the last two epochs. Returns the state and whether the cap
    was hit (the seed landed further ahead than the model allows to guess).
    """
    dt = t - last_t
    capped = dt > horizon_s
    dt = min(dt, horizon_s)
    direction = last.course_deg if last.course_deg is not None else last.heading_deg
    v = last.speed_kmh / KMH_PER_MS
    if direction is None and prev is not None and last_t > prev_t:
        de, dn = last.east - prev.east, last.north - prev.north
        ve, vn = de / (last_t - prev_t), dn / (last_t - prev_t)
    elif direction is None:
        ve = vn = 0.0
    else:
        ve, vn = v * math.sin(math.radians(direction)), v * math.cos(math.radians(direction))
    heading = last.heading_deg
    if (
        heading is not None
        and prev is not None
        and prev.heading_deg is not None
        and last_t > prev_t
    ):
        rate = heading_diff(prev.heading_deg, heading) / (last_t - prev_t)
        heading = wrap_deg(heading + rate * dt)
    state = AntennaState(
        east=last.east + ve * dt,
        north=last.north + vn * dt,
        up=last.up,
        speed_kmh=last.speed_kmh,
        heading_deg=heading,
        heading_source=last.heading_source,
        fix=last.fix,
        extrapolated=True,
    )
    return state, capped


# ---------------------------------------------------------------- oracle


@dataclass(frozen=True)
class MeasuredEpoch:
    """A receiver epoch at its TRUE instant, in the same local ENU as the ground truth."""

    t_true: float
    east: float
    north: float
    heading_deg: float


def oracle_landing(
    offset: RowOffset,
    t_land: float,
    true_pose_at: Callable[[float], PoseLike],
    epochs: Sequence[MeasuredEpoch],
) -> tuple[float, float]:
    """The landing point the best possible method would report with this receiver.

    Definition: for each epoch k the receiver's error is ``measured_k − true(t_k)`` in east,
    north and heading (wrapped). The oracle takes the TRUE antenna pose at the TRUE landing
    instant, adds the error linearly interpolated between the epochs bracketing ``t_land``
    (the nearest epoch's error outside the range), and applies the row's lever arm with the
    erroneous heading. It has no timing error and no trajectory-model error; what remains is
    the GNSS noise as an interpolating method would see it. ``epochs`` must be sorted by time.
    """
    if not epochs:
        raise ValueError("oracle needs at least one measured epoch")
    times = [ep.t_true for ep in epochs]
    i = bisect.bisect_right(times, t_land)
    if i == 0:
        ks, a = (0, 0), 0.0
    elif i >= len(epochs):
        ks, a = (len(epochs) - 1, len(epochs) - 1), 0.0
    else:
        t0, t1 = times[i - 1], times[i]
        ks, a = (i - 1, i), (0.0 if t1 <= t0 else (t_land - t0) / (t1 - t0))

    def error(k: int) -> tuple[float, float, float]:
        ep = epochs[k]
        truth = true_pose_at(ep.t_true)
        return (
            ep.east - truth.east,
            ep.north - truth.north,
            heading_diff(truth.heading_deg, ep.heading_deg),
        )

    e0, e1 = error(ks[0]), error(ks[1])
    err = [x0 + a * (x1 - x0) for x0, x1 in zip(e0, e1, strict=True)]
    truth = true_pose_at(t_land)
    de, dn = rotate_offset(offset, wrap_deg(truth.heading_deg + err[2]))
    return truth.east + err[0] + de, truth.north + err[1] + dn


# ---------------------------------------------------------------- the positioner


@dataclass
class PositionerStats:
    epochs: int = 0
    epochs_ignored: int = 0  # repeated or out-of-order UTC
    seeds: int = 0
    interpolated: int = 0
    extrapolated: int = 0
    extrapolation_capped: int = 0
    unpositioned: int = 0  # edges that arrived before any epoch (held until the first one)
    pending_overflow: int = 0
    time_steps: int = 0  # receiver UTC jumped against the host clock


# A seed waiting for its bracketing epoch: (row, t_land). A plain tuple: one is made per seed.
_Pending = tuple[int, float]
_DROP_FIELDS = frozenset(SeedDrop.model_fields)
_object_new = object.__new__
_setattr = object.__setattr__


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


_FIX_NAMES = frozenset(FIX_RANK)
# (east, north, t) of "no previous seed in this row": infinitely long ago
_NO_PREVIOUS = (0.0, 0.0, -math.inf)
# SeedDrop's own bounds (gateway/core/records.py), checked before skipping its validation.
_DROP_MAX_ROW = 128


def _new_drop(
    row: int,
    utc: datetime,
    lat: float,
    lon: float,
    fix: FixQuality,
    speed_kmh: float,
    heading_deg: float | None,
    heading_source: HeadingSource,
    extrapolated: bool,
    method: PositionMethod,
    spacing_m: float | None,
) -> SeedDrop:
    """A ``SeedDrop`` without pydantic validation when the values already satisfy it.

    Validation is ~6 µs of the ~20 µs a seed costs, and every value here is valid by
    construction (wrapped headings, clamped speeds, hypot spacings, a geodetic conversion).
    The bounds and types are still checked, cheaply; anything odd (a NaN from a broken epoch,
    an int subclass) goes through the real validator and fails or coerces exactly as before.
    A test checks the result equals a validated drop.
    """
    if (
        type(row) is int and 1 <= row <= _DROP_MAX_ROW
        and type(lat) is float and -90.0 <= lat <= 90.0
        and type(lon) is float and -180.0 <= lon <= 180.0
        and type(speed_kmh) is float and speed_kmh >= 0.0
        and (heading_deg is None or (type(heading_deg) is float and 0.0 <= heading_deg < 360.0))
        and (spacing_m is None or (type(spacing_m) is float and spacing_m >= 0.0))
        and type(fix) is str and fix in _FIX_NAMES
    ):
        drop = _object_new(SeedDrop)
        _setattr(drop, "__dict__", {
            "row": row, "utc": utc, "lat": lat, "lon": lon, "fix": fix,
            "speed_kmh": speed_kmh, "heading_deg": heading_deg,
            "heading_source": heading_source, "extrapolated": extrapolated,
            "method": method, "spacing_m": spacing_m,
        })
        _setattr(drop, "__pydantic_fields_set__", set(_DROP_FIELDS))
        _setattr(drop, "__pydantic_extra__", None)
        _setattr(drop, "__pydantic_private__", None)
        return drop
    return SeedDrop(
        row=row, utc=utc, lat=lat, lon=lon, fix=fix, speed_kmh=speed_kmh,
        heading_deg=heading_deg, heading_source=heading_source, extrapolated=extrapolated,
        method=method, spacing_m=spacing_m,
    )


def utc_us_of(ts: float) -> int:
    """``datetime.fromtimestamp(ts, UTC)`` as integer microseconds, rounded as CPython does."""
    frac, whole = math.modf(ts)
    us = round(frac * 1e6)  # half to even, like _PyTime_ROUND_HALF_EVEN
    return int(whole) * 1_000_000 + us


class Landing:
    """A positioned seed in the local frame, alongside the record it became.

    ``stored`` holds the record as the store writes it (a ``SeedRow``); ``drop`` (the
    ``SeedDrop``) is built from it on first access, so the daemon, which only stores rows,
    never builds one. Rows
    given to :meth:`_lazy` must already satisfy ``SeedDrop``'s schema (the positioner checks).
    """

    __slots__ = ("_drop", "east", "north", "stored", "t_land")

    def __init__(self, drop: SeedDrop, east: float, north: float, t_land: float) -> None:
        self._drop: SeedDrop | None = drop
        self.stored: SeedRow = drop_row(drop)
        self.east = east
        self.north = north
        self.t_land = t_land

    @classmethod
    def _lazy(cls, row: SeedRow, east: float, north: float, t_land: float) -> Landing:
        la = _object_new(cls)
        la._drop = None
        la.stored = row
        la.east = east
        la.north = north
        la.t_land = t_land
        return la

    @property
    def drop(self) -> SeedDrop:
        drop = self._drop
        if drop is None:
            us, row, lat, lon, fix, speed, heading, source, extrap, method, spacing = self.stored
            drop = _new_drop(
                row, us_to_utc(us), lat, lon, fix, speed, heading,
                source, extrap, method, spacing,
            )
            self._drop = drop
        return drop

    def _key(self) -> tuple[SeedRow, float, float, float]:
        return (self.stored, self.east, self.north, self.t_land)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Landing):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        return (
            f"Landing(drop={self.drop!r}, east={self.east!r}, north={self.north!r}, "
            f"t_land={self.t_land!r})"
        )


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
    ) -> None:
        self.settings = settings
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
        self._fall_s = 0.0  # fall time at the speed of the epoch _fall_for
        self._fall_for: AntennaSample | None = None
        self._defer = False  # hold ready seeds until settle() (see defer_resolution)

    @property
    def rows(self) -> int:
        return len(self.offsets)

    @property
    def pending(self) -> int:
        return len(self._pending)

    # ------------------------------------------------------------ inputs

    def add_epoch(self, epoch: AntennaEpoch) -> list[Landing]:
        utc_s = _utc_seconds(epoch.utc)
        out: list[Landing] = []
        if self.clock.is_step(epoch.t_mono, utc_s):
            # receiver time jumped: finish pending seeds on the old time line, then restart it
            self.stats.time_steps += 1
            log.warning("GNSS time stepped by %.1f s: restarting the epoch history",
                        epoch.t_mono - utc_s - self.clock.offset_s - self.clock.latency_s)
            out = self.flush()
            self._samples.clear()
        elif self._samples and utc_s <= self._samples[-1].utc_s:
            self.stats.epochs_ignored += 1
            return self._expire(epoch.t_mono)
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
            )
        )
        self.clock.observe(epoch.t_mono, utc_s)
        self.stats.epochs += 1
        replayed: list[Landing] = []
        while self._before_fix:
            replayed += self.add_edge(*self._before_fix.popleft())
        return out + replayed + self._resolve_ready() + self._expire(epoch.t_mono)

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
        if newest is not self._fall_for:
            # the fall time depends only on the newest epoch's speed: once per epoch, not seed
            self._fall_s = fall_time_s(newest.speed_kmh, self.settings.fall_time_table)
            self._fall_for = newest
        t_land = t_edge + self._fall_s
        pending = self._pending
        pending.append((row, t_land))
        # The bracketing epoch usually comes after the edge: nothing to resolve yet.
        out = (
            self._resolve_ready()
            if pending[0][1] <= self.clock.mono_of_utc(newest.utc_s) else []
        )
        if len(pending) > MAX_PENDING_SEEDS:
            out += self._overflow()
        if pending and t_mono - pending[0][1] > self.settings.pending_timeout_s:
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
        if newest is not self._fall_for:
            self._fall_s = fall_time_s(newest.speed_kmh, self.settings.fall_time_table)
            self._fall_for = newest
        latency_s = self.settings.seed_edge_latency_ms / 1000.0
        fall_s = self._fall_s
        ready_at = self.clock.mono_of_utc(newest.utc_s)
        timeout = self.settings.pending_timeout_s
        pending = self._pending
        append = pending.append
        defer = self._defer
        out = []
        for row, t_mono in zip(rows, times, strict=True):
            append((row, t_mono - latency_s + fall_s))
            if pending[0][1] <= ready_at and not defer:
                out += self._resolve_ready()
            if len(pending) > MAX_PENDING_SEEDS:
                out += self._overflow()
            if pending and t_mono - pending[0][1] > timeout:
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
        out: list[Landing] = []
        for p in ready:
            row, t = p
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
                    source, worst_fix(s0.fix, s1.fix),
                )
            (t0, dt, degenerate, e0, d_e, n0, d_n, u0, d_u, v0, d_v, both, h0, dh, h_const,
             source, fix) = pair
            a = 0.0 if degenerate else min(1.0, max(0.0, (t - t0) / dt))
            # interpolate_heading when both epochs have one
            heading = wrap_deg(h0 + a * dh) if both else h_const
            if heading is not None:
                lever_heading: float | None = heading
            else:
                if not lever_fallback:
                    lever_fallback.append(self._last_known_heading())
                lever_heading = lever_fallback[0]
            east, north = e0 + a * d_e, n0 + a * d_n
            if lever_heading is not None:  # rotate_offset
                nb, r = offsets[row - 1]
                h = radians(lever_heading)
                sh, ch = sin(h), cos(h)
                east, north = east + (nb * sh + r * ch), north + (nb * ch + r * -sh)
            else:
                east, north = east + 0.0, north + 0.0
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
                row, fromtimestamp(t - off, tz=UTC), lat, lon, fix,
                max(0.0, speed), None if heading is None else wrap_deg(heading),
                source, False, method, spacing,
            )
            out.append(Landing(drop, east, north, t))
        return out

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
        pend = np.array(ready, dtype=np.float64).reshape(k, 2)
        t = pend[:, 1]
        rows = pend[:, 0].astype(np.intp)
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
        east = east + (nb * sh + r * ch)
        north = north + (nb * ch + r * -sh)
        lat, lon, geo_ok = frame.to_geodetic_many(east, north, up)
        frac, whole = np.modf(t - off)  # utc_us_of, vectorised
        utc_us = whole.astype(np.int64) * 1_000_000 + np.rint(frac * 1e6).astype(np.int64)
        with np.errstate(invalid="ignore"):
            good &= (
                geo_ok & (rows >= 1) & (rows <= _DROP_MAX_ROW)
                & (lat >= -90.0) & (lat <= 90.0) & (lon >= -180.0) & (lon <= 180.0)
                & (speed >= 0.0) & (heading >= 0.0) & (heading < 360.0)
                & np.isfinite(east) & np.isfinite(north)
            )
        if None not in pair_ok.values() and bool(good.all()):
            return self._landings_of_columns(
                rows, t, i1, pair_ok, east, north, lat, lon, speed, heading, utc_us
            )
        previous = self._previous
        reset_gap = self.settings.spacing_reset_gap_s
        method = self.method
        hypot = math.hypot
        lazy = Landing._lazy
        interpolate = self._interpolate
        out: list[Landing] = []
        done = 0
        for p, ok, i, e, nn, la, lo, v, hd, us in zip(
            ready, good.tolist(), i1.tolist(), east.tolist(), north.tolist(), lat.tolist(),
            lon.tolist(), speed.tolist(), heading.tolist(), utc_us.tolist(), strict=True,
        ):
            pair = pair_ok.get(i) if ok else None
            if pair is None:
                out.append(interpolate(p))
                continue
            row, tl = p
            spacing: float | None = None
            prev = previous.get(row)
            if prev is not None and tl - prev[2] <= reset_gap:
                spacing = hypot(e - prev[0], nn - prev[1])
            previous[row] = (e, nn, tl)
            out.append(lazy(
                (us, row, la, lo, pair[0], v, hd, pair[1], False, method, spacing), e, nn, tl,
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
            spacing,
        )
        out = list(map(Landing._lazy, stored, east.tolist(), north.tolist(), t.tolist()))
        self.stats.seeds += len(out)
        self.stats.interpolated += len(out)
        return out

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
        row, t_land = p
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
        return self._make(row, t_land, state)

    def _extrapolate(self, p: _Pending) -> Landing:
        row, t_land = p
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
        return self._make(row, t_land, state)

    def _make(self, row: int, t_land: float, state: AntennaState) -> Landing:
        assert self.frame is not None
        offset = self.offsets[row - 1]
        heading = state.heading_deg
        lever_heading = heading if heading is not None else self._last_known_heading()
        de, dn = rotate_offset(offset, lever_heading) if lever_heading is not None else (0.0, 0.0)
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
    ) -> Landing:
        spacing: float | None = None
        prev = self._previous.get(row)
        if prev is not None and t_land - prev[2] <= self.settings.spacing_reset_gap_s:
            spacing = math.hypot(east - prev[0], north - prev[1])
        self._previous[row] = (east, north, t_land)
        self.stats.seeds += 1
        utc = datetime.fromtimestamp(self.clock.utc_of_mono(t_land), tz=UTC)
        drop = _new_drop(
            row, utc, lat, lon, fix, max(0.0, speed_kmh),
            None if heading is None else wrap_deg(heading), source, extrapolated, self.method,
            spacing,
        )
        return Landing(drop, east, north, t_land)


def _utc_seconds(utc: datetime) -> float:
    if utc.tzinfo is None:
        utc = utc.replace(tzinfo=UTC)  # receivers speak UTC; a naive stamp is UTC, not local
    return utc.timestamp()
