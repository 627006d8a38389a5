"""A monotone curve through measured points, and its exact inverse.

A drill's discharge against shaft speed is not a parabola: the rotor under-fills at low
speed, fills less again past a knee at high speed, and the motor's speed against duty bends
too. Forcing paper A's quadratic eq. (6) through such a drill leaves 1–3 % of rate error and
refuses some monotonic drills as "non-monotonic" (issue 25). The rotation test therefore
keeps the drill's own shape: a piecewise cubic through its set points that rises wherever
the points rise (Fritsch–Carlson's monotone Hermite interpolation, the PCHIP of Fritsch &
Carlson 1980, SIAM J. Numer. Anal. 17(2), with the end slopes of scipy's ``pchip``), so the
controller can invert it without picking a wrong root.

Written here rather than taken from scipy: the daemon runs on an in-cab computer where
scipy's ~40 MB is the whole rate model's only use, and the interpolation is twenty lines;
``tests/gateway/core/test_monotone.py`` checks it against the published properties
(through the points, monotone, C¹, exact on a straight line).

Beyond the end points the curve goes on straight with the end slopes (the controller flags
any shaft speed outside the calibrated range anyway).
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache


def _end_slope(h0: float, h1: float, d0: float, d1: float) -> float:
    """The one-sided three-point end slope, kept monotone (scipy's ``pchip`` ends)."""
    m = ((2.0 * h0 + h1) * d0 - h0 * d1) / (h0 + h1)
    if m * d0 <= 0.0:
        return 0.0
    if d0 * d1 <= 0.0 and abs(m) > 3.0 * abs(d0):
        return 3.0 * d0
    return m


@dataclass(frozen=True)
class MonotoneCurve:
    """Monotone piecewise-cubic through ``points`` (x strictly rising, y strictly rising)."""

    xs: tuple[float, ...]
    ys: tuple[float, ...]
    slopes: tuple[float, ...]

    @classmethod
    def through(cls, points: Sequence[Sequence[float]]) -> MonotoneCurve:
        """The curve through ``points``; ValueError unless x and y both strictly rise (a
        curve that is flat or falls somewhere has no unique inverse) and are finite."""
        pts = [(float(p[0]), float(p[1])) for p in points]
        if len(pts) < 2:
            raise ValueError("a curve needs at least 2 points")
        if not all(math.isfinite(v) for p in pts for v in p):
            raise ValueError("curve points must be finite numbers")
        for (x0, y0), (x1, y1) in itertools.pairwise(pts):
            if not (x1 > x0 and y1 > y0):
                raise ValueError(
                    f"curve points must rise in both coordinates: ({x0:g}, {y0:g}) then "
                    f"({x1:g}, {y1:g})")
        xs = tuple(p[0] for p in pts)
        ys = tuple(p[1] for p in pts)
        h = [xs[i + 1] - xs[i] for i in range(len(xs) - 1)]
        d = [(ys[i + 1] - ys[i]) / h[i] for i in range(len(h))]
        if len(h) == 1:
            return cls(xs, ys, (d[0], d[0]))
        m = [0.0] * len(xs)
        for k in range(1, len(xs) - 1):
            w1, w2 = 2.0 * h[k] + h[k - 1], h[k] + 2.0 * h[k - 1]
            m[k] = (w1 + w2) / (w1 / d[k - 1] + w2 / d[k])  # weighted harmonic mean
        m[0] = _end_slope(h[0], h[1], d[0], d[1])
        m[-1] = _end_slope(h[-1], h[-2], d[-1], d[-2])
        return cls(xs, ys, tuple(m))

    def __call__(self, x: float) -> float:
        xs, ys, m = self.xs, self.ys, self.slopes
        if x <= xs[0]:
            return ys[0] + m[0] * (x - xs[0])
        if x >= xs[-1]:
            return ys[-1] + m[-1] * (x - xs[-1])
        i = bisect.bisect_right(xs, x) - 1
        h = xs[i + 1] - xs[i]
        t = (x - xs[i]) / h
        t2, t3 = t * t, t * t * t
        return ((2 * t3 - 3 * t2 + 1) * ys[i] + (t3 - 2 * t2 + t) * h * m[i]
                + (-2 * t3 + 3 * t2) * ys[i + 1] + (t3 - t2) * h * m[i + 1])

    def inverse(self, y: float) -> float:
        """The x where the curve is ``y`` (the curve is strictly rising between its points,
        so bisection on the one segment that holds ``y`` finds the only root). Beyond the
        ends: the straight continuation; ValueError where that is flat."""
        xs, ys, m = self.xs, self.ys, self.slopes
        if y <= ys[0] or y >= ys[-1]:
            end = 0 if y <= ys[0] else -1
            if m[end] <= 0.0:
                if y == ys[end]:
                    return xs[end]
                raise ValueError(f"{y:g} is beyond the curve's range {ys[0]:g}..{ys[-1]:g}")
            return xs[end] + (y - ys[end]) / m[end]
        i = bisect.bisect_right(ys, y) - 1
        lo, hi = xs[i], xs[i + 1]
        for _ in range(60):  # 2^-60 of a segment: exact to float precision
            mid = 0.5 * (lo + hi)
            if self(mid) < y:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def points(self) -> list[list[float]]:
        return [[x, y] for x, y in zip(self.xs, self.ys, strict=True)]


@lru_cache(maxsize=64)
def cached_curve(points: tuple[tuple[float, float], ...]) -> MonotoneCurve:
    """The curve for a config's points, built once (the controller evaluates it per tick)."""
    return MonotoneCurve.through(points)
