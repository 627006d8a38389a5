"""Field calibration maths and the calibration file (pure functions + atomic persistence).

Every seeder controller on the market has a "rotation test" and a speed calibration, because
the catalogue g/rev and the radar's mounting angle are never quite those of the machine in
the field. These are the fits the operator runs with ``sowgate calibrate``:

- paper A: duty -> shaft speed line ``R = slope*K + intercept`` and shaft speed -> metering
  rate quadratic ``Q = a*w^2 + b*w + c`` (g/min), both refused unless increasing over the
  working range (an inverse of a non-monotonic model picks the wrong root);
- paper B: grams per revolution ``m = M / (n*t/60)`` (``2M/n`` for 30 s runs), runs below
  20 r/min excluded as unstable, averaged;
- speed: a measured distance over the distance integrated from a speed source -> factor;
- inclinometer: paper A's level-ground zero; paper B's critical angle = mean of 3 readings
  with the implement lowered to the ground.

Results live in ``<state_dir>/calibration.json``; each save keeps the value it replaced so
``undo`` can restore it. Writes are atomic (temp file + fsync + rename) so a power cut in the
cab leaves either the old or the new file, never half of one.
"""

from __future__ import annotations

import bisect
import itertools
import json
import math
import os
import statistics
import tempfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from gateway.core.errors import GatewayError
from gateway.core.monotone import MonotoneCurve

_V = TypeVar("_V")


def by_set_point(set_points: Sequence[float], values: Sequence[_V]) -> dict[float, list[_V]]:
    """``values`` grouped by their run's set point, in run order: a rotation test repeats each
    set point, and every judgement of its repeats (scatter, means, weighing) starts here."""
    out: dict[float, list[_V]] = {}
    for k, v in zip(set_points, values, strict=True):
        out.setdefault(float(k), []).append(v)
    return out

CALIBRATION_FILE = "calibration.json"
FILE_VERSION = 1
HISTORY_MAX = 50  # undo depth kept in the file
PAPER_B_MIN_STABLE_RPM = 20.0
MIN_POINTS_LINE = 2
MIN_POINTS_QUAD = 3
SPEED_FACTOR_RANGE = (0.5, 1.5)
MIN_CAL_DISTANCE_M = 10.0
LOWERED_READINGS = 3
MAX_READING_SPREAD_DEG = 2.0  # readings further apart: the machine was moving

# Fit quality gates (``sowgate calibrate rotation`` refuses a fit outside them, with the
# reason, unless ``--accept-poor-fit``, which is logged and saved in the entry).
# Paper B's repeated runs agree within a few % (its table 2 runs: CV < 2 %); a CV above 10 %
# is a weighing, timing or typing mistake (a mass from another run, all outlets in one run and
# one in the next), not a meter that changes its displacement with speed. Both judge the
# constant g/rev, so they apply where the constant is saved (fewer than MIN_POINTS_MONOTONE set
# speeds); a test with a g/rev curve is judged on the curve (OFF_CURVE_SIGMAS).
MAX_GPR_CV_PCT = 10.0
MIN_GPR_R2 = 0.95  # delivered g/min against r/min through the origin (paper B: linear)
MIN_MOTOR_R2 = 0.95  # paper A eq. 5, duty -> r/min (the paper's fits: R² > 0.99)
MIN_METER_R2 = 0.95  # paper A eq. 6, r/min -> g/min
# Paper A set points spanning less than this fraction of the largest one give a line and a
# parabola that are not determined outside a sliver of the working range (poorly conditioned).
MIN_SET_POINT_SPAN = 0.25
# A result further than this from the value it replaces is shown side by side and refused
# unless ``--accept-large-change``: a 25x per-outlet/all-outlets mix-up must not pass quietly.
LARGE_CHANGE_PCT = 25.0


class CalibrationError(GatewayError):
    """A calibration cannot be accepted; the message tells the operator why."""


class InconsistentSetPoints(CalibrationError):
    """The readings of a rotation test contradict each other (a fall beyond the weighing
    noise): the message says it at length for the CLI; ``set_points`` are the ones to repeat,
    so a one-line display (the touchscreen's, 255 ASCII bytes) can name them first."""

    def __init__(self, message: str, what: str, set_points: Sequence[float]) -> None:
        super().__init__(message)
        self.what = what
        self.set_points = tuple(sorted(float(k) for k in set_points))


@dataclass(frozen=True)
class LineFit:
    slope: float
    intercept: float
    r2: float
    residuals: tuple[float, ...]

    def predict(self, x: float) -> float:
        return self.slope * x + self.intercept


@dataclass(frozen=True)
class QuadFit:
    a: float
    b: float
    c: float
    r2: float
    residuals: tuple[float, ...]

    def predict(self, x: float) -> float:
        return self.a * x * x + self.b * x + self.c


def _r2(y: np.ndarray[Any, Any], fitted: np.ndarray[Any, Any]) -> float:
    ss_res = float(np.sum((y - fitted) ** 2))
    ss_tot = float(np.sum((y - np.mean(y)) ** 2))
    return 1.0 if ss_tot == 0 else 1.0 - ss_res / ss_tot


def _arrays(xs: Sequence[float], ys: Sequence[float], need: int,
            what: str) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    if len(xs) != len(ys):
        raise CalibrationError(f"{what}: {len(xs)} x values but {len(ys)} y values")
    x, y = np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise CalibrationError(f"{what}: values must be finite numbers")
    if len(set(x.tolist())) < need:
        raise CalibrationError(f"{what}: need at least {need} distinct set points")
    return x, y


def fit_line(xs: Sequence[float], ys: Sequence[float]) -> LineFit:
    x, y = _arrays(xs, ys, MIN_POINTS_LINE, "line fit")
    slope, intercept = np.polyfit(x, y, 1)
    fitted = slope * x + intercept
    return LineFit(float(slope), float(intercept), _r2(y, fitted), tuple((y - fitted).tolist()))


def fit_quadratic(xs: Sequence[float], ys: Sequence[float]) -> QuadFit:
    x, y = _arrays(xs, ys, MIN_POINTS_QUAD, "quadratic fit")
    a, b, c = np.polyfit(x, y, 2)
    fitted = a * x * x + b * x + c
    return QuadFit(float(a), float(b), float(c), _r2(y, fitted), tuple((y - fitted).tolist()))


def fit_motor_line(duty_pct: Sequence[float], rpm: Sequence[float],
                   working_range: tuple[float, float] | None = None) -> LineFit:
    """Paper A eq. (5): shaft r/min against PWM duty %; must rise with duty."""
    fit = fit_line(duty_pct, rpm)
    if fit.slope <= 0:
        lo, hi = working_range or (min(duty_pct), max(duty_pct))
        raise CalibrationError(
            f"motor speed does not rise with duty over {lo:g}..{hi:g} % "
            f"(slope {fit.slope:.4f} r/min per %); check the motor wiring and the readings"
        )
    return fit


def fit_meter_quadratic(rpm: Sequence[float], rate_g_min: Sequence[float],
                        working_range: tuple[float, float] | None = None) -> QuadFit:
    """Paper A eq. (6): metering rate g/min against shaft r/min; must rise over the range."""
    fit = fit_quadratic(rpm, rate_g_min)
    lo, hi = working_range or (min(rpm), max(rpm))
    if lo >= hi:
        raise CalibrationError(f"working range {lo:g}..{hi:g} r/min is empty")
    slopes = [2 * fit.a * w + fit.b for w in (lo, hi)]  # derivative is linear: ends suffice
    if min(slopes) <= 0:
        raise CalibrationError(
            f"metering rate is not increasing over {lo:g}..{hi:g} r/min (dQ/dw "
            f"{slopes[0]:.2f} .. {slopes[1]:.2f}); narrow the range or repeat the weighings"
        )
    return fit


# A rotation test with at least this many distinct set points is fitted with the drill's own
# monotone shape (``fit_monotone``) instead of paper A's line and quadratic (issue 25).
MIN_POINTS_MONOTONE = 5
# The weighing noise assumed when no set point was repeated: paper B's repeated runs agree
# within 2 % (its table 2: CV < 2 %). Repeats give the test's own noise instead.
DEFAULT_RUN_CV = 0.02
# A fall between neighbouring set points beyond this many standard errors of the difference
# is not noise: the readings are inconsistent and those set points are to be repeated.
MONOTONE_FALL_SIGMAS = 3.0


@dataclass(frozen=True)
class MonotoneFit:
    """The drill's own curve: monotone piecewise cubic through the set points' means (knots),
    with falls within the noise pooled (isotonic regression) rather than refused."""

    points: tuple[tuple[float, float], ...]  # knots, both coordinates strictly rising
    residuals: tuple[float, ...]  # each run against the curve, in y units
    pooled: tuple[tuple[float, ...], ...]  # groups of set-point x merged as within noise
    run_cv: float  # the relative noise used (from repeats, or DEFAULT_RUN_CV)
    model: str = "monotone_cubic"

    def predict(self, x: float) -> float:
        return MonotoneCurve.through(self.points)(x)


def fit_monotone(xs: Sequence[float], ys: Sequence[float], what: str,
                 groups: Sequence[float] | None = None,
                 weights: Sequence[float] | None = None) -> MonotoneFit:
    """Paper A's rotation test fitted with the drill's own shape (issue 25).

    Runs of one set point (``groups``: the set point of each run, e.g. its duty; default the
    x value) are averaged into one knot. Where a knot is lower than the one before it the
    fall is compared with the noise of the two means (the runs' own scatter when set points
    were repeated, else ``DEFAULT_RUN_CV``): within ``MONOTONE_FALL_SIGMAS`` it is noise and
    the two are pooled (pool-adjacent-violators, the least-squares monotone fit); beyond, the
    readings are inconsistent and CalibrationError names the set points to repeat. The knots
    left carry a monotone piecewise cubic (``gateway.core.monotone``), which the controller
    inverts exactly.

    ``weights``: each run's length (default all equal). Set points may run for different
    lengths (``--seconds 300,240,120,60,60,60``): a knot, and a pooled block, is then the
    time-weighted mean of its runs' rates, i.e. its total catch over its total run time, not
    a plain mean that would give a 60 s run as much say as a 300 s one. The fall test keeps
    counting runs (the noise of a long run's set point is over-, not under-stated: pooled
    rather than refused).
    """
    x, y = _arrays(xs, ys, 2, what)
    w = np.ones(len(x)) if weights is None else np.asarray(list(weights), dtype=float)
    if len(w) != len(x) or not bool(np.all(w > 0)):
        raise CalibrationError(f"{what}: {len(w)} positive run lengths needed for {len(x)} runs")
    keys = list(groups) if groups is not None else x.tolist()
    if len(keys) != len(x):
        raise CalibrationError(f"{what}: {len(keys)} set points for {len(x)} runs")
    by_key = by_set_point(keys, range(len(keys)))
    if len(by_key) < MIN_POINTS_MONOTONE:
        raise CalibrationError(
            f"{what}: the drill's own curve needs at least {MIN_POINTS_MONOTONE} distinct set "
            f"points (got {len(by_key)})")
    rel = [float(y[i] / np.mean(y[idx])) for idx in by_key.values() if len(idx) > 1
           for i in idx if np.mean(y[idx]) > 0]
    n_rep = sum(len(idx) - 1 for idx in by_key.values() if len(idx) > 1)
    run_cv = DEFAULT_RUN_CV
    if n_rep >= 3:  # enough repeats to measure the test's own noise (never below 0.5 %)
        run_cv = max(0.005, math.sqrt(sum((r - 1.0) ** 2 for r in rel) / n_rep))
    # blocks: (set points, runs n, mean x, mean y, run time t), in order of mean x; the means
    # weighted by run time (equal lengths: the plain means)
    blocks = sorted(
        ([k], float(len(idx)), float(np.average(x[idx], weights=w[idx])),
         float(np.average(y[idx], weights=w[idx])), float(np.sum(w[idx])))
        for k, idx in by_key.items())
    merged: list[tuple[list[float], float, float, float, float]] = []
    for blk in blocks:
        merged.append(blk)
        while len(merged) > 1 and merged[-1][3] <= merged[-2][3]:
            (k1, n1, x1, y1, t1), (k2, n2, x2, y2, t2) = merged[-2], merged[-1]
            level = max(abs(y1), abs(y2), 1e-9)
            se = run_cv * level * math.sqrt(1.0 / n1 + 1.0 / n2)
            if y1 - y2 > MONOTONE_FALL_SIGMAS * se:
                raise InconsistentSetPoints(
                    f"{what} is not increasing: falls from {y1:.4g} at set point(s) "
                    f"{_names(k1)} to {y2:.4g} at {_names(k2)}, {(y1 - y2) / se:.1f} times the "
                    "weighing noise "
                    f"({run_cv * 100:.1f} %): the readings are inconsistent; repeat set "
                    f"point(s) {_names(k1 + k2)}", what, k1 + k2)
            t = t1 + t2
            merged[-2:] = [(k1 + k2, n1 + n2, (t1 * x1 + t2 * x2) / t,
                            (t1 * y1 + t2 * y2) / t, t)]
    points = tuple((b[2], b[3]) for b in merged)
    if len(points) < 2 or any(b[0] <= a[0] for a, b in itertools.pairwise(points)):
        raise CalibrationError(f"{what}: the set points do not spread over a range")
    curve = MonotoneCurve.through(points)
    resid = tuple(float(yi - curve(float(xi))) for xi, yi in zip(x, y, strict=True))
    return MonotoneFit(points, resid, tuple(tuple(b[0]) for b in merged if len(b[0]) > 1),
                       run_cv)


# A set point's mean flow known only to worse than this (its standard error from the repeats,
# relative) carries that much into the rate wherever the drill sows near it: rapeseed's catches
# of 25–150 g on a σ 2 g scale are 1–8 % per weighing, and leave ~2 % of rate error at p90
# over drills (benchmarks/bench_rate.py); a finer scale or longer runs bring it under 1 %.
SET_POINT_SE_LIMIT_PCT = 1.0


@dataclass(frozen=True)
class ImpreciseSetPoint:
    set_point: float
    se_pct: float  # standard error of its mean flow, % of the mean
    runs: int  # runs weighed
    runs_needed: int  # of the same length, for SET_POINT_SE_LIMIT_PCT (SE falls as 1/√n)


def imprecise_set_points(set_points: Sequence[float], rates: Sequence[float],
                         limit_pct: float = SET_POINT_SE_LIMIT_PCT) -> list[ImpreciseSetPoint]:
    """The repeated set points whose mean flow is known to worse than ``limit_pct`` (the
    scatter of their own repeats): a warning with what to repeat, not a refusal — the
    readings are consistent, only too few or too small for the rate wanted."""
    by_key = by_set_point(set_points, [float(q) for q in rates])
    out = []
    for k, qs in sorted(by_key.items()):
        mean = statistics.fmean(qs)
        if len(qs) < 2 or mean <= 0:
            continue
        se = statistics.stdev(qs) / math.sqrt(len(qs)) / mean * 100.0
        if se > limit_pct:
            need = math.ceil(len(qs) * (se / limit_pct) ** 2)
            out.append(ImpreciseSetPoint(k, se, len(qs), need))
    return out


def _names(keys: Sequence[float]) -> str:
    return ", ".join(f"{k:.4g}" for k in sorted(keys))


@dataclass(frozen=True)
class RotationRun:
    """One timed run of the rotation test: shaft speed, duration, weighed mass."""

    rpm: float  # effective shaft speed over the run (turns per minute of run time)
    seconds: float
    mass_g: float
    set_rpm: float | None = None  # the commanded speed, when it differs (measured turns)

    @property
    def stability_rpm(self) -> float:
        """The speed the paper's "below 20 r/min is unstable" rule is about: the set speed."""
        return self.rpm if self.set_rpm is None else self.set_rpm

    @property
    def grams_per_rev(self) -> float:
        return self.mass_g / (self.rpm * self.seconds / 60.0)


@dataclass(frozen=True)
class GramsPerRevFit:
    grams_per_rev: float
    used: tuple[RotationRun, ...]
    excluded: tuple[RotationRun, ...]
    per_run: tuple[float, ...]
    cv_pct: float
    r2: float  # of delivered g/min against r/min through the origin (paper B: linear)
    residuals_g_min: tuple[float, ...]


def grams_per_rev(runs: Sequence[RotationRun],
                  min_stable_rpm: float = PAPER_B_MIN_STABLE_RPM) -> GramsPerRevFit:
    """Paper B's per-revolution displacement from weighed runs."""
    for r in runs:
        if not (r.rpm > 0 and r.seconds > 0 and r.mass_g >= 0) or not all(
            math.isfinite(v) for v in (r.rpm, r.seconds, r.mass_g)
        ):
            raise CalibrationError(f"run {r}: speed and time must be > 0, mass >= 0")
    used = tuple(r for r in runs if r.stability_rpm >= min_stable_rpm)
    excluded = tuple(r for r in runs if r.stability_rpm < min_stable_rpm)
    if len(used) < 2:
        raise CalibrationError(
            f"need at least 2 runs at or above {min_stable_rpm:g} r/min (slower runs are "
            f"unstable); got {len(used)}"
        )
    per_run = np.array([r.grams_per_rev for r in used])
    mean = float(np.mean(per_run))
    if mean <= 0:
        raise CalibrationError("the weighed masses give no discharge; was the hopper empty?")
    n = np.array([r.rpm for r in used])
    q = np.array([r.mass_g / (r.seconds / 60.0) for r in used])
    fitted = mean * n
    cv = float(np.std(per_run, ddof=1) / mean * 100)
    return GramsPerRevFit(mean, used, excluded, tuple(per_run.tolist()), cv, _r2(q, fitted),
                          tuple((q - fitted).tolist()))


def grams_per_rev_by_speed(runs: Sequence[RotationRun]) -> list[tuple[float, float]] | None:
    """Paper B's g/rev as a function of shaft speed: [r/min, g/rev] knots, or None with fewer
    than ``MIN_POINTS_MONOTONE`` set speeds (then the constant ``grams_per_rev`` is used).

    Paper B runs its test at 10..60 r/min: a meter whose cells fill less at speed delivers
    fewer grams per turn there (20 % less from 10 to 60 r/min: a constant g/rev errs by
    +8.5 / +6.9 / -3.9 % across the range, issue 25). Every run counts here, the slow ones
    too (their speed is what the curve is about; repeats average their scatter). The
    delivered g/min must rise with speed (``fit_monotone``: a fall beyond the weighing noise
    is refused naming the speeds to repeat); the channel inverts that curve."""
    keys = [r.stability_rpm for r in runs]
    if len(set(keys)) < MIN_POINTS_MONOTONE:
        return None
    fit = fit_monotone([r.rpm for r in runs], [r.mass_g / (r.seconds / 60.0) for r in runs],
                       "delivered g/min against r/min", groups=keys,
                       weights=[r.seconds for r in runs])
    return [(n, q / n) for n, q in fit.points]


# Paper B's g/rev curve is judged as the model it is (issue 25 §3): each set speed's g/rev
# against the curve through the other set speeds, in units of what its weighing, its turn
# count and the curve's ignorance of the meter between set speeds explain. Beyond
# ``OFF_CURVE_SIGMAS`` of that the run is named to be repeated. (The constant g/rev's R² and CV
# gates judged a straight line through the runs that the curve replaces: they refused 12 of
# 60 drawn meters whose g/rev changes with speed, benchmarks/bench_multichannel.py.)
OFF_CURVE_SIGMAS = 3.0
# The shaft's turns over a run are known to ±¼ turn (counted to the nearest ½ turn, or the
# controller's speed integrated, run-down included), taken as one σ: 5 % of a 30 s run at
# 10 r/min, 0.8 % at 60 r/min. The turns of a manual run are its set speed times its time.
TURN_COUNT_SIGMA = 0.25
# The meter's own run-to-run variation beyond the scale and the count (fit_monotone's floor
# for a test's measured noise), one σ per run.
RUN_FLOOR_CV = 0.005
# What the curve through the other set speeds cannot know of the meter between them, one σ.
# Where within a gap between set speeds a meter makes its change is unknown: with a knee on
# the speed left out the whole change lies on one side of it and the curve through the others
# is off by up to half the gap's change, so 3 σ is half of it (CURVE_SHAPE_FRACTION of the
# change of g/rev across the others' gap). Beyond the others' ends the curve is extrapolated:
# a fall steepening towards 60 r/min (a late knee, power 2) leaves the end speed twice the
# change across the nearest gap off, so there one σ is that change (CURVE_END_FRACTION, per
# gap's width out). Never below CURVE_SHAPE_CV. Checked on meters changing −25…+5 % from
# knees at 10…40 r/min (tests/gateway/calibration/test_gpr_curve_gate.py).
CURVE_SHAPE_FRACTION = 0.17
CURVE_END_FRACTION = 1.0
CURVE_SHAPE_CV = 0.01
# the curve through the others needs this many set speeds (a cubic with its end slopes)
MIN_OTHER_SPEEDS = 3


@dataclass(frozen=True)
class SpeedOnCurve:
    """One set speed of a paper-B test against the curve through the others."""

    set_rpm: float
    runs: int
    grams_per_rev: float  # its own: its catch over its turns
    curve_grams_per_rev: float  # the curve through the other set speeds, at its speed
    off_pct: float  # its own against the curve's, %
    sigma_pct: float  # what the weighing, the turn count and the curve's shape explain, 1 σ
    # an end speed named, whose neighbour's leaving out would also make the rest agree: the
    # end is judged on the others' curve carried on from that neighbour, which either throws
    beside_rpm: float | None = None

    @property
    def sigmas(self) -> float:
        return abs(self.off_pct) / self.sigma_pct

    def problem(self) -> str:
        """Which run to repeat and why, in the words of the paper-A test's refusals."""
        runs = "run" if self.runs == 1 else f"{self.runs} runs"
        what = f"the {self.set_rpm:g} r/min {runs}"
        beside = ""
        if self.beside_rpm is not None:
            what += f" and the {self.beside_rpm:g} r/min run beside it"
            beside = (f"; the end is judged on the others' curve carried on from "
                      f"{self.beside_rpm:g} r/min, which a mistake in either throws off")
        return (
            f"repeat {what}: the {self.set_rpm:g} r/min g/rev {self.grams_per_rev:.4g} is "
            f"{self.off_pct:+.1f} % off the curve through the others "
            f"({self.curve_grams_per_rev:.4g} there), {self.sigmas:.1f} times what the "
            f"weighing, the turn count and the curve's shape explain (±{self.sigma_pct:.1f} %, "
            f"OFF_CURVE_SIGMAS {OFF_CURVE_SIGMAS:g}){beside}; a catch from another run, or "
            "outlets missed?")


@dataclass(frozen=True)
class _SpeedPoint:
    set_rpm: float
    runs: int
    rpm: float  # its runs' turns over their time
    flow: float  # g/min: its runs' catch over their time
    cv: float  # relative σ of its g/rev (weighing, turns, floor)


def _speed_points(runs: Sequence[RotationRun], scale_g: float,
                  outlets_weighed: int) -> list[_SpeedPoint]:
    """The set speeds' g/min points, each with its g/rev's relative σ: the scale's ``scale_g``
    on each weighed catch (``outlets_weighed`` outlets' worth of the per-outlet mass), the
    turn count's ``TURN_COUNT_SIGMA`` on each run's turns, ``RUN_FLOOR_CV`` per run; where
    repeats say the runs scatter more (3 or more repeats), their own scatter."""
    groups = by_set_point([r.stability_rpm for r in runs], list(runs))
    rel = [r.grams_per_rev / statistics.fmean(g.grams_per_rev for g in grp) for grp in
           groups.values() if len(grp) > 1 for r in grp]
    n_rep = sum(len(grp) - 1 for grp in groups.values() if len(grp) > 1)
    scatter = math.sqrt(sum((x - 1.0) ** 2 for x in rel) / n_rep) if n_rep >= 3 else 0.0
    out = []
    for k, grp in sorted(groups.items()):
        minutes = sum(r.seconds for r in grp) / 60.0
        catch = sum(r.mass_g for r in grp) * outlets_weighed
        turns = sum(r.rpm * r.seconds / 60.0 for r in grp)
        n = len(grp)
        var = (n * scale_g**2 / catch**2 if catch > 0 else 0.0) + (  # none: not the scale
            n * TURN_COUNT_SIGMA**2 / turns**2) + RUN_FLOOR_CV**2 / n
        cv = max(math.sqrt(var), scatter / math.sqrt(n))
        out.append(_SpeedPoint(k, n, turns / minutes, sum(r.mass_g for r in grp) / minutes,
                               cv))
    return out


def _pooled(points: Sequence[tuple[float, float, float]]) -> list[tuple[float, float]]:
    """(x, y, weight) rising in x made rising in y too by pooling neighbours (the
    least-squares monotone fit): the curve through the others is built as the saved one is,
    without its refusals (the whole test has been judged by ``fit_monotone`` already)."""
    merged: list[tuple[float, float, float]] = []
    for p in points:
        merged.append(p)
        while len(merged) > 1 and merged[-1][1] <= merged[-2][1]:
            (x1, y1, w1), (x2, y2, w2) = merged[-2], merged[-1]
            w = w1 + w2
            merged[-2:] = [((w1 * x1 + w2 * x2) / w, (w1 * y1 + w2 * y2) / w, w)]
    return [(x, y) for x, y, _ in merged]


def _shape_cv(rpm: float, others: Sequence[_SpeedPoint]) -> float:
    """What the curve through ``others`` cannot know of the meter at ``rpm``, relative, 1 σ:
    the change of g/rev across the others' gap that holds it (where in the gap a meter makes
    it is unknown: a knee on the speed left out puts the whole change on one side of it),
    ``CURVE_SHAPE_FRACTION`` of it, never below ``CURVE_SHAPE_CV``; beyond the others' ends
    ``CURVE_END_FRACTION`` of the change across the nearest gap per gap's width out (the curve
    is extrapolated there)."""
    pts = sorted((o.rpm, o.flow / o.rpm) for o in others)
    mean = statistics.fmean(g for _, g in pts)
    if rpm <= pts[0][0] or rpm >= pts[-1][0]:
        (x0, g0), (x1, g1) = pts[:2] if rpm <= pts[0][0] else pts[-2:]
        out = (pts[0][0] - rpm) if rpm <= pts[0][0] else (rpm - pts[-1][0])
        cv = CURVE_END_FRACTION * abs(g1 - g0) / mean * max(1.0, out / (x1 - x0))
    else:
        i = bisect.bisect_right([x for x, _ in pts], rpm) - 1
        cv = CURVE_SHAPE_FRACTION * abs(pts[i + 1][1] - pts[i][1]) / mean
    return max(CURVE_SHAPE_CV, cv)


def _against_others(point: _SpeedPoint, others: Sequence[_SpeedPoint]) -> SpeedOnCurve | None:
    """``point`` against the monotone curve through ``others`` (None when they do not make
    one). The curve's own error at the point: each other point moved by its σ in turn.

    Beyond the others' ends the g/rev is carried on along the g/rev trend of their nearest
    gap, not the g/min curve's end slope: g/min extrapolated from 20 and 30 r/min down to 10
    quadruples their errors in g/rev there (a 2.6 % count at 20 r/min becomes 10 %), g/rev
    doubles them."""
    x = point.rpm

    def predict(ys: Sequence[float]) -> float | None:
        knots = _pooled([(o.rpm, y, float(o.runs)) for o, y in zip(others, ys, strict=True)])
        if len(knots) < 2 or any(b[0] <= a[0] for a, b in itertools.pairwise(knots)):
            return None
        if knots[0][0] < x < knots[-1][0]:
            return MonotoneCurve.through(knots)(x)
        (x0, q0), (x1, q1) = knots[:2] if x <= knots[0][0] else knots[-2:]
        g0, g1 = q0 / x0, q1 / x1
        return (g0 + (g1 - g0) * (x - x0) / (x1 - x0)) * x

    ys = [o.flow for o in others]
    base = predict(ys)
    if base is None or base <= 0:
        return None
    spread = 0.0
    for i, o in enumerate(others):
        moved = predict([*ys[:i], o.flow * (1 + o.cv), *ys[i + 1:]])
        if moved is not None:
            spread += (moved / base - 1.0) ** 2
    sigma = math.sqrt(point.cv**2 + spread + _shape_cv(point.rpm, others) ** 2)
    return SpeedOnCurve(point.set_rpm, point.runs, point.flow / point.rpm, base / point.rpm,
                        (point.flow / base - 1.0) * 100.0, sigma * 100.0)


def speeds_on_curve(runs: Sequence[RotationRun], *, scale_g: float,
                    outlets_weighed: int = 1) -> tuple[list[SpeedOnCurve], list[SpeedOnCurve]]:
    """Paper B's set speeds each against the g/rev curve through the others: (all of them as
    first judged, the ones off it).

    While any is beyond ``OFF_CURVE_SIGMAS``, one is named (``_the_one_off``), left out, and
    the rest judged again without it, as long as ``MIN_OTHER_SPEEDS`` others remain.
    ``scale_g``: the scale's σ per weighing; ``outlets_weighed``: how many outlets each
    weighed catch held (the runs' masses are per outlet)."""
    if not scale_g > 0:
        raise CalibrationError(f"the scale's error must be > 0 g (got {scale_g:g})")
    points = _speed_points(runs, scale_g, outlets_weighed)
    first: list[SpeedOnCurve] = []
    off: list[SpeedOnCurve] = []
    while len(points) > MIN_OTHER_SPEEDS:
        judged = _judge(points)
        if not first:
            first = [j for _, j in judged]
        if max(j.sigmas for _, j in judged) <= OFF_CURVE_SIGMAS:
            break
        point, named = _the_one_off(points, judged)
        off.append(named)
        points = [p for p in points if p is not point]
    return first, off


def _the_one_off(points: Sequence[_SpeedPoint],
                 judged: Sequence[tuple[_SpeedPoint, SpeedOnCurve]]) -> tuple[
                     _SpeedPoint, SpeedOnCurve]:
    """Which set speed to name when some are off the curve through the others.

    A bad run also throws the curve through the others off at its neighbours, the ends most
    (extrapolated), so the one furthest off need not be it. Named: one whose leaving out makes
    the rest agree, and of those the one that, left out, explains most (its own σ² off the
    others' curve, less the rest's about theirs); where none does, the furthest off. An end
    named whose neighbour's leaving out would also make the rest agree is named with it."""
    worst = max(judged, key=lambda pj: pj[1].sigmas)
    if len(points) - 1 <= MIN_OTHER_SPEEDS:
        return worst
    scored = []
    for p, j in judged:
        left = [k.sigmas for _, k in _judge([o for o in points if o is not p])]
        scored.append((max([OFF_CURVE_SIGMAS, *left]), sum(x * x for x in left) - j.sigmas**2,
                       p, j))
    scored.sort(key=lambda t: (t[0], t[1]))
    _, _, p, j = scored[0]
    speeds = sorted(o.set_rpm for o in points)
    if p.set_rpm in (speeds[0], speeds[-1]):
        beside = speeds[1] if p.set_rpm == speeds[0] else speeds[-2]
        if any(o.set_rpm == beside and agree <= OFF_CURVE_SIGMAS for agree, _, o, _ in scored):
            j = replace(j, beside_rpm=beside)
    return p, j


def _judge(points: Sequence[_SpeedPoint]) -> list[tuple[_SpeedPoint, SpeedOnCurve]]:
    out = []
    for p in points:
        j = _against_others(p, [o for o in points if o is not p])
        if j is not None:
            out.append((p, j))
    return out


def grams_per_rev_test_problems(fit: GramsPerRevFit, runs: Sequence[RotationRun],
                                by_speed: list[tuple[float, float]] | None, *,
                                scale_g: float, outlets_weighed: int = 1) -> list[str]:
    """Why a paper-B rotation test should not be saved, judged on the model that is saved
    (empty: it passes). With a g/rev curve (``by_speed``), each set speed against the curve
    through the others (``speeds_on_curve``): a meter whose g/rev changes with speed is the
    curve's business, a run off it is named. With the constant (fewer set speeds), the
    constant's own gates (``grams_per_rev_problems``)."""
    if by_speed is None:
        return grams_per_rev_problems(fit)
    return [s.problem() for s in speeds_on_curve(runs, scale_g=scale_g,
                                                 outlets_weighed=outlets_weighed)[1]]


def grams_per_rev_result(fit: GramsPerRevFit,
                         by_speed: list[tuple[float, float]] | None) -> dict[str, Any]:
    """What a paper-B rotation test saves as its entry's ``result``: the fit, and the g/rev
    curve when the test had enough set speeds. One builder for ``sowgate calibrate rotation``
    and the benchmark that judges it (bench_multichannel), so the figures are measured on
    what the daemon applies, not on a copy of it. New files say their model
    (``gpr_model``); older readers use the mean."""
    result = asdict(fit)
    if by_speed is not None:
        result.update(gpr_model="per_speed_curve",
                      grams_per_rev_curve=[list(p) for p in by_speed])
    return result


def grams_per_rev_problems(fit: GramsPerRevFit, *, max_cv_pct: float = MAX_GPR_CV_PCT,
                           min_r2: float = MIN_GPR_R2) -> list[str]:
    """Why the constant g/rev should not be trusted (empty: it passes every gate). Only where
    the constant is what is saved and sown with: a test with a g/rev curve is judged on the
    curve (``grams_per_rev_test_problems``)."""
    problems = []
    if fit.cv_pct > max_cv_pct:
        problems.append(
            f"the runs disagree: g/rev CV {fit.cv_pct:.1f} % > {max_cv_pct:g} % "
            "(MAX_GPR_CV_PCT); check each mass belongs to its run and the same outlets were "
            "weighed every time"
        )
    if fit.r2 < min_r2:
        problems.append(
            f"delivered g/min does not follow r/min: R² {fit.r2:.3f} < {min_r2:g} (MIN_GPR_R2)"
        )
    return problems


def _span_fraction(values: Sequence[float]) -> float:
    top = max(abs(v) for v in values)
    return 0.0 if top == 0 else (max(values) - min(values)) / top


def paper_a_problems(line: LineFit, quad: QuadFit, duties: Sequence[float],
                     rpm: Sequence[float], *, min_motor_r2: float = MIN_MOTOR_R2,
                     min_meter_r2: float = MIN_METER_R2,
                     min_span: float = MIN_SET_POINT_SPAN) -> list[str]:
    """Why paper A's eq. 5 / eq. 6 fits should not be trusted (empty: every gate passes)."""
    problems = []
    if line.r2 < min_motor_r2:
        problems.append(
            f"eq. 5 (duty -> r/min) fits poorly: R² {line.r2:.3f} < {min_motor_r2:g} "
            "(MIN_MOTOR_R2); re-measure the shaft speeds"
        )
    if quad.r2 < min_meter_r2:
        problems.append(
            f"eq. 6 (r/min -> g/min) fits poorly: R² {quad.r2:.3f} < {min_meter_r2:g} "
            "(MIN_METER_R2); repeat the weighings"
        )
    for what, values in (("duty", duties), ("shaft speed", rpm)):
        span = _span_fraction(values)
        if span < min_span:
            problems.append(
                f"the {what} set points span only {span * 100:.0f} % of the largest "
                f"(< {min_span * 100:g} %, MIN_SET_POINT_SPAN): the fit is poorly conditioned; "
                "spread the runs over the working range"
            )
    return problems


@dataclass(frozen=True)
class PaperAFit:
    """A paper-A rotation test fitted: eq. 5 and eq. 6 always (shown, and read by older
    versions), the drill's own curves from ``MIN_POINTS_MONOTONE`` set points on."""

    line: LineFit
    quad: QuadFit
    motor_own: MonotoneFit | None
    meter_own: MonotoneFit | None
    problems: list[str]
    working_range: tuple[float, float]
    rates_g_min: tuple[float, ...] = ()  # each run's discharge, as fitted

    def predict_flow(self, rpm: float) -> float:
        return self.meter_own.predict(rpm) if self.meter_own else self.quad.predict(rpm)

    def result(self) -> dict[str, Any]:
        """The calibration entry's ``result``: new files say their model."""
        out: dict[str, Any] = {"motor": asdict(self.line), "meter": asdict(self.quad),
                               "omega_range": list(self.working_range),
                               "meter_model": "quadratic"}
        if self.meter_own is not None and self.motor_own is not None:
            out.update(meter_model=self.meter_own.model, motor_model=self.motor_own.model,
                       meter_curve=[list(p) for p in self.meter_own.points],
                       motor_curve=[list(p) for p in self.motor_own.points],
                       pooled_set_points=[list(g) for g in self.meter_own.pooled])
        return out


def fit_paper_a(duties: Sequence[float], rpm: Sequence[float], rates: Sequence[float],
                working_range: tuple[float, float],
                seconds: Sequence[float] | None = None) -> PaperAFit:
    """Paper A's rotation test: with ``MIN_POINTS_MONOTONE`` distinct duties or more, the
    drill's own monotone curves (its quadratic is then only shown: a monotonic drill with a
    knee is not refused because a parabola through it turns over); fewer, eq. 5 and eq. 6 as
    the paper fits them, refused unless increasing. CalibrationError when it cannot fit.

    ``rpm`` and ``rates`` are per run (turns and catch over that run's own length);
    ``seconds``: the runs' lengths when set points ran for different ones, the own curves'
    knots then weighting each run by its length (``fit_monotone``)."""
    line = fit_motor_line(duties, rpm)
    if len(set(duties)) >= MIN_POINTS_MONOTONE:
        motor_own = fit_monotone(duties, rpm, "duty -> r/min", weights=seconds)
        meter_own = fit_monotone(rpm, rates, "r/min -> g/min", groups=duties, weights=seconds)
        quad = fit_quadratic(rpm, rates)
        # the R² gates judge the line and the quadratic, which the own curves replace
        problems = paper_a_problems(line, quad, duties, rpm, min_motor_r2=-math.inf,
                                    min_meter_r2=-math.inf)
        return PaperAFit(line, quad, motor_own, meter_own, problems, working_range,
                         tuple(rates))
    quad = fit_meter_quadratic(rpm, rates, working_range)
    return PaperAFit(line, quad, None, None, paper_a_problems(line, quad, duties, rpm),
                     working_range, tuple(rates))


def fit_rotation_test(duties: Sequence[float], rpm: Sequence[float],
                      catches_g: Sequence[float], seconds: Sequence[float], *,
                      whole_machine: float = 1.0,
                      working_range: tuple[float, float] | None = None) -> PaperAFit:
    """Paper A's rotation test as typed, fitted: the one fit behind ``calibrate rotation``
    and the touchscreen's "save" (F=09 ``04``), so a drill calibrated at either gets the same
    curves (a knee drill its own monotone curves from ``MIN_POINTS_MONOTONE`` set points on,
    with the same refusals, ``fit_paper_a``).

    Per run: its duty, the shaft r/min read, the catch weighed and the run's length (set
    points run for different lengths: each rate is its catch over its own length, and the
    own curves' knots weight each run by that length). ``whole_machine``: the factor from
    the outlets weighed to all of them (eq. 6 is the whole machine's discharge).
    ``working_range``: r/min, default the speeds read."""
    if not len(duties) == len(rpm) == len(catches_g) == len(seconds):
        raise CalibrationError(
            f"rotation test: {len(duties)} duties, {len(rpm)} shaft speeds, "
            f"{len(catches_g)} catches and {len(seconds)} run lengths")
    if not all(t > 0 for t in seconds):
        raise CalibrationError("rotation test: every run must last more than 0 s")
    rates = [m * whole_machine / (t / 60.0) for m, t in zip(catches_g, seconds, strict=True)]
    wr = working_range if working_range is not None else (min(rpm), max(rpm))
    return fit_paper_a(duties, rpm, rates, wr, seconds=seconds)


def paper_a_changes(motor: dict[str, float], meter: dict[str, float], fit: PaperAFit,
                    duties: Sequence[float]) -> list[tuple[str, float, float]]:
    """What a paper-A result changes against the eq. 5 / eq. 6 it replaces: (what, old, new)
    for the motor at the middle duty and the discharge at the middle of the working range
    (the new one on the drill's own curve when it has one). ``LARGE_CHANGE_PCT`` judges these
    rows at the CLI and at the touchscreen alike."""
    mid_duty = (min(duties) + max(duties)) / 2
    mid_w = (fit.working_range[0] + fit.working_range[1]) / 2
    old_q = meter["a"] * mid_w * mid_w + meter["b"] * mid_w + meter["c"]
    return [
        (f"r/min at {mid_duty:.0f} % duty (eq. 5)",
         motor["slope"] * mid_duty + motor["intercept"], fit.line.predict(mid_duty)),
        (f"g/min at {mid_w:.0f} r/min (eq. 6)", old_q, fit.predict_flow(mid_w)),
    ]


def change_pct(new: float, old: float) -> float:
    """Signed relative change of ``new`` against ``old`` in % (inf when old is 0)."""
    if old == 0:
        return 0.0 if new == 0 else math.inf
    return (new - old) / abs(old) * 100.0


@dataclass(frozen=True)
class SpeedCalibration:
    source: str
    measured_m: float
    integrated_m: float
    factor: float  # multiply the source's speed by this


def integrate_distance(samples: Sequence[tuple[float, float]], *,
                       between_marks: bool = False) -> float:
    """Trapezoidal distance (m) from (time s, speed km/h) samples.

    ``between_marks``: the samples are a log taken at a steady interval between the start and
    the finish mark, so the first sample comes on average half an interval after the start
    and the last half an interval before the finish. The trapezoid alone misses that travel
    (a 3 Hz log over a 50 m run came out ~0.6 % short, so the factor ~0.6 % too high); half
    the median interval is added at each end, at the end samples' speeds.
    """
    if len(samples) < 2:
        raise CalibrationError("need at least 2 speed samples to integrate a distance")
    dist = 0.0
    for (t0, v0), (t1, v1) in itertools.pairwise(samples):
        if t1 < t0:
            raise CalibrationError("speed samples must be in time order")
        dist += (t1 - t0) * (v0 + v1) / 2 / 3.6
    if between_marks:
        gaps = sorted(t1 - t0 for (t0, _), (t1, _) in itertools.pairwise(samples))
        half = gaps[len(gaps) // 2] / 2
        dist += half * (samples[0][1] + samples[-1][1]) / 3.6
    return dist


def speed_correction(source: str, measured_m: float, integrated_m: float) -> SpeedCalibration:
    """Paper A drives 50 m against a tape; the factor corrects the source for slip/angle."""
    if measured_m < MIN_CAL_DISTANCE_M:
        raise CalibrationError(f"drive at least {MIN_CAL_DISTANCE_M:g} m (got {measured_m:g})")
    if integrated_m <= 0:
        raise CalibrationError(f"{source} reported no distance; was the source working?")
    factor = measured_m / integrated_m
    lo, hi = SPEED_FACTOR_RANGE
    if not lo <= factor <= hi:
        raise CalibrationError(
            f"{source}: correction {factor:.3f} is outside {lo}..{hi}; the source or the "
            "measured distance is wrong"
        )
    return SpeedCalibration(source, measured_m, integrated_m, factor)


@dataclass(frozen=True)
class TiltCalibration:
    mode: str  # "level_zero" (paper A) or "lowered_critical" (paper B)
    readings: tuple[float, ...]
    zero_offset_deg: float | None  # zeroed = raw - zero_offset_deg
    critical_angle_deg: float | None  # working below, raised above


def _readings(readings: Sequence[float], need: int) -> tuple[float, ...]:
    r = tuple(float(x) for x in readings)
    if len(r) < need:
        raise CalibrationError(f"need at least {need} readings, got {len(r)}")
    if not all(math.isfinite(x) and -180 <= x <= 180 for x in r):
        raise CalibrationError("readings must be angles in -180..180 degrees")
    if max(r) - min(r) > MAX_READING_SPREAD_DEG:
        raise CalibrationError(
            f"readings spread {max(r) - min(r):.2f}° > {MAX_READING_SPREAD_DEG}°: keep the "
            "machine still and repeat"
        )
    return r


def tilt_level_zero(readings: Sequence[float]) -> TiltCalibration:
    """Paper A: the machine stands on level ground; the mean reading becomes 0°."""
    r = _readings(readings, 1)
    return TiltCalibration("level_zero", r, sum(r) / len(r), None)


def tilt_lowered_critical(readings: Sequence[float]) -> TiltCalibration:
    """Paper B: implement lowered to the ground; mean of 3 readings is the critical angle."""
    r = _readings(readings, LOWERED_READINGS)
    return TiltCalibration("lowered_critical", r, None, sum(r) / len(r))


TILT_FIELDS = ("zero_offset_deg", "critical_angle_deg")


def save_tilt(store: CalibrationStore, key: str, result: TiltCalibration,
              **extra: Any) -> dict[str, Any]:
    """Save a zero or a critical angle without losing the other half of the sensor's record.

    Both live under one key (``tilt.<sensor>``); a level-ground zero after a lowered
    critical angle (or the HMI "zero" button) must not silently drop the critical angle back
    to the config value, nor the reverse. The saved entry carries both; ``undo`` restores the
    entry as it was before. Returns the entry saved.
    """
    entry = to_entry(result, **extra)
    prev = store.get(key)
    old = prev.get("result") if isinstance(prev, dict) else None
    if isinstance(old, dict):
        for name in TILT_FIELDS:
            if entry["result"].get(name) is None and old.get(name) is not None:
                entry["result"][name] = old[name]
    store.save(key, entry)
    return entry


# ---- persistence ---------------------------------------------------------------------------


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def to_entry(result: Any, **extra: Any) -> dict[str, Any]:
    """A JSON-ready record of a fit (dataclass) plus context such as channel or crop."""
    data = asdict(result) if hasattr(result, "__dataclass_fields__") else dict(result)
    return {"saved_at": _now(), **extra, "result": data}


def atomic_write_json(path: Path, doc: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2, sort_keys=True)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)  # make the rename itself durable
    finally:
        os.close(dir_fd)


class CalibrationStore:
    """``calibration.json``: current values by key plus an undo history."""

    def __init__(self, state_dir: str | os.PathLike[str]) -> None:
        self.path = Path(state_dir) / CALIBRATION_FILE

    def load(self) -> dict[str, Any]:
        if not self.path.exists():
            return {"version": FILE_VERSION, "current": {}, "history": []}
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise CalibrationError(
                f"{self.path}: unreadable ({exc}); move it aside to start afresh"
            ) from None
        if not isinstance(doc, dict) or not isinstance(doc.get("current"), dict) or (
            not isinstance(doc.get("history"), list)
        ):
            raise CalibrationError(f"{self.path}: not a sowgate calibration file")
        return doc

    def current(self) -> dict[str, Any]:
        cur: dict[str, Any] = self.load()["current"]
        return cur

    def get(self, key: str) -> dict[str, Any] | None:
        value: dict[str, Any] | None = self.current().get(key)
        return value

    def save(self, key: str, entry: dict[str, Any]) -> None:
        doc = self.load()
        doc["history"].append({"key": key, "previous": doc["current"].get(key),
                               "replaced_at": _now()})
        doc["history"] = doc["history"][-HISTORY_MAX:]
        doc["current"][key] = entry
        atomic_write_json(self.path, doc)

    def undo(self, key: str | None = None) -> tuple[str, dict[str, Any] | None]:
        """Restore the value replaced by the last save (of ``key`` if given)."""
        doc = self.load()
        hist = doc["history"]
        idx = next((i for i in range(len(hist) - 1, -1, -1)
                    if key is None or hist[i]["key"] == key), None)
        if idx is None:
            raise CalibrationError(f"nothing to undo{' for ' + key if key else ''}")
        item = hist.pop(idx)
        k, prev = item["key"], item["previous"]
        if prev is None:
            doc["current"].pop(k, None)
        else:
            doc["current"][k] = prev
        atomic_write_json(self.path, doc)
        return k, prev
