"""Re-positioning stored seeds, and fitting the position model to surveyed seeds.

A field check finds seeds that did not land where the records say: a lever arm measured with
a tape to the wrong mark, a fall time of another seed lot or airflow, a latency nobody
measured. These errors are systematic, so a few dozen seeds dug up and surveyed with an RTK
rover are enough to fit them out:

- :func:`reposition` puts one stored record where the current model (fall-time table,
  ``delay_correction_ms``, lever arm, antenna height) says it landed. It needs what every
  record keeps for that: the antenna position at the landing instant (``offset_east_m`` /
  ``offset_north_m`` back from the seed), the edge-to-landing delay used (``delay_ms``), the
  speed, heading and attitude. Moving the landing instant by Δt moves the antenna by
  v·Δt along the heading (the machine goes straight over a few tens of milliseconds).
- :func:`fit_survey` fits three numbers by robust least squares: the along-track delay
  (fall time + latencies, one correction for all speeds), and the lever arm's distance
  behind the antenna and lateral shift (one for all rows). The model is linear in them, so
  the fit is iteratively reweighted least squares with Huber weights (numpy; scipy is not
  among the project's dependencies), which a few mis-matched or kicked seeds cannot pull.
  The delay and the behind-distance both move seeds along the track; only their different
  dependence on speed (v·Δt against a constant) tells them apart, so a survey whose seeds
  were all sown at one speed is refused (``MIN_SPEED_SPREAD_KMH``).

Plain functions on plain values, like the rest of the model; ``sowgate calibrate positions``
and ``sowgate export --reposition`` (``gateway.app.position_calibration``) wire them to the
store, the CSV and the calibration file.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime

import numpy as np

from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning.geometry import (
    LocalFrame,
    RowOffset,
    antenna_ground_shift,
    rotate_offset,
    row_offset,
    terrain_offset,
    trailed_offset,
)
from gateway.recording.positioning.implement_track import ImplementTrack
from gateway.recording.positioning.methods import KMH_PER_MS, fall_time_s

# Fewer surveyed seeds than this and three parameters are fitted to noise (RTK ~1 cm, bounce).
MIN_SURVEY_SEEDS = 20
# Speeds sown (10th to 90th percentile of the surveyed seeds) must span this much, or the
# delay cannot be told from the behind-distance: both move seeds along the track, only the
# delay's effect grows with speed. At 3 km/h and 1 cm RTK noise, 50 seeds fit the delay to
# ~2 ms.
MIN_SPEED_SPREAD_KMH = 3.0
# With this much speed spread the delay is fitted as a function of speed (a slope in ms per
# km/h about the surveyed median speed): the seed's slide in the furrow grows with the square
# of its speed and a fall-time table of another lot has another slope, which a constant
# delay cannot follow (v·(d0 + d1·v) holds a v² term). Below it only the constant.
MIN_SPREAD_FOR_SLOPE_KMH = 6.0
# ... and only when the survey has a third speed: at least this share of the surveyed seeds
# sown well inside the speed range (more than a quarter of the 10th-90th percentile spread
# from both ends). Two speeds (and the few seeds sown accelerating between them) fit any
# slope: it trades off against the delay and the behind-distance. With a third speed the
# slope is always fitted, not only when it stands out of the noise: every lot slides further
# the faster it is sown (physics, not a hypothesis to test), and dropping the slope that a
# survey of 50 seeds measures to only ±1 ms per km/h (3 standard errors: dropped in 12 of 20
# bench draws) left 16 km/h seeds 10-20 mm off (docs/positioning.md).
MIN_THIRD_SPEED_SHARE = 0.25
# The slope is laid into the fall-time table over this speed range (knots added at its ends
# with the table's end values, so the table's clamping does not cut the line short).
SLOPE_SPEEDS_KMH = (1.0, 30.0)
HUBER_K = 1.5  # Huber threshold in robust standard deviations (MAD-based)
HUBER_FLOOR_M = 0.005  # never treat residuals under 5 mm as outliers
IRLS_ROUNDS = 20
# A fit that moves the lever arm or delay further than this is shown and refused unless the
# fitter accepts it: more likely a survey matched to the wrong seeds than a tape 0.5 m off.
MAX_PLAUSIBLE_SHIFT_M = 0.5
MAX_PLAUSIBLE_DELAY_MS = 150.0


class SurveyError(ValueError):
    """The survey cannot give a fit (too few seeds, one speed, records without raw data)."""


def repositionable(record: SeedDrop) -> bool:
    """Whether the record keeps what re-positioning needs (records stored before these
    fields existed, and paper C's method, do not)."""
    return (
        record.delay_ms is not None
        and record.offset_east_m is not None
        and record.offset_north_m is not None
        and record.heading_deg is not None
        and record.method == "interpolated"
    )


def model_delay_s(speed_kmh: float, settings: PositioningSection) -> float:
    """Host edge stamp to landing, as the positioner computes it for ``settings``."""
    return (
        fall_time_s(speed_kmh, settings.fall_time_table)
        - settings.seed_edge_latency_ms / 1000.0
        + settings.delay_correction_ms / 1000.0
    )


def lean_height_m(settings: PositioningSection) -> float:
    """The height whose lean on a slope separates the antenna from the outlets: the antenna's
    own, less a trailed implement's hitch height (the hitch leans with the tractor, the
    implement rests on the ground behind it), as the positioner's trailed model has it."""
    hitch = settings.hitch
    return settings.antenna_height_m - (hitch.height_m if hitch is not None else 0.0)


# WGS84, for the metres <-> degrees of a shift of a few metres (reposition)
_A = 6378137.0
_E2 = 6.69437999014e-3


def shift_latlon(lat: float, lon: float, east_m: float, north_m: float) -> tuple[float, float]:
    """``(lat, lon)`` moved ``east_m``, ``north_m`` along the local tangent plane.

    With the ellipsoid's radii of curvature at ``lat``; for the few metres a re-positioning
    moves a seed the flat step is off by the Earth's curvature, d²/2R: 2 µm at 5 m, 0.2 mm
    at 50 m. No pymap3d call, so a million records re-position in seconds."""
    phi = math.radians(lat)
    w = math.sqrt(1.0 - _E2 * math.sin(phi) ** 2)
    meridian = _A * (1.0 - _E2) / w**3
    normal = _A / w
    return (lat + math.degrees(north_m / meridian),
            lon + math.degrees(east_m / (normal * math.cos(phi))))


@dataclass(frozen=True)
class _Basis:
    """One record re-positioned with ``settings``, as an (east, north) shift from where it
    is stored, and the shift per unit of each fitted parameter."""

    east: float
    north: float
    d_delay: tuple[float, float]  # per second of delay
    d_behind: tuple[float, float]  # per metre further behind
    d_right: tuple[float, float]  # per metre further right


def _basis(record: SeedDrop, settings: PositioningSection,
           implement_deg: float | None = None) -> _Basis:
    """With a trailed implement and its heading at the record (``ImplementTrack``) the
    outlets follow it, as the positioner put them (``SeedPositioner._trailed``); without,
    a rigid lever arm along the tractor's heading."""
    assert record.delay_ms is not None and record.heading_deg is not None
    assert record.offset_east_m is not None and record.offset_north_m is not None
    ant_e, ant_n = -record.offset_east_m, -record.offset_north_m  # the stored seed at 0, 0
    h = math.radians(record.heading_deg)
    fwd = (math.sin(h), math.cos(h))
    right = (math.cos(h), -math.sin(h))
    v = record.speed_kmh / KMH_PER_MS
    dt = model_delay_s(record.speed_kmh, settings) - record.delay_ms / 1000.0
    ant_e, ant_n = ant_e + v * dt * fwd[0], ant_n + v * dt * fwd[1]
    offset = row_offset(settings, record.row)
    roll = pitch = 0.0
    if record.attitude != "none":
        roll = record.roll_deg or 0.0
        pitch = record.pitch_deg or 0.0
    hitch = settings.hitch
    if hitch is not None and implement_deg is not None:
        forward, sideways = antenna_ground_shift(roll, pitch, lean_height_m(settings))
        se, sn = rotate_offset(RowOffset(-forward, sideways), record.heading_deg)
        cos_r = math.cos(math.radians(roll))
        de, dn = trailed_offset(record.heading_deg, implement_deg, hitch.behind_antenna_m,
                                hitch.outlets_behind_hitch_m, offset.right_m * cos_r)
        hi = math.radians(implement_deg)
        return _Basis(
            ant_e + de + se, ant_n + dn + sn,
            (v * fwd[0], v * fwd[1]),
            (-math.sin(hi), -math.cos(hi)),  # outlets_behind_hitch_m, along the implement
            (cos_r * math.cos(hi), -cos_r * math.sin(hi)),
        )
    lever = terrain_offset(offset, roll, pitch, lean_height_m(settings))
    de, dn = rotate_offset(lever, record.heading_deg)
    cos_p, cos_r = math.cos(math.radians(pitch)), math.cos(math.radians(roll))
    return _Basis(
        ant_e + de, ant_n + dn,
        (v * fwd[0], v * fwd[1]),
        (-cos_p * fwd[0], -cos_p * fwd[1]),
        (cos_r * right[0], cos_r * right[1]),
    )


def reposition(record: SeedDrop, settings: PositioningSection,
               implement_heading_deg: float | None = None) -> tuple[float, float]:
    """Where ``record``'s seed landed by the model ``settings`` describes: (lat, lon).

    With a trailed implement, give its heading at the record (``ImplementTrack.heading``,
    fed every record in stored order), or the outlets are put on a rigid lever arm along
    the tractor's heading. Raises ``SurveyError`` for a record that does not keep the raw
    data (:func:`repositionable`).
    """
    if not repositionable(record):
        raise SurveyError("record lacks the raw data re-positioning needs")
    b = _basis(record, settings, implement_heading_deg)
    return shift_latlon(record.lat, record.lon, b.east, b.north)


@dataclass(frozen=True)
class ErrorStats:
    """Horizontal errors of a set of seeds, as paper C reports them."""

    n: int
    mean_m: float
    sd_m: float
    cv_pct: float
    max_m: float

    @classmethod
    def of(cls, errors: Sequence[float]) -> ErrorStats:
        if not errors:
            return cls(0, math.nan, math.nan, math.nan, math.nan)
        mean = statistics.fmean(errors)
        sd = statistics.stdev(errors) if len(errors) > 1 else 0.0
        return cls(len(errors), mean, sd, 100.0 * sd / mean if mean > 0 else math.nan,
                   max(errors))

    def line(self) -> str:
        return (f"mean {self.mean_m * 1000:.1f} mm, SD {self.sd_m * 1000:.1f} mm, "
                f"CV {self.cv_pct:.1f} %, max {self.max_m * 1000:.1f} mm (n = {self.n})")


@dataclass(frozen=True)
class SurveyFit:
    """The fitted corrections, relative to the settings fitted against, and the result."""

    delay_ms: float  # added to delay_correction_ms (0 when held fixed)
    behind_m: float  # added to outlet_behind_antenna_m
    right_m: float  # added to every row_lateral_m
    delay_fitted: bool
    before: ErrorStats
    after: ErrorStats
    residuals_before_m: tuple[float, ...]
    residuals_after_m: tuple[float, ...]
    speed_spread_kmh: float
    outliers: int  # seeds the robust weights took down to under half weight
    # what the survey cannot tell apart, and what to survey next (survey_coverage)
    coverage_warnings: tuple[str, ...] = ()
    # the delay's change per km/h about speed_ref_kmh (0: a constant delay was fitted)
    delay_ms_per_kmh: float = 0.0
    speed_ref_kmh: float = 0.0

    def settings(self, base: PositioningSection) -> PositioningSection:
        """``base`` with the fit applied (what the calibration file makes of the config)."""
        return apply_fit(base, self.delay_ms, self.behind_m, self.right_m,
                         self.delay_ms_per_kmh, self.speed_ref_kmh)

    def problems(self) -> list[str]:
        """Why this fit looks wrong (empty when it does not)."""
        out = []
        if abs(self.behind_m) > MAX_PLAUSIBLE_SHIFT_M or abs(self.right_m) > MAX_PLAUSIBLE_SHIFT_M:
            out.append(
                f"the lever arm moves {self.behind_m:+.3f} m behind / {self.right_m:+.3f} m "
                f"right, more than {MAX_PLAUSIBLE_SHIFT_M} m: are the surveyed seeds matched "
                "to the right records?"
            )
        if abs(self.delay_ms) > MAX_PLAUSIBLE_DELAY_MS:
            out.append(f"the delay moves {self.delay_ms:+.1f} ms, more than "
                       f"{MAX_PLAUSIBLE_DELAY_MS:g} ms")
        if not self.after.mean_m < self.before.mean_m:
            out.append("the fit does not reduce the mean error")
        return out


def sloped_table(table: Sequence[tuple[float, float]], ms_per_kmh: float, ref_kmh: float
                 ) -> list[tuple[float, float]]:
    """The fall-time table with ``ms_per_kmh`` · (v − ``ref_kmh``) added, extended to
    ``SLOPE_SPEEDS_KMH`` first with its end values (the same function before the slope)."""
    lo, hi = SLOPE_SPEEDS_KMH
    knots = [(float(v), float(t)) for v, t in table]
    if knots[0][0] > lo:
        knots.insert(0, (lo, knots[0][1]))
    if knots[-1][0] < hi:
        knots.append((hi, knots[-1][1]))
    return [(v, t + ms_per_kmh * (v - ref_kmh)) for v, t in knots]


def apply_fit(
    base: PositioningSection, delay_ms: float, behind_m: float, right_m: float,
    delay_ms_per_kmh: float = 0.0, speed_ref_kmh: float = 0.0,
) -> PositioningSection:
    """``base`` with a fit's corrections; with a trailed implement the outlets move along
    its drawbar (``hitch.outlets_behind_hitch_m``), the hitch staying where it was measured.
    A delay slope goes into the fall-time table (``sloped_table``)."""
    lateral = [r + right_m for r in base.lateral_offsets()]
    update: dict[str, object] = {
        "delay_correction_ms": base.delay_correction_ms + delay_ms,
        "row_lateral_m": lateral,
    }
    if delay_ms_per_kmh:
        update["fall_time_table"] = sloped_table(base.fall_time_table, delay_ms_per_kmh,
                                                 speed_ref_kmh)
    if base.hitch is None:
        update["outlet_behind_antenna_m"] = base.outlet_behind_antenna_m + behind_m
    else:
        update["hitch"] = base.hitch.model_copy(
            update={"outlets_behind_hitch_m": base.hitch.outlets_behind_hitch_m + behind_m}
        )
    return base.model_copy(update=update)


def _irls(a: np.ndarray, y: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Robust least squares, Huber weights per seed (both its coordinates)."""
    weights = np.ones(n)
    params = np.zeros(a.shape[1])
    for _ in range(IRLS_ROUNDS):
        w2 = np.repeat(np.sqrt(weights), 2)
        params_new, *_ = np.linalg.lstsq(a * w2[:, None], y * w2, rcond=None)
        res = np.hypot(*(y - a @ params_new).reshape(n, 2).T)
        sigma = max(1.4826 * float(np.median(res)), HUBER_FLOOR_M)
        k = HUBER_K * sigma
        weights = np.where(res <= k, 1.0, k / np.maximum(res, 1e-12))
        done = bool(np.allclose(params_new, params, rtol=0, atol=1e-7))
        params = params_new
        if done:
            break
    return params, weights


def third_speed_share(speeds: Sequence[float]) -> float:
    """The share of ``speeds`` more than a quarter of their 10th-90th percentile spread from
    both ends: seeds of a third speed, which tell a delay slope from the constant delay and
    the behind-distance (``MIN_THIRD_SPEED_SHARE``)."""
    if len(speeds) < 3:
        return 0.0
    v = np.asarray(speeds, dtype=np.float64)
    lo, hi = np.percentile(v, [10.0, 90.0])
    margin = 0.25 * float(hi - lo)
    return float(np.mean((v > lo + margin) & (v < hi - margin)))


def speed_spread_kmh(speeds: Sequence[float]) -> float:
    """10th to 90th percentile of the speeds (one fast seed does not make a spread)."""
    if len(speeds) < 2:
        return 0.0
    lo, hi = np.percentile(np.asarray(speeds, dtype=np.float64), [10.0, 90.0])
    return float(hi - lo)


def fit_survey(
    records: Sequence[SeedDrop],
    surveyed: Sequence[tuple[float, float]],
    settings: PositioningSection,
    *,
    fit_delay: bool = True,
    sown: Sown | None = None,
) -> SurveyFit:
    """Fit delay and lever arm so ``records`` re-positioned land on ``surveyed`` (lat, lon).

    ``fit_delay=False`` keeps the delay and fits the lever arm alone (a survey sown at one
    speed). Raises ``SurveyError`` naming the minimum when the survey cannot tell (too few
    seeds, one speed); a survey that tells the parameters apart only poorly
    (``survey_coverage``, given the ``sown`` records) gets warnings saying what to survey
    next in ``coverage_warnings``.
    """
    if len(records) != len(surveyed):
        raise ValueError(f"{len(records)} records for {len(surveyed)} surveyed seeds")
    unusable = sum(not repositionable(r) for r in records)
    if unusable:
        raise SurveyError(
            f"{unusable} of the matched records lack the raw data re-positioning needs "
            "(stored before this version, or positioned with method = 'paper')"
        )
    n = len(records)
    if n < MIN_SURVEY_SEEDS:
        raise SurveyError(
            f"{n} surveyed seeds matched; the fit needs at least {MIN_SURVEY_SEEDS} "
            "(50 or more recommended)"
        )
    spread = speed_spread_kmh([r.speed_kmh for r in records])
    if fit_delay and spread < MIN_SPEED_SPREAD_KMH:
        raise SurveyError(
            f"the surveyed seeds were sown at {spread:.1f} km/h of speed spread (10th-90th "
            f"percentile); telling the delay from the lever arm needs at least "
            f"{MIN_SPEED_SPREAD_KMH:g} km/h: survey seeds from two speeds, or fit the lever "
            "arm alone (--lever-only)"
        )
    frame = LocalFrame(records[0].lat, records[0].lon)
    bases = [_basis(r, settings, None if sown is None else sown.implement_of(r))
             for r in records]
    target = np.array([frame.to_enu(lat, lon)[:2] for lat, lon in surveyed], dtype=np.float64)
    stored = np.array([frame.to_enu(r.lat, r.lon)[:2] for r in records], dtype=np.float64)
    base = stored + np.array([(b.east, b.north) for b in bases], dtype=np.float64)
    slope = (fit_delay and spread >= MIN_SPREAD_FOR_SLOPE_KMH
             and third_speed_share([r.speed_kmh for r in records]) >= MIN_THIRD_SPEED_SHARE)
    lo, hi = SLOPE_SPEEDS_KMH
    ref = float(np.median([r.speed_kmh for r in records]))
    cols = [[b.d_delay for b in bases]] if fit_delay else []
    if slope:  # delay per km/h about ref: the delay column times (v - ref)
        cols.append([(b.d_delay[0] * (min(max(r.speed_kmh, lo), hi) - ref),
                      b.d_delay[1] * (min(max(r.speed_kmh, lo), hi) - ref))
                     for b, r in zip(bases, records, strict=True)])
    cols += [[b.d_behind for b in bases], [b.d_right for b in bases]]
    design = np.stack([np.asarray(c, dtype=np.float64) for c in cols], axis=-1)  # n x 2 x p
    y = (target - base).reshape(-1)
    a = design.reshape(2 * n, -1)
    params, weights = _irls(a, y, n)
    before = np.hypot(*(y.reshape(n, 2).T))
    after = np.hypot(*(y - a @ params).reshape(n, 2).T)
    delay_s = float(params[0]) if fit_delay else 0.0
    behind, right = float(params[-2]), float(params[-1])
    return SurveyFit(
        delay_ms=delay_s * 1000.0,
        behind_m=behind,
        right_m=right,
        delay_fitted=fit_delay,
        before=ErrorStats.of(before.tolist()),
        after=ErrorStats.of(after.tolist()),
        residuals_before_m=tuple(before.tolist()),
        residuals_after_m=tuple(after.tolist()),
        speed_spread_kmh=spread,
        outliers=int(np.sum(weights < 0.5)),
        coverage_warnings=tuple(survey_coverage(records, sown)),
        delay_ms_per_kmh=float(params[1]) * 1000.0 if slope else 0.0,
        speed_ref_kmh=ref if slope else 0.0,
    )


# -- can the survey tell the parameters apart? ----------------------------------------------

# Surveyed seeds whose headings' resultant (mean unit vector) is longer than this were all sown
# driving one way (±25°): a lateral lever-arm error then looks exactly like a cross slope's
# lean or an RTK offset, and the fit would double it on the passes driven the other way.
ONE_WAY_RESULTANT = 0.9
# The sown speeds (5th-95th percentile) reaching this far beyond the surveyed ones: the delay
# (which grows with speed) is extrapolated there.
SPEED_COVERAGE_MARGIN_KMH = 2.0
# The surveyed seeds spanning less than this share of the field across the passes.
MIN_ACROSS_SHARE = 0.5


@dataclass
class Sown:
    """What the coverage checks need of every stored record (one pass over the store), and
    with a trailed implement its heading at the records the fit uses (``ImplementTrack``,
    followed over every record; ``keep`` remembers it for one), which the fit's lever arm
    follows."""

    speed_kmh: list[float]
    heading_deg: list[float]
    lat: list[float]
    lon: list[float]
    track: ImplementTrack | None = None
    implement: dict[tuple[datetime, int], float] = field(default_factory=dict)
    _last: float | None = None

    @classmethod
    def empty(cls, settings: PositioningSection | None = None) -> Sown:
        """``settings``: the positioning the records are fitted against (its hitch)."""
        track = None if settings is None or settings.hitch is None else ImplementTrack(
            settings, made_with=settings)  # the records were made with them
        return cls([], [], [], [], track)

    def keep(self, record: SeedDrop) -> None:
        """Remember the implement's heading at ``record``, the record last added (a surveyed
        one: only those are kept, a day's store holds a million records)."""
        if self._last is not None:
            self.implement[(record.utc, record.row)] = self._last

    def implement_of(self, record: SeedDrop) -> float | None:
        """The implement's heading at ``record`` (kept before), None without a hitch."""
        return self.implement.get((record.utc, record.row))

    def add(self, record: SeedDrop) -> None:
        self._last = None if self.track is None else self.track.heading(record)
        if record.heading_deg is None:
            return
        self.speed_kmh.append(record.speed_kmh)
        self.heading_deg.append(record.heading_deg)
        self.lat.append(record.lat)
        self.lon.append(record.lon)


def _resultant(headings_deg: Sequence[float], doubled: bool = False) -> tuple[float, float]:
    """(resultant length, mean direction in degrees) of headings (doubled: of axes)."""
    a = np.radians(np.asarray(headings_deg, dtype=np.float64)) * (2.0 if doubled else 1.0)
    s, c = float(np.mean(np.sin(a))), float(np.mean(np.cos(a)))
    mean = math.degrees(math.atan2(s, c)) / (2.0 if doubled else 1.0)
    return math.hypot(s, c), mean % 360.0


def survey_coverage(surveyed: Sequence[SeedDrop], sown: Sown | None = None) -> list[str]:
    """Why the surveyed seeds tell the fitted parameters apart only poorly, each warning
    saying what to survey next: every surveyed seed sown driving one way (the lateral shift
    is then a slope's lean or an RTK offset as much as a lever arm); and, given what was
    ``sown``, sown speeds well beyond the surveyed ones (the delay is extrapolated there) and
    surveyed seeds on one side of the field (RTK error and slope differ across it). Too few
    seeds or one speed are refused by ``fit_survey`` itself."""
    warnings: list[str] = []
    headings = [r.heading_deg for r in surveyed if r.heading_deg is not None]
    if len(headings) >= 2:
        length, mean = _resultant(headings)
        if length > ONE_WAY_RESULTANT:
            warnings.append(
                f"all surveyed seeds were sown driving one way (heading {mean:.0f}°): a "
                "lateral error of the lever arm cannot be told from a slope's lean or an RTK "
                f"offset; survey seeds from a pass driven the other way (heading "
                f"{(mean + 180.0) % 360.0:.0f}°) too"
            )
    if sown is None or len(sown.speed_kmh) < 2 or not surveyed:
        return warnings
    speeds = [r.speed_kmh for r in surveyed]
    lo, hi = min(speeds), max(speeds)
    s_lo, s_hi = (float(x) for x in np.percentile(np.asarray(sown.speed_kmh), [5.0, 95.0]))
    missing = [v for v in (s_lo, s_hi) if v < lo - SPEED_COVERAGE_MARGIN_KMH
               or v > hi + SPEED_COVERAGE_MARGIN_KMH]
    if missing:
        warnings.append(
            f"the seeds were sown at {s_lo:.0f}–{s_hi:.0f} km/h, the surveyed ones at "
            f"{lo:.0f}–{hi:.0f} km/h: the delay is extrapolated to "
            f"{' and '.join(f'{v:.0f}' for v in missing)} km/h; survey seeds sown at "
            f"{' and '.join(f'{v:.0f}' for v in missing)} km/h too"
        )
    _len, axis = _resultant(sown.heading_deg, doubled=True)
    frame = LocalFrame(sown.lat[0], sown.lon[0])
    across_dir = math.radians(axis + 90.0)
    ux, uy = math.sin(across_dir), math.cos(across_dir)

    def across(lat: float, lon: float) -> float:
        e, n, _u = frame.to_enu(lat, lon)
        return e * ux + n * uy

    step = max(1, len(sown.lat) // 20_000)  # a sample is enough for the field's extent
    field = np.asarray([across(a, b) for a, b in zip(sown.lat[::step], sown.lon[::step],
                                                      strict=True)])
    f_lo, f_hi = (float(x) for x in np.percentile(field, [2.0, 98.0]))
    ours = [across(r.lat, r.lon) for r in surveyed]
    width = f_hi - f_lo
    if width > 0 and (max(ours) - min(ours)) < MIN_ACROSS_SHARE * width:
        centre = (min(ours) + max(ours)) / 2.0
        far = f_hi if abs(centre - f_lo) < abs(centre - f_hi) else f_lo
        warnings.append(
            f"the surveyed seeds span {max(ours) - min(ours):.0f} m of the field's "
            f"{width:.0f} m across the passes (one side): RTK error and slope differ across a "
            f"field; survey seeds from the passes about {abs(far - centre):.0f} m across from "
            "these too"
        )
    return warnings
