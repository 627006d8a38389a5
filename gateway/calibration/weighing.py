"""What the rotation test's scale can tell, and how long the runs must be for it (issue 25 §3).

A rotation test's catch is weighed once per run on a scale of stated error ±σ (one standard
deviation). That error is per weighing: it does not shrink with the run, so a set point's
relative uncertainty is σ / catch, and over ``n`` runs of the same set point σ / (catch · √n).
A run twice as long halves it; twice the runs only divide it by √2 — longer runs, not more of
them, are what a small catch needs (rapeseed: 25–150 g in 60 s on a ±2 g scale, 1.5–8 % a
weighing; ``benchmarks/bench_rate.py``: 3 × 60 s leaves rapeseed at ~1.7 % rate error p90,
3 × 180 s at ~0.6 %).

``weighing_advice`` works from the numbers in front of the CLI (set points, weighed masses, run
lengths, one per set point if need be, the scale's σ) and from nothing about the drill: for
each set point its uncertainty and the run length (at the same number of runs) that brings it
to ``SET_POINT_SE_LIMIT_PCT`` at p90, or the scale that would do at the current length. It advises,
it never refuses: the readings can be consistent and still too small for the rate wanted.

``unexplained_scatter`` is the other question: repeats of a set point that disagree by more
than the scale explains are not weighing noise (timing, a bridging hopper, a leak): those set
points are to be repeated, whatever the scale.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass

from gateway.calibration.fits import SET_POINT_SE_LIMIT_PCT, by_set_point

# paper A weighs each catch on a scale of ±2 g (taken as one standard deviation)
DEFAULT_SCALE_G = 2.0
# advised run lengths are rounded up to this (a stopwatch figure a farmer can keep)
ROUND_SECONDS = 30.0
# scales one can buy: the advice names the coarsest of these that would do
SCALE_STEPS_G = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0)
# repeats whose scatter is beyond this many times what the scale explains are not weighing
# noise. With 3 runs the sample SD's square is σ²·χ²₂/2: P(> 2² times) = e⁻⁴ ≈ 2 % per set
# point when the scale is all there is.
SCATTER_FACTOR = 2.0
# a set point's mean is to be within the target at p90, not at one σ: its standard error at
# most target / 1.645. Once each set point runs only as long as it needs (issue 25 §3, runs
# per set point) there is no longer the longest run's margin on the others: at one σ =
# 1 %, bench_rate's rapeseed came out at 1.05 % p90 rate error
P90_Z = 1.645
# a rotation test whose runs take longer than this end to end is not one a farmer runs before
# sowing (a kitchen scale of ±5–10 g on rapeseed asks for 2–4 h): past it the advice says so
# and names the finer scale that brings the test under it
PRACTICAL_TEST_S = 2 * 3600.0
# paper A's runs per set point: what a run length is worked out for before any is weighed
# (the touchscreen's test, where each run is timed by the daemon)
PAPER_A_REPEATS = 3


def run_seconds_needed(catch_g_per_s: float, scale_g: float, runs: int,
                       target_pct: float = SET_POINT_SE_LIMIT_PCT) -> float:
    """The run length (rounded up to ``ROUND_SECONDS``) at which ``runs`` weighings of a set
    point catching ``catch_g_per_s`` on a ±``scale_g`` scale give its mean within
    ``target_pct`` at p90: σ / (catch · √runs) ≤ target / 1.645. The one formula of the CLI's
    advice and of the touchscreen's run lengths."""
    if not (catch_g_per_s > 0 and scale_g > 0 and runs > 0 and target_pct > 0):
        raise ValueError("catch, scale σ, runs and target must be positive")
    return _round_up(scale_g * 100.0 * P90_Z / (catch_g_per_s * target_pct * math.sqrt(runs)))


def remaining_run_seconds(catch_g_per_s: float, scale_g: float, runs: int,
                          done_s: Sequence[float] = (),
                          target_pct: float = SET_POINT_SE_LIMIT_PCT) -> float:
    """The length of each run of a set point still to come, when ``done_s`` of its ``runs``
    are run: what brings the set point's mean catch (the catches over the mean length, as
    ``weighing_advice`` judges it) to ``run_seconds_needed``. Runs already made shorter than
    that are made up by longer ones (rounded up; never shorter than 0)."""
    left = runs - len(done_s)
    if left <= 0:
        raise ValueError(f"{len(done_s)} runs done of {runs}: none left")
    mean = run_seconds_needed(catch_g_per_s, scale_g, runs, target_pct)
    return _round_up(max(0.0, (runs * mean - sum(done_s)) / left))


def scale_for_seconds(catch_g_per_s: float, seconds: float, runs: int,
                      target_pct: float = SET_POINT_SE_LIMIT_PCT) -> float:
    """The coarsest usual scale (``SCALE_STEPS_G``) with which runs of ``seconds`` do."""
    se = 100.0 / (catch_g_per_s * seconds * math.sqrt(runs))  # per gram of scale σ
    return _scale_for(1.0, se, target_pct / P90_Z)


def duration(seconds: float) -> str:
    """A test's length as a farmer reads it: '45 min', '4 h 18 min'."""
    minutes = math.ceil(seconds / 60.0 - 1e-9)
    if minutes < 60:
        return f"{minutes} min"
    return f"{minutes // 60} h" + (f" {minutes % 60:02d} min" if minutes % 60 else "")


@dataclass(frozen=True)
class SetPointWeighing:
    """One set point's weighing: its catches, their uncertainty, the run that would do."""

    set_point: float
    runs: int
    mean_mass_g: float  # mean catch per run (what was on the scale)
    per_weighing_pct: float  # σ / catch
    se_pct: float  # of its mean over its runs: per_weighing_pct / √runs
    seconds_needed: float  # run length for se_pct <= the target at the same runs (rounded up)
    scale_needed_g: float  # the coarsest usual scale that would do at the current length
    seconds: float  # its runs' length (their mean, were they of different lengths)


@dataclass(frozen=True)
class WeighingAdvice:
    scale_g: float
    seconds: float  # the longest run of the test (its only length when all are one)
    target_pct: float
    set_points: tuple[SetPointWeighing, ...]
    # each set point's run length, in the order the test ran them (first run of each)
    lengths: tuple[tuple[float, float], ...] = ()
    counts: tuple[int, ...] = ()  # runs per set point, in the order of ``lengths``

    @property
    def limit_pct(self) -> float:
        """The standard error a set point's mean may have: the target at p90."""
        return self.target_pct / P90_Z

    @property
    def short(self) -> tuple[SetPointWeighing, ...]:
        """The set points whose runs were too short for the target on this scale."""
        return tuple(p for p in self.set_points if p.se_pct > self.limit_pct * (1 + 1e-9))

    @property
    def advised_by_set_point(self) -> tuple[tuple[float, float], ...]:
        """Each set point with the run length that brings it to the target (its current one
        when it already does), in the test's order: what ``--seconds`` is to say."""
        need = {p.set_point: p.seconds_needed for p in self.set_points}
        return tuple((k, need.get(k, t)) for k, t in self.lengths)

    @property
    def advised_seconds(self) -> float:
        """The longest run length advised (every set point within the target at it; the
        current length when the test already does)."""
        return max([t for _, t in self.advised_by_set_point] or [self.seconds])

    @property
    def seconds_option(self) -> str:
        """The ``--seconds`` value for the advised test: one length when all set points
        take the same, else one per set point in the order of the test's set points."""
        ts = [t for _, t in self.advised_by_set_point]
        if len(set(ts)) <= 1:
            return f"{self.advised_seconds:g}"
        return ",".join(f"{t:g}" for t in ts)

    def test_seconds(self, scale_g: float | None = None) -> float:
        """The advised test end to end (every run of every set point at its advised length,
        as many runs as now) on this scale, or on a ±``scale_g`` one: the catches stay, the
        scale's error per weighing scales with it; no set point runs shorter than now."""
        ratio = 1.0 if scale_g is None else scale_g / self.scale_g
        points = {p.set_point: p for p in self.set_points}
        total = 0.0
        for (k, t), n in zip(self.lengths, self.counts, strict=True):
            p = points.get(k)
            need = t
            if p is not None and p.se_pct * ratio > self.limit_pct * (1 + 1e-9):
                need = max(t, run_seconds_needed(p.mean_mass_g / p.seconds, self.scale_g * ratio,
                                                 p.runs, self.target_pct))
            total += n * need
        return total

    @property
    def impractical(self) -> bool:
        """The advised test runs longer than ``PRACTICAL_TEST_S`` end to end."""
        return bool(self.short) and self.test_seconds() > PRACTICAL_TEST_S

    @property
    def practical_scale_g(self) -> float:
        """The coarsest usual scale finer than this one whose advised test takes at most
        ``PRACTICAL_TEST_S`` (the finest usual scale when none does)."""
        finer = [s for s in SCALE_STEPS_G if s < self.scale_g * (1 - 1e-9)]
        for s in reversed(finer):
            if self.test_seconds(s) <= PRACTICAL_TEST_S:
                return s
        return SCALE_STEPS_G[0]

    def practical_note(self, what: str) -> str | None:
        """When the advised test is impractical, that said plainly with the finer scales
        that bring it back: the one for a test under ``PRACTICAL_TEST_S`` and the one with
        which the runs as made already do. ``None`` when the test is practical."""
        if not self.impractical:
            return None
        runs = sum(self.counts)
        fine = self.practical_scale_g
        as_made = min(p.scale_needed_g for p in self.short)
        masses = [p.mean_mass_g for p in self.set_points]
        lengths = sorted({t for _, t in self.lengths})
        made = (f"{lengths[0]:g} s" if len(lengths) == 1
                else f"{lengths[0]:g}–{lengths[-1]:g} s")
        return (
            f"{what}: the advised test runs {duration(self.test_seconds())} end to end "
            f"({runs} runs) on a ±{self.scale_g:g} g scale, more than "
            f"{duration(PRACTICAL_TEST_S)}: not practical. Catches of {min(masses):.3g}–"
            f"{max(masses):.3g} g need a finer scale: on a ±{fine:g} g scale the advised "
            f"test takes {duration(self.test_seconds(fine))}; on a ±{as_made:g} g scale the "
            f"runs as made ({made}) do")

    def messages(self, what: str, label: str = "{:g}") -> list[str]:
        """The advice as sentences, one per short set point, then what to do.

        ``what``: the channel or crop (``rapeseed``); ``label``: how a set point is said
        (``"{:g} % duty"``)."""
        short = self.short
        if not short:
            return []
        out = []
        for p in short:
            over = (f" (±{p.se_pct:.1f} % over its {p.runs} runs)" if p.runs > 1 else "")
            out.append(
                f"{what} at {label.format(p.set_point)}: {p.mean_mass_g:.3g} g in "
                f"{p.seconds:g} s on a ±{self.scale_g:g} g scale is "
                f"±{p.per_weighing_pct:.1f} %{over}; run this set point for at least "
                f"{p.seconds_needed:g} s (or weigh on a ±{p.scale_needed_g:g} g scale)")
        names = ", ".join(label.format(p.set_point) for p in short)
        option = self.seconds_option
        how = ("one length per set point, in the order of the set points; only " + names +
               " longer" if "," in option else "the longest needed above, for " + names)
        out.append(
            f"each set point's mean is to be within ±{self.target_pct:g} % (p90; ±"
            f"{self.limit_pct:.2g} % one σ) for the rate to land within 1 %: run the test "
            f"again with --seconds {option} "
            f"({how}; as many runs per set point as now). "
            "Longer runs, not more of them: the scale's error is per weighing, so a run twice "
            "as long halves it and twice the runs only divide it by 1.4")
        return out

    def to_entry(self) -> dict[str, object]:
        """What calibration.json keeps of it (so a later look, or a script, knows what was
        advised). ``seconds`` and ``advised_seconds`` are the longest run (as before runs
        could differ by set point); the ``*_by_set_point`` lists are [set point, seconds]
        pairs in the test's order."""
        return {"scale_g": self.scale_g, "seconds": self.seconds,
                "target_pct": self.target_pct, "advised_seconds": self.advised_seconds,
                "seconds_by_set_point": [[k, t] for k, t in self.lengths],
                "advised_seconds_by_set_point": [[k, t] for k, t in self.advised_by_set_point],
                "advised_seconds_option": self.seconds_option,
                "advised_test_s": self.test_seconds(),
                "impractical": self.impractical,
                "short_set_points": [p.set_point for p in self.short],
                "se_pct": {f"{p.set_point:g}": round(p.se_pct, 3) for p in self.set_points}}


def _round_up(seconds: float) -> float:
    return ROUND_SECONDS * math.ceil(seconds / ROUND_SECONDS - 1e-9)


def _scale_for(scale_g: float, se_pct: float, target_pct: float) -> float:
    need = scale_g * target_pct / se_pct
    fit = [s for s in SCALE_STEPS_G if s <= need * (1 + 1e-9)]
    return fit[-1] if fit else SCALE_STEPS_G[0]


def weighing_advice(set_points: Sequence[float], masses_g: Sequence[float],
                    seconds: float | Sequence[float],
                    scale_g: float = DEFAULT_SCALE_G,
                    target_pct: float = SET_POINT_SE_LIMIT_PCT) -> WeighingAdvice:
    """Each set point's relative weighing uncertainty from the scale's σ and its catches,
    and the run length that brings it to ``target_pct`` (see the module docstring).

    ``masses_g``: what was on the scale for each run (in run order, ``set_points`` giving
    each run's set point); ``seconds``: the runs' length, one for all or one per run."""
    if len(set_points) != len(masses_g):
        raise ValueError(f"{len(set_points)} set points for {len(masses_g)} masses")
    lengths = ([float(seconds)] * len(set_points) if isinstance(seconds, (int, float))
               else [float(t) for t in seconds])
    if len(lengths) != len(set_points):
        raise ValueError(f"{len(lengths)} run lengths for {len(set_points)} runs")
    if not (scale_g > 0 and target_pct > 0 and all(t > 0 for t in lengths)
            and (not isinstance(seconds, (int, float)) or seconds > 0)):
        raise ValueError("scale σ, run length and target must be positive")
    by_key = by_set_point(set_points, [(float(m), t) for m, t in zip(masses_g, lengths,
                                                                    strict=True)])
    points = []
    for k, mts in sorted(by_key.items()):
        mean = statistics.fmean(m for m, _ in mts)
        length = statistics.fmean(t for _, t in mts)
        if mean <= 0:  # nothing caught: no uncertainty to speak of, the fit says the rest
            continue
        per = scale_g / mean * 100.0
        se = per / math.sqrt(len(mts))
        # the catch grows with the run, the scale's error does not: se ∝ 1 / seconds
        limit = target_pct / P90_Z
        needed = (run_seconds_needed(mean / length, scale_g, len(mts), target_pct)
                  if se > limit * (1 + 1e-9) else length)
        points.append(SetPointWeighing(k, len(mts), mean, per, se, needed,
                                       _scale_for(scale_g, se, limit), length))
    order = tuple((k, statistics.fmean(t for _, t in mts)) for k, mts in by_key.items())
    counts = tuple(len(mts) for mts in by_key.values())
    return WeighingAdvice(scale_g, max(lengths, default=0.0), target_pct, tuple(points), order,
                          counts)


@dataclass(frozen=True)
class ScatteredSetPoint:
    set_point: float
    runs: int
    scatter_pct: float  # the runs' own SD, % of their mean
    scale_pct: float  # what the scale explains of it (σ / mean catch), %


def unexplained_scatter(set_points: Sequence[float], masses_g: Sequence[float],
                        scale_g: float = DEFAULT_SCALE_G,
                        target_pct: float = SET_POINT_SE_LIMIT_PCT,
                        factor: float = SCATTER_FACTOR) -> list[ScatteredSetPoint]:
    """The repeated set points whose mean is known to worse than ``target_pct`` from their
    runs' own scatter, a scatter more than ``factor`` times the scale's error: something other
    than weighing differs between their runs (timing, flow); repeat them. (Wheat's runs scatter
    by ~0.5 % of a kilogram catch from the operator's timing: beyond the scale, but its mean
    is within the target, so not named.)"""
    by_key = by_set_point(set_points, [float(m) for m in masses_g])
    out = []
    for k, ms in sorted(by_key.items()):
        mean = statistics.fmean(ms)
        if len(ms) < 2 or mean <= 0:
            continue
        sd = statistics.stdev(ms)
        if sd > factor * scale_g and sd / mean / math.sqrt(len(ms)) * 100.0 > target_pct:
            out.append(ScatteredSetPoint(k, len(ms), sd / mean * 100.0, scale_g / mean * 100.0))
    return out
