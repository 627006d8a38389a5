"""The radar's scale, learnt continuously against an RTK-fixed GNSS speed (issue 25 §3).

A radar's speed calibration (``sowgate calibrate speed``, paper A's 50 m against a tape) holds
for the surface it was driven on: stubble, a seedbed, wet soil and a mounting knocked by a
clod each change the Doppler return's scale by a few percent, and that passes 1:1 into the
rate (+4 % surface change: 3.9 % rate error). An RTK-fixed receiver's Doppler speed is good
to a few cm/s and does not care about the surface, but it is a poor speed to sow on directly
where the fix drops (float, dropouts under trees) and it sees the antenna, not the ground.
So the radar stays the speed source and its scale is learnt from the GNSS wherever the two
can be compared fairly:

* the GNSS fix is RTK fixed (a float or DGPS speed can be off by more than the effect);
* the machine drives straight (course change within ``max_turn_deg_s``: in a turn the
  antenna and the radar travel arcs of different radius) at a steady speed (the GNSS speed
  within ±``steady_span`` over ``STEADY_S``: the two sources lag differently in a ramp);
* above ``min_speed_kmh`` (a radar's relative noise grows at walking pace).

Each accepted radar reading gives the ratio GNSS speed / raw radar speed; the scale is the
median of the ratios of the last ``window_s`` of such driving (robust to a radar glitch or a
GNSS outlier, and a window so a changing surface is followed). It is used (the radar's
correction replaced) once ``MIN_SAMPLES`` ratios exist, and ``radar.scale_drift`` is raised
while it is more than ``alarm_pct`` from the calibrated factor. Plain arithmetic on plain
values: the controller feeds it; nothing here reads a clock or a device.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass

STEADY_S = 3.0  # the GNSS speed is steady over this long
PAIR_MAX_AGE_S = 0.5  # a radar reading is compared with a GNSS speed at most this old
MIN_SAMPLES = 90  # ratios before the learnt scale is used (30 s of straight driving at 3 Hz)
MAX_SAMPLES = 4000  # bound on memory whatever the window


@dataclass(frozen=True)
class RadarScaleSettings:
    window_s: float = 180.0
    alarm_pct: float = 2.0
    min_speed_kmh: float = 2.0
    max_turn_deg_s: float = 2.0
    steady_span: float = 0.05


def _course_change(a: float, b: float) -> float:
    """The smallest angle between two courses, degrees."""
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


class RadarScaleLearner:
    """Feed ``on_gnss`` each epoch and ``on_radar`` each raw radar reading; ``scale``."""

    def __init__(self, settings: RadarScaleSettings, calibrated: float = 1.0) -> None:
        self.settings = settings
        self.calibrated = calibrated
        self._gnss: deque[tuple[float, float, float | None]] = deque()  # (t, kmh, course)
        self._gnss_ok_t: float | None = None  # newest epoch that was RTK fixed and straight
        self._ratios: deque[tuple[float, float]] = deque(maxlen=MAX_SAMPLES)
        self.accepted = 0
        self.rejected = 0

    def on_gnss(self, t: float, fix: str, speed_kmh: float | None,
                course_deg: float | None) -> None:
        if fix != "rtk_fixed" or speed_kmh is None or not math.isfinite(speed_kmh):
            self._gnss.clear()
            self._gnss_ok_t = None
            return
        self._gnss.append((t, speed_kmh, course_deg))
        while self._gnss and t - self._gnss[0][0] > STEADY_S:
            self._gnss.popleft()
        self._gnss_ok_t = t if self._straight_and_steady() else None

    def _straight_and_steady(self) -> bool:
        s = self.settings
        first_t, _, first_course = self._gnss[0]
        last_t, last_v, last_course = self._gnss[-1]
        if last_t - first_t < STEADY_S * 0.8 or last_v < s.min_speed_kmh:
            return False
        speeds = [v for _, v, _ in self._gnss]
        if max(speeds) - min(speeds) > 2.0 * s.steady_span * last_v:
            return False
        if first_course is None or last_course is None:
            return False
        turn = _course_change(first_course, last_course) / max(last_t - first_t, 1e-9)
        return turn <= s.max_turn_deg_s

    def on_radar(self, t: float, raw_kmh: float) -> None:
        """One raw (uncorrected) radar reading: compared with the GNSS when fair to."""
        ok_t = self._gnss_ok_t
        if (ok_t is None or not 0.0 <= t - ok_t <= PAIR_MAX_AGE_S or raw_kmh <= 0.0
                or not math.isfinite(raw_kmh)):
            self.rejected += 1
            return
        self._ratios.append((t, self._gnss[-1][1] / raw_kmh))
        self.accepted += 1
        while self._ratios and t - self._ratios[0][0] > self.settings.window_s:
            self._ratios.popleft()

    @property
    def scale(self) -> float | None:
        """The learnt factor (GNSS / raw radar), None until ``MIN_SAMPLES`` ratios."""
        if len(self._ratios) < MIN_SAMPLES:
            return None
        return statistics.median(r for _, r in self._ratios)

    def drift_pct(self) -> float | None:
        """How far the learnt scale is from the calibrated factor, %."""
        k = self.scale
        return None if k is None else (k / self.calibrated - 1.0) * 100.0

    def drifted(self) -> bool:
        d = self.drift_pct()
        return d is not None and abs(d) > self.settings.alarm_pct
