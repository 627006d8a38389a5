"""The two prediction methods' models: paper C's fixed lag, and the antenna between epochs.

Owns the arithmetic each method applies to GNSS epochs, without any queueing or state:

- paper C exactly (:func:`paper_lag_m`, :func:`paper_landing`, :data:`PAPER_MM_PER_DEG`);
- the seed's fall time from the sensor to the furrow (:func:`fall_time_s`);
- one epoch in the local frame with its heading chosen (:class:`AntennaSample`,
  :func:`choose_heading`), and the antenna at any instant, interpolated between two epochs
  or dead-reckoned past the last (:class:`AntennaState`, :func:`interpolate_state`,
  :func:`extrapolate_state`, with the worst fix/heading source of the two).

Separate from :mod:`.positioner` because these are the model, stated once in plain
per-seed form; the positioner decides *when* to apply them (pending queue, timeouts) and
inlines the same operations in its fast paths, which tests check against these functions.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass

from gateway.config.recording import PositioningSection
from gateway.core.records import FixQuality, HeadingSource
from gateway.recording.positioning.geometry import (
    RowOffset,
    heading_diff,
    interpolate_heading,
    rotate_offset,
    wrap_deg,
)

# Paper C's metres↔degrees constant: 1° of latitude taken as 1.112e8 mm everywhere.
PAPER_MM_PER_DEG = 1.112e8
KMH_PER_MS = 3.6
# Below this speed the course over ground is noise, so it cannot stand in for the heading.
MIN_COURSE_SPEED_KMH = 1.0
FIX_RANK: dict[FixQuality, int] = {
    "none": 0, "single": 1, "dgps": 2, "rtk_float": 3, "rtk_fixed": 4,
}
HEADING_RANK: dict[HeadingSource, int] = {"none": 0, "course": 1, "dual_antenna": 2}


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
    # the machine's attitude at this epoch (positioning.attitude_source), None = not measured
    roll_deg: float | None = None
    pitch_deg: float | None = None
    # a trailed implement's heading ([positioning.hitch]), None without one
    implement_heading_deg: float | None = None


def lerp_optional(a: float | None, b: float | None, f: float) -> float | None:
    """Linear between two optional values; the one present when the other is missing."""
    if a is None:
        return b
    if b is None:
        return a
    return a + f * (b - a)


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
    roll_deg: float | None = None
    pitch_deg: float | None = None
    implement_heading_deg: float | None = None


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
        roll_deg=lerp_optional(s0.roll_deg, s1.roll_deg, a),
        pitch_deg=lerp_optional(s0.pitch_deg, s1.pitch_deg, a),
        implement_heading_deg=(
            interpolate_heading(s0.implement_heading_deg, s1.implement_heading_deg, a)
            if s0.implement_heading_deg is not None and s1.implement_heading_deg is not None
            else s1.implement_heading_deg if s0.implement_heading_deg is None
            else s0.implement_heading_deg
        ),
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
        roll_deg=last.roll_deg,
        pitch_deg=last.pitch_deg,
        implement_heading_deg=last.implement_heading_deg,
    )
    return state, capped
