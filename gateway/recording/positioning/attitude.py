"""The machine's attitude at each GNSS epoch: roll and pitch from the configured source, the
pitch from the antenna's climb along its track, and a trailed implement's heading.

Owns :class:`EpochAttitude`, the state these need between epochs (the last inclinometer
reading, the recent track, where the implement's axle was pulled to). Separate from the
positioner because it is one self-contained question per epoch ("how is the machine
leaning, where does the implement point?") with its own state; the positioner stores the
answers with each epoch and interpolates them per seed. Conventions: see
:mod:`.geometry` (positive roll = right side down, positive pitch = nose up).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Protocol

import numpy as np
import numpy.typing as npt

from gateway.config.recording import HitchSection, PositioningSection
from gateway.core.records import AttitudeSource, FixQuality
from gateway.recording.positioning.geometry import (
    FloatArray,
    baseline_attitude,
    follow_hitch,
    hitch_point,
    implement_heading,
)
from gateway.recording.positioning.methods import AntennaSample, lerp_optional

# An inclinometer roll older than this (s) at an epoch is not used (the bus polls at ~3 Hz).
ATTITUDE_STALE_S = 1.0
# A trailed implement's axle is pulled after its hitch in steps of at most this (m): the
# discrete tractrix is then within ~0.01 % of the continuous one on any field curve.
HITCH_STEP_M = 0.02
# The hitch point jumping further than this between epochs (a fix jump, an outage) restarts
# the implement straight behind the tractor instead of dragging it across.
HITCH_RESET_M = 5.0
# Pitch from the track (positioning.pitch_from_track_m): a jump between epochs longer than
# this restarts the climb's window (a dropout, a time step), as does a fix that is not RTK
# fixed (a float solution's height wanders by decimetres).
TRACK_RESET_M = 5.0


IntArray = npt.NDArray[np.intp] | npt.NDArray[np.int64]


class _Epoch(Protocol):
    """What is read from an epoch (``positioner.AntennaEpoch``)."""

    @property
    def t_mono(self) -> float: ...
    @property
    def alt_m(self) -> float | None: ...
    @property
    def fix(self) -> FixQuality: ...
    @property
    def heading_valid(self) -> bool: ...


class EpochAttitude:
    """Per epoch: (roll, pitch) from ``positioning.attitude_source``, the pitch from the
    track (``positioning.pitch_from_track_m``) and the trailed implement's heading."""

    def __init__(self, settings: PositioningSection, baseline_offset_deg: float = 0.0) -> None:
        self.attitude_source: AttitudeSource = settings.attitude_source
        self._attitude_sign = -1.0 if settings.attitude_invert else 1.0
        # gnss.heading_offset_deg: where the dual-antenna baseline points (baseline_attitude)
        self.baseline_offset_deg = baseline_offset_deg
        self._incl_roll: tuple[float, float] | None = None  # (t_mono, roll) from add_roll
        # pitch from the antenna's climb: (distance along the track, up) of recent epochs
        self.pitch_track_m = settings.pitch_from_track_m
        self._track: deque[tuple[float, float]] = deque()
        self._track_at: tuple[float, float] | None = None  # (east, north) of the newest
        self._track_dist = 0.0
        # a trailed implement: its axle line's position, and the hitch point it was pulled to
        self.hitch: HitchSection | None = settings.hitch
        self._axle: tuple[float, float] | None = None
        self._hitch_at: tuple[float, float] | None = None

    def set_hitch(self, hitch: HitchSection | None) -> None:
        """A new calibration: a changed hitch restarts the implement straight behind it."""
        if hitch != self.hitch:
            self._axle = self._hitch_at = None
        self.hitch = hitch

    def add_roll(self, t_mono: float, roll_deg: float) -> None:
        """An inclinometer roll reading (degrees, as the sensor reads it) taken at ``t_mono``;
        used by the epochs that follow while fresh (positioning.attitude_source =
        "inclinometer")."""
        if math.isfinite(roll_deg):
            self._incl_roll = (t_mono, roll_deg)

    def roll_pitch(self, epoch: _Epoch) -> tuple[float | None, float | None]:
        """(roll, pitch) of the machine at this epoch from the configured source, signs per
        the convention (right side down, nose up positive), or None where not measured."""
        source = self.attitude_source
        sign = self._attitude_sign
        if source == "dual_antenna":
            baseline = getattr(epoch, "baseline_pitch_deg", None)
            if baseline is None or not epoch.heading_valid or not math.isfinite(baseline):
                return None, None
            roll, pitch = baseline_attitude(baseline, self.baseline_offset_deg)
        elif source == "inclinometer":
            incl = self._incl_roll
            if incl is None or abs(epoch.t_mono - incl[0]) > ATTITUDE_STALE_S:
                return None, None
            roll, pitch = incl[1], None
        else:
            return None, None
        roll = None if roll is None else max(-90.0, min(90.0, sign * roll))
        pitch = None if pitch is None else max(-90.0, min(90.0, sign * pitch))
        return roll, pitch

    def track_pitch(self, east: float, north: float, up: float, epoch: _Epoch) -> float | None:
        """The machine's pitch from the antenna's climb over the last ``pitch_from_track_m``
        of its track (degrees, nose up positive), or None (off, too little track yet, or
        not RTK fixed).

        Side-by-side antennas measure only roll, and the inclinometer's pitch axis tells
        raised from lowered; yet 0.5° of slope along the pass leans a 2.5 m antenna 22 mm
        back (climbing) or forward. The ground's slope under the track is the climb of the
        antenna per metre driven: the height difference across the window, so the RTK
        height's slow wander cancels and only its change over a few seconds remains. It is
        the slope of the last few metres, lagging the antenna by half the window."""
        if self.pitch_track_m <= 0.0 or epoch.alt_m is None or epoch.fix != "rtk_fixed":
            self._track.clear()
            self._track_at = None
            return None
        last = self._track_at
        step = 0.0 if last is None else math.hypot(east - last[0], north - last[1])
        if last is None or step > TRACK_RESET_M:
            self._track.clear()
            self._track_dist = 0.0
        else:
            self._track_dist += step
        self._track_at = (east, north)
        track, dist = self._track, self._track_dist
        track.append((dist, up))
        while len(track) >= 2 and dist - track[1][0] >= self.pitch_track_m:
            track.popleft()
        run = dist - track[0][0]
        if run < self.pitch_track_m:
            return None
        return math.degrees(math.atan2(up - track[0][1], run))

    def restarts_hitch(self, east: float, north: float, heading: float) -> bool:
        """Whether ``follow_hitch`` would restart the implement at this point."""
        if self.hitch is None or self._hitch_at is None or self._axle is None:
            return True
        at = hitch_point(east, north, heading, self.hitch.behind_antenna_m)
        return math.dist(self._hitch_at, at) > HITCH_RESET_M

    def follow_hitch(self, east: float, north: float, heading: float | None,
                     start: float | None = None) -> float | None:
        """Pull the trailed implement after the hitch to this epoch; its heading (None
        without a hitch or a tractor heading). ``start``: where the implement points if it
        restarts here (``ImplementTrack``: as a record says the positioner had it), else
        straight behind the tractor."""
        hitch = self.hitch
        if hitch is None or heading is None:
            return None
        at = hitch_point(east, north, heading, hitch.behind_antenna_m)
        # the wheels steer the implement: its heading follows the hitch over their distance
        length = hitch.wheels_behind_hitch_m or hitch.outlets_behind_hitch_m
        last, axle = self._hitch_at, self._axle
        if last is None or axle is None or math.dist(last, at) > HITCH_RESET_M:
            axle = hitch_point(at[0], at[1], heading if start is None else start, length)
        else:
            steps = max(1, math.ceil(math.dist(last, at) / HITCH_STEP_M))
            for k in range(1, steps + 1):
                f = k / steps
                axle = follow_hitch(
                    axle, (last[0] + f * (at[0] - last[0]), last[1] + f * (at[1] - last[1])),
                    length,
                )
        self._axle, self._hitch_at = axle, at
        return implement_heading(axle, at)


def nan_of(x: float | None) -> float:
    return math.nan if x is None else x


def lerp_nan(values: FloatArray, i0: IntArray, i1: IntArray, a: FloatArray) -> FloatArray:
    """``lerp_optional`` over arrays: NaN = not measured; one side NaN → the other."""
    v0, v1 = values[i0], values[i1]
    v0f = np.where(np.isnan(v0), v1, v0)
    v1f = np.where(np.isnan(v1), v0, v1)
    out: FloatArray = v0f + a * (v1f - v0f)
    return out


def attitude_pair(
    s0: AntennaSample, s1: AntennaSample
) -> tuple[float | None, float, float | None, float]:
    """(roll, d_roll, pitch, d_pitch) between two epochs: linear where both measured, the
    one measured held where only one did (methods.lerp_optional)."""
    r0, r1, p0, p1 = s0.roll_deg, s1.roll_deg, s0.pitch_deg, s1.pitch_deg
    roll: float | None
    pitch: float | None
    if r0 is not None and r1 is not None:
        roll, d_roll = r0, r1 - r0
    else:
        roll, d_roll = lerp_optional(r0, r1, 0.0), 0.0
    if p0 is not None and p1 is not None:
        pitch, d_pitch = p0, p1 - p0
    else:
        pitch, d_pitch = lerp_optional(p0, p1, 0.0), 0.0
    return roll, d_roll, pitch, d_pitch
