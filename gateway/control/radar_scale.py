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

Each accepted radar reading gives the ratio raw radar speed / GNSS speed (the radar's
reading per true km/h: its 3 % scatter is additive there, so a mean of it is unbiased); the
scale is the inverse of the trimmed mean of the ratios of the last ``window_s`` of such
driving (a radar glitch or a GNSS outlier left out; 1.3 times less scatter than a median).
A surface that changes mid-pass is not left to slide through that window (a median of 3 min
followed a +4 % step only after ~1.5 min, the rate 4 % off meanwhile): when the last
``RECENT_N`` ratios differ from the ones before by more than ``CHANGE_Z`` standard errors,
the window restarts from the newest ``KEEP_AFTER_CHANGE`` (a +4 % step is followed in ~8 s,
+2 % in ~17 s); a slow drift below that test is followed by the window. The window is of
driving, not of the clock: a stop longer than it keeps what was learnt. The scale is used
(the radar's correction replaced) once ``MIN_SAMPLES`` ratios exist, and
``radar.scale_drift`` is raised while it is more than ``alarm_pct`` from the calibrated
factor. Plain arithmetic on plain
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
TRIM = 0.1  # the estimate: the mean of the ratios with the 10 % lowest and highest left out
RECENT_N = 60  # a change is tested on the last 20 s of ratios (at 3 Hz) against the rest
MIN_OLDER = 30  # ... once there are at least this many before them
CHANGE_Z = 4.0  # ... and found when the two differ by more than this many standard errors
KEEP_AFTER_CHANGE = 12  # the newest ratios the window restarts from after a change


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
        self._scale: float | None = None  # the estimate over the window, once learnt
        self._since_change = 0  # ratios since the last detected change (or the start)
        self.accepted = 0
        self.rejected = 0
        self.changes = 0  # scale changes detected (the window restarted)

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
                or not math.isfinite(raw_kmh) or self._gnss[-1][1] <= 0.0):
            self.rejected += 1
            return
        self._ratios.append((t, raw_kmh / self._gnss[-1][1]))
        self.accepted += 1
        self._since_change += 1
        # the window is of driving, not of the clock: after a stop the ratios before it stay
        # until enough new ones replace them (a surface changed meanwhile is found as below)
        while len(self._ratios) > MIN_SAMPLES and t - self._ratios[0][0] > self.settings.window_s:
            self._ratios.popleft()
        ratios = [r for _, r in self._ratios]
        if self._changed(ratios):
            del ratios[:-KEEP_AFTER_CHANGE]
            while len(self._ratios) > KEEP_AFTER_CHANGE:
                self._ratios.popleft()
            self._since_change = len(ratios)
            self.changes += 1
        if len(ratios) >= (KEEP_AFTER_CHANGE if self._scale is not None else MIN_SAMPLES):
            self._scale = 1.0 / _trimmed_mean(ratios)

    def _changed(self, ratios: list[float]) -> bool:
        """The last ``RECENT_N`` ratios tell a scale other than the ones before them: the
        surface (or the mounting) changed, and what was learnt before no longer holds."""
        if len(ratios) < RECENT_N + MIN_OLDER or self._since_change < RECENT_N:
            return False
        older, recent = ratios[:-RECENT_N], ratios[-RECENT_N:]
        spread = _robust_sd(older)
        if spread <= 0.0:
            return False
        se = spread * math.sqrt(1.0 / len(older) + 1.0 / len(recent))
        return abs(_trimmed_mean(recent) - _trimmed_mean(older)) > CHANGE_Z * se

    @property
    def scale(self) -> float | None:
        """The learnt factor (GNSS / raw radar), None until ``MIN_SAMPLES`` ratios."""
        return self._scale

    def drift_pct(self) -> float | None:
        """How far the learnt scale is from the calibrated factor, %."""
        k = self.scale
        return None if k is None else (k / self.calibrated - 1.0) * 100.0

    def drifted(self) -> bool:
        d = self.drift_pct()
        return d is not None and abs(d) > self.settings.alarm_pct


def _trimmed_mean(values: list[float]) -> float:
    """The mean of the middle 80 % (a radar glitch or a GNSS outlier left out, and 1.3 times
    less scatter than the median of the same ratios)."""
    v = sorted(values)
    k = int(len(v) * TRIM)
    return statistics.fmean(v[k:len(v) - k] if len(v) - 2 * k > 0 else v)


def _robust_sd(values: list[float]) -> float:
    """The ratios' scatter from their median absolute deviation (normal-consistent)."""
    med = statistics.median(values)
    return 1.4826 * statistics.median(abs(x - med) for x in values)
