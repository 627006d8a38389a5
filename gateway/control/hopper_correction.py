"""Hopper scale → discharge correction: how far the drill's true discharge is off its model.

Paper A's chain is open loop (duty → shaft speed → discharge), so a drill whose discharge is
8 % above its fitted eq. (6) sows 8 % too much, for ever. A weight transmitter under the
hopper sees the truth: the mass that left. This module compares it with the mass the model
predicted, and gives the factor ``discharge_correction`` = true / model that the controller
divides its flow target by. Plain arithmetic on plain values: the controller feeds it one
sample per control tick, nothing here reads a clock, a device or a file.

The estimate
    Per sample: the hopper weight ``y`` (kg) and ``x``, the cumulative mass the *uncorrected*
    model predicted (kg, at the commanded duty). While the hopper is only emptied by the
    meter, ``y = a - k·x`` with ``k`` = true / model: a straight line whose slope is the
    factor. Using the uncorrected model keeps ``k`` independent of the correction applied.

    * Only samples taken while seeding steadily are fitted (``SteadyGate``: sowing, the
      motor following the speed, past the start-up, speed steady); standing, turning and
      start-ups are left out. ``x`` keeps counting through them, and the line goes on
      across a headland, because the model predicts no discharge when the motor is off and
      the meter's lag makes a start-up differ from the model by only grams.
    * Samples are fitted in windows of ``window_s`` of steady seeding. Each window is first
      fitted alone, by least squares iterated with outliers (beyond 3.5 robust σ of the
      residuals, σ from the median absolute deviation) dropped: a knock on the load cells
      does not pull the line. Its inliers then join the evidence.
    * A silence of the scale (no usable reading for ``SILENCE_END_LINE_S``) ends the line:
      nothing learnt across it, the factor frozen until a full window after it.
    * A refill (the weight jumping up, or any jump: the median of the last readings against
      the median of the ones before, beyond ``max(REFILL_MIN_KG, 5 σ)``) ends the line: the
      window in progress is dropped and a new line (own intercept ``a``) starts. A jump down
      is counted apart (``jumps``): no meter empties kilograms in seconds, so it is a load
      cell shifting or failing, never evidence. So does
      motor running that the model does not describe (emptying).
    * Evidence is pooled across windows and lines as one weighted least-squares slope with a
      separate intercept per line (the sums of each line, centred, added), with exponential
      forgetting (time constant ``FORGET_S``): recursive least squares with forgetting, so a
      seed lot that drifts is followed, about 2 × ``FORGET_S`` behind (a shorter memory
      follows faster and is noisier: the standard error grows as memory^-1.5). One slope
      over a long line is worth far more than the mean of short windows: its standard
      error falls as T^-1.5 (the spread of ``x`` grows with T), a mean of window slopes
      only as T^-0.5.

Honest confidence under correlated disturbances
    ``σ / sqrt(Sxx)`` (σ the scale's noise estimated from the residuals, Sxx the spread of
    ``x`` pooled) is the slope's standard error only if each reading's error is independent.
    On a moving seeder it is not: the frame rocks over seconds, slopes tilt the hopper on its
    cells for tens of seconds, load cells drift with temperature. Then the residuals of a
    line look like σ but the slope errs far more. Each closed window's own slope is compared
    with the pooled slope before it: ``z = (k_w - k) / sqrt(SE_w² + SE²)`` averages z² = 1
    under independent noise; the mean z² (the dispersion, forgotten like the evidence, with
    ``DISPERSION_PRIOR_N`` windows of 1 assumed) inflates the standard error by its square
    root (batch means). Correlations as long as a window are seen only in part: at 1.5 kg
    correlated over 10 s (plus 2 kg independent) ±1.96 SE covers the true error in about
    95 % of runs after 20 minutes, over 60 s in about 80 % (tests/gateway/control/
    test_hopper_correction.py; ``benchmarks/bench_rate.py``'s sensitivity rows).

How much evidence before it is applied
    The standard error of ``k`` is ``σ / sqrt(Sxx)`` times the square root of the dispersion
    (and the t over normal quantile of the windows compared: ±1.96 SE is a 95 % interval).
    Under independent noise: one 120 s window alone at σ 2 kg on wheat
    (about 3 kg/min, 3 readings/s) has an SE of about 6 %: useless on its own. Nothing is
    applied until the SE is below ``APPLY_MAX_SE`` (3 %: about 3 minutes of continuous
    wheat seeding at σ 2 kg and 3 Hz, 20 s at σ 0.2 kg); from then on the applied factor is
    the estimate shrunk towards 1 by its confidence (the posterior mean with a prior of
    σ ``PRIOR_SIGMA`` = 5 %, the spread of drills and seed lots in the field): at SE 3 % it
    moves 74 % of the way, at 1 % 96 % (about 10 minutes of continuous wheat at σ 2 kg and
    3 Hz give an SE of 0.8 %), at 0.3 % (20 minutes) 99.6 %. Clamped to
    1 ± ``max_correction_pct``.
    An estimate further from 1 than the prior's 5 % is its own prior spread (a drill 26 % off
    is corrected fully once the SE allows, not shrunk towards the 5 % of typical drills).
    An estimate beyond the clamp by ``OUT_OF_RANGE_SES`` standard errors is flagged
    ``out_of_range`` (alarm ``hopper_scale.out_of_range``), applied yet or not: the drill
    then sows off target by what the clamp leaves, and only a rotation test (or a check of
    the drill) brings it back.

    Rapeseed (a few hundred g/min) moves 2–5 kg in 10 minutes: at σ 2 kg the SE stays above
    3 % for tens of minutes, so a hopper scale rarely corrects rapeseed, and says so with
    its SE; rotation tests calibrate it.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, field

APPLY_MAX_SE = 0.03  # the pooled estimate is applied once its standard error is below this
PRIOR_SIGMA = 0.05  # spread of true/model over drills and seed lots (the shrinkage prior)
FORGET_S = 900.0  # evidence older than this weighs e^-1 (follows a drifting seed lot)
OUTLIER_SIGMAS = 3.5  # a reading this many robust σ off its window's line is dropped
ROBUST_ITERATIONS = 3
# windows agreeing with independent noise assumed before any is seen (the dispersion's prior)
DISPERSION_PRIOR_N = 1.0
DISPERSION_Z2_MAX = 100.0  # one wild window (a fault) does not inflate the SE for ever
MIN_WINDOW_SAMPLES = 10  # a window with fewer inliers adds nothing
JUMP_MEDIAN_N = 10  # readings in each median of the jump (refill) detector: a knock of a
# few readings does not move a median of 10, a refill (a step that stays) does
REFILL_MIN_KG = 10.0  # no jump below this counts as a refill, whatever the noise
JUMP_SIGMAS = 5.0  # ... nor below this many σ of the difference of the two medians
DEFAULT_SIGMA_KG = 2.0  # the noise assumed until the residuals give it
# The estimate is "outside the correction range" (alarm hopper_scale.out_of_range) once it is
# beyond 1 ± max_correction by this many standard errors, applied or not yet: a drill 26 %
# off its model is known to be off minutes before its SE reaches APPLY_MAX_SE, and sows
# uncorrected (or held at the bound) all that time.
OUT_OF_RANGE_SES = 2.0
# No usable reading for this long (the scale silent, or every reading rejected: the device is
# alarmed after 2 s) ends the line like a refill: the factor stays frozen through the silence
# and until a whole window of steady seeding after it. A window fitted across the gap joined
# readings from before and after a transmitter that may have restarted (re-tared) or drifted
# unseen, and moved the correction 0.0045 in the fault matrix's hopper_scale_silent row.
SILENCE_END_LINE_S = 2.0
STEADY_AFTER_S = 5.0  # seeding this long before samples count (start-up, speed filter)
STEADY_SPEED_SPAN = 0.10  # filtered speed within ±10 % over STEADY_SPEED_S
STEADY_SPEED_S = 3.0


@dataclass
class LineSums:
    """Weighted sums of one line's samples (``y = a - k·x``), forgetting applied."""

    w: float = 0.0
    sx: float = 0.0
    sy: float = 0.0
    sxx: float = 0.0
    sxy: float = 0.0
    syy: float = 0.0

    def add(self, x: float, y: float) -> None:
        self.w += 1.0
        self.sx += x
        self.sy += y
        self.sxx += x * x
        self.sxy += x * y
        self.syy += y * y

    def scale(self, factor: float) -> None:
        self.w *= factor
        self.sx *= factor
        self.sy *= factor
        self.sxx *= factor
        self.sxy *= factor
        self.syy *= factor

    def centred(self) -> Evidence:
        if self.w <= 0.0:
            return Evidence()
        return Evidence(
            cxx=max(0.0, self.sxx - self.sx * self.sx / self.w),
            cxy=self.sxy - self.sx * self.sy / self.w,
            cyy=max(0.0, self.syy - self.sy * self.sy / self.w),
            w=self.w,
            lines=1.0,
        )


@dataclass
class Evidence:
    """Centred sums of one or more lines, each with its own intercept: what the slope needs.

    Adding two is pooling them; scaling is forgetting. Kept across restarts (to_dict)."""

    cxx: float = 0.0
    cxy: float = 0.0
    cyy: float = 0.0
    w: float = 0.0
    lines: float = 0.0
    # each window's slope against the pooled one before it, in units of their claimed
    # standard errors: the sum of the squares and how many (the dispersion, see below)
    zz: float = 0.0
    zn: float = 0.0

    def __add__(self, other: Evidence) -> Evidence:
        return Evidence(self.cxx + other.cxx, self.cxy + other.cxy, self.cyy + other.cyy,
                        self.w + other.w, self.lines + other.lines, self.zz + other.zz,
                        self.zn + other.zn)

    def scaled(self, factor: float) -> Evidence:
        return Evidence(self.cxx * factor, self.cxy * factor, self.cyy * factor,
                        self.w * factor, self.lines * factor, self.zz * factor,
                        self.zn * factor)

    def slope(self) -> float | None:
        """``k`` (true / model), None without spread in ``x``."""
        return None if self.cxx <= 1e-12 else -self.cxy / self.cxx

    def sigma(self) -> float | None:
        """The scale's noise from the residuals, None with too few samples."""
        dof = self.w - self.lines - 1.0
        if self.cxx <= 1e-12 or dof < 2.0:
            return None
        rss = max(0.0, self.cyy - self.cxy * self.cxy / self.cxx)
        return math.sqrt(rss / dof)

    def white_standard_error(self) -> float | None:
        """The slope's standard error if the readings' errors were independent."""
        s = self.sigma()
        return None if s is None else s / math.sqrt(self.cxx)

    def dispersion(self) -> float:
        """How much more the window slopes scatter than their independent-noise standard
        errors claim (batch means): 1 for independent noise, more when the disturbances are
        correlated over seconds to minutes (the frame rocking, slopes, drift) or the true
        factor moves. ``DISPERSION_PRIOR_N`` windows agreeing are assumed before any is seen;
        never below 1 (too few windows cannot show the noise is better than independent)."""
        return max(1.0, (DISPERSION_PRIOR_N + self.zz) / (DISPERSION_PRIOR_N + self.zn))

    def standard_error(self) -> float | None:
        """The honest standard error: the independent-noise one inflated by the dispersion,
        and by the Student t quantile of the windows compared over the normal one (the
        dispersion is itself estimated from few windows), so that ±1.96 of it is a 95 %
        interval."""
        se = self.white_standard_error()
        if se is None:
            return None
        return se * math.sqrt(self.dispersion()) * t_over_normal(DISPERSION_PRIOR_N + self.zn)

    def to_dict(self) -> dict[str, float]:
        return {"cxx": self.cxx, "cxy": self.cxy, "cyy": self.cyy, "w": self.w,
                "lines": self.lines, "zz": self.zz, "zn": self.zn}

    @classmethod
    def from_dict(cls, data: dict[str, float]) -> Evidence:
        ev = cls(*(float(data[k]) for k in ("cxx", "cxy", "cyy", "w", "lines")),
                 *(float(data.get(k, 0.0)) for k in ("zz", "zn")))  # older files: none
        if (not all(math.isfinite(v) for v in ev.to_dict().values()) or ev.cxx < 0 or ev.w < 0
                or ev.zz < 0 or ev.zn < 0):
            raise ValueError("hopper evidence holds non-finite or negative sums")
        return ev


def t_over_normal(dof: float) -> float:
    """Student t's two-sided 95 % quantile over the normal's (1.96) at ``dof`` degrees of
    freedom (Cornish–Fisher to 1/dof², within 3 % from 2 dof; capped at 1 dof's 6.5)."""
    if dof <= 1.0:
        return 12.71 / 1.96
    z = 1.959964
    t = z + (z**3 + z) / (4 * dof) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * dof**2)
    return min(12.71, t) / z


@dataclass(frozen=True)
class WindowFit:
    """One window fitted alone (outliers dropped): its own slope and standard error."""

    factor: float
    standard_error: float
    sigma_kg: float
    inliers: list[tuple[float, float]]
    dropped: int


def robust_line(points: list[tuple[float, float]]) -> WindowFit | None:
    """Least squares ``y = a - k·x`` iterated with outliers dropped; None if it cannot fit."""
    kept = list(points)
    dropped = 0
    for _ in range(ROBUST_ITERATIONS + 1):
        sums = LineSums()
        for x, y in kept:
            sums.add(x, y)
        ev = sums.centred()
        k = ev.slope()
        if k is None or len(kept) < MIN_WINDOW_SAMPLES:
            return None
        mx, my = sums.sx / sums.w, sums.sy / sums.w
        resid = [y - (my - k * (x - mx)) for x, y in kept]
        mad = statistics.median(abs(r) for r in resid)
        robust_sigma = max(1.4826 * mad, 1e-6)
        keep = [p for p, r in zip(kept, resid, strict=True)
                if abs(r) <= OUTLIER_SIGMAS * robust_sigma]
        if len(keep) == len(kept):
            break
        dropped += len(kept) - len(keep)
        kept = keep
    se = ev.white_standard_error()  # one window: its own residuals, no dispersion yet
    sigma = ev.sigma()
    if k is None or se is None or sigma is None:
        return None
    return WindowFit(k, se, sigma, kept, dropped)


@dataclass
class SteadyGate:
    """Whether the drill is seeding steadily: sowing with the motor following the speed, for
    ``STEADY_AFTER_S`` already (start-up and the speed filter settled), speed within
    ±``STEADY_SPEED_SPAN`` over the last ``STEADY_SPEED_S``."""

    since: float | None = None
    speeds: deque[tuple[float, float]] = field(default_factory=deque)

    def update(self, t: float, seeding: bool, speed_kmh: float | None) -> bool:
        if not seeding or speed_kmh is None or speed_kmh <= 0.0:
            self.since = None
            self.speeds.clear()
            return False
        if self.since is None:
            self.since = t
        self.speeds.append((t, speed_kmh))
        while self.speeds and t - self.speeds[0][0] > STEADY_SPEED_S:
            self.speeds.popleft()
        if t - self.since < STEADY_AFTER_S:
            return False
        lo = min(v for _, v in self.speeds)
        hi = max(v for _, v in self.speeds)
        return hi - lo <= 2.0 * STEADY_SPEED_SPAN * speed_kmh


@dataclass(frozen=True)
class CorrectionState:
    """What the estimator says now (published, logged, persisted)."""

    factor: float  # applied: true / model, 1.0 until the evidence is enough
    estimate: float | None  # the pooled estimate before shrinkage and clamp
    standard_error: float | None  # of the estimate
    sigma_kg: float | None  # the scale noise the residuals show
    at_bound: bool  # the estimate is beyond 1 ± max_correction and the factor held there
    applied: bool  # the evidence was enough to apply
    windows: int  # windows that added evidence since the start (or the reset)
    refills: int  # upward jumps (refills) seen
    last_window: WindowFit | None  # the newest window, fitted alone (for disagreement)
    dispersion: float = 1.0  # the SE's inflation² for correlated noise (1: independent)
    jumps: int = 0  # downward jumps: a load cell, not seed (the line restarts, nothing fitted)
    # the estimate is beyond 1 ± max_correction by OUT_OF_RANGE_SES standard errors (applied
    # or not yet): the drill sows ``residual_pct`` off target and the correction cannot reach
    out_of_range: bool = False
    residual_pct: float = 0.0  # estimate / applied factor - 1, in % (when out of range)


class HopperCorrection:
    """The estimator: feed ``add`` one sample per control tick; read ``state``.

    ``evidence`` and ``factor`` restore what a previous run learnt for the same calibration
    identity (see ``gateway.control.hopper_store``).
    """

    def __init__(self, *, window_s: float, max_correction_pct: float,
                 evidence: Evidence | None = None, factor: float = 1.0,
                 forget_s: float = FORGET_S) -> None:
        if window_s <= 0 or max_correction_pct <= 0 or forget_s <= 0:
            raise ValueError("window_s, max_correction_pct and forget_s must be positive")
        self.window_s = window_s
        self.bound = max_correction_pct / 100.0
        self.forget_s = forget_s
        self.closed = evidence or Evidence()  # lines that have ended (and restored evidence)
        self.line = LineSums()  # the current line
        self.factor = self._clamp(factor)
        self._window: list[tuple[float, float]] = []
        self._window_steady_s = 0.0
        self._last_t: float | None = None
        self._last_steady = False
        self._recent: deque[float] = deque(maxlen=2 * JUMP_MEDIAN_N)
        self._sigma = DEFAULT_SIGMA_KG
        self.windows = 0
        self.refills = 0
        self.jumps = 0  # downward jumps: implausible (a load cell, not seed)
        self.silences = 0  # lines ended by the scale going silent (SILENCE_END_LINE_S)
        self._last_reading_t: float | None = None
        self.last_jump_kg = 0.0
        self.last_window: WindowFit | None = None
        self._update_factor()

    # ---- feeding ---------------------------------------------------------------------------
    def add(self, t: float, weight_kg: float | None, model_kg: float, *, steady: bool,
            modelled: bool = True) -> bool:
        """One sample: hopper weight (None: no reading this tick), the cumulative mass the
        uncorrected model predicted, whether the drill seeds steadily, and whether every
        discharge since the last sample is in the model (False: emptying). True when a window
        was just pooled (the factor may have changed)."""
        dt = 0.0 if self._last_t is None else max(0.0, t - self._last_t)
        self._last_t = t
        if not modelled:
            self._end_line()
            return False
        if weight_kg is None or not math.isfinite(weight_kg):
            self._last_steady = False
            return False
        silent_s = None if self._last_reading_t is None else t - self._last_reading_t
        self._last_reading_t = t
        if silent_s is not None and silent_s > SILENCE_END_LINE_S:
            self.silences += 1
            self._end_line()  # frozen: the window across the silence is not fitted
        jump = self._jump(weight_kg)
        if jump is not None:
            if jump > 0:
                self.refills += 1
            else:  # seed does not leave this fast: a load cell, not the meter
                self.jumps += 1
                self.last_jump_kg = jump
            self._end_line()
            self._recent.append(weight_kg)
            return False
        self._recent.append(weight_kg)
        if not steady:
            self._last_steady = False
            return False
        if self._last_steady:
            self._window_steady_s += dt
        self._last_steady = True
        self._window.append((model_kg, weight_kg))
        if self._window_steady_s >= self.window_s:
            return self._close_window()
        return False

    def _jump(self, weight_kg: float) -> float | None:
        """The step (kg, + up) when the weight just jumped, else None."""
        recent = list(self._recent)
        if len(recent) < 2 * JUMP_MEDIAN_N - 1:
            return None
        before = statistics.median(recent[: JUMP_MEDIAN_N])
        after = statistics.median([*recent[JUMP_MEDIAN_N:], weight_kg])
        sigma_diff = 1.25 * self._sigma * math.sqrt(2.0 / JUMP_MEDIAN_N)
        step = after - before
        return step if abs(step) > max(REFILL_MIN_KG, JUMP_SIGMAS * sigma_diff) else None

    def _end_line(self) -> None:
        """A refill or unmodelled discharge: the window in progress is dropped (it may hold
        the jump), the current line's evidence is kept, a new line starts."""
        self.closed = self.closed + self.line.centred()
        self.line = LineSums()
        self._window = []
        self._window_steady_s = 0.0
        self._recent.clear()
        self._last_steady = False

    def _close_window(self) -> bool:
        points, self._window = self._window, []
        duration, self._window_steady_s = self._window_steady_s, 0.0
        fit = robust_line(points)
        if fit is None:
            return False
        self.last_window = fit
        self._sigma = fit.sigma_kg
        before = self.evidence()
        k_before, se_before = before.slope(), before.white_standard_error()
        forget = math.exp(-duration / self.forget_s)
        self.closed = self.closed.scaled(forget)
        if k_before is not None and se_before is not None:
            # this window alone against the pooled evidence before it: independent under
            # independent noise, so z² averages 1 there, more under correlated noise
            z2 = (fit.factor - k_before) ** 2 / (fit.standard_error**2 + se_before**2)
            self.closed = self.closed + Evidence(zz=min(z2, DISPERSION_Z2_MAX), zn=1.0)
        self.line.scale(forget)
        for x, y in fit.inliers:
            self.line.add(x, y)
        self.windows += 1
        self._update_factor()
        return True

    # ---- the factor ----------------------------------------------------------------------------
    def evidence(self) -> Evidence:
        return self.closed + self.line.centred()

    def _clamp(self, k: float) -> float:
        return min(1.0 + self.bound, max(1.0 - self.bound, k))

    def _update_factor(self) -> None:
        ev = self.evidence()
        k, se = ev.slope(), ev.standard_error()
        if k is None or se is None or se > APPLY_MAX_SE:
            return  # not enough evidence: the factor stays (1.0, or what was restored)
        # the prior's spread is PRIOR_SIGMA, or the offset found when that is larger: a drill
        # found 26 % off (many SE away from 1) is corrected fully, not shrunk as if drills
        # spread only 5 % (which left it ~7 % short at SE 3 %)
        prior_var = max(PRIOR_SIGMA**2, (k - 1.0) ** 2)
        weight = prior_var / (prior_var + se**2)
        self.factor = self._clamp(1.0 + (k - 1.0) * weight)

    def state(self) -> CorrectionState:
        ev = self.evidence()
        k, se = ev.slope(), ev.standard_error()
        applied = k is not None and se is not None and se <= APPLY_MAX_SE
        at_bound = applied and k is not None and abs(k - 1.0) >= self.bound
        out = (k is not None and se is not None
               and abs(k - 1.0) - OUT_OF_RANGE_SES * se > self.bound)
        residual = (k / self.factor - 1.0) if out and k is not None else 0.0
        return CorrectionState(
            factor=self.factor, estimate=k, standard_error=se, sigma_kg=ev.sigma(),
            at_bound=at_bound, applied=applied, windows=self.windows, refills=self.refills,
            last_window=self.last_window, dispersion=ev.dispersion(), jumps=self.jumps,
            out_of_range=out, residual_pct=residual * 100.0,
        )

    def disagreement(self, disagree_pct: float) -> float | None:
        """The newest window's own factor minus the applied one, when that is beyond both
        ``disagree_pct`` and 3 of the window's standard errors (a blocked outlet, a bridged
        hopper, a load cell fault: not noise); else None."""
        w = self.last_window
        if w is None:
            return None
        diff = w.factor - self.factor
        if abs(diff) > max(disagree_pct / 100.0, 3.0 * w.standard_error):
            return diff
        return None


def time_to_empty_min(mass_kg: float | None, flow_g_min: float) -> float | None:
    """Minutes until the hopper is empty at ``flow_g_min`` (None when not emptying)."""
    if mass_kg is None or flow_g_min <= 0.0:
        return None
    return max(0.0, mass_kg) * 1000.0 / flow_g_min
