"""The truth drill the rate benchmark judges against: independent of gateway, and physical."""

from __future__ import annotations

import ast
import itertools
import random
import statistics
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import simulator.drill_truth as truth
from simulator.drill_truth import (
    DISCHARGE_FACTOR_RANGE,
    MAX_SHAFT_RPM,
    MOTOR_OFFSET_RANGE_RPM,
    MOTOR_SLOPE_RANGE,
    PAPER_A_METER,
    PAPER_A_MOTOR,
    PAPER_A_SET_POINTS_RPM,
    RADAR_BIAS_RANGE,
    SaturatingCurve,
    field_drills,
    fit_saturating,
    reference_drill,
)

FIRST_PARTY = {"gateway", "drivers", "protocol", "simulator", "benchmarks", "tests"}


def _eq6(crop: str, w: float) -> float:
    a, b, c = PAPER_A_METER[crop]
    return a * w * w + b * w + c


def test_truth_module_imports_nothing_from_the_code_it_judges() -> None:
    tree = ast.parse(Path(truth.__file__).read_text(encoding="utf-8"))
    imported: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "relative import in the truth module"
            imported.add((node.module or "").split(".")[0])
    assert not imported & FIRST_PARTY, imported & FIRST_PARTY


def test_importing_the_truth_loads_no_gateway_module_at_all() -> None:
    """Also catches an indirect import through a package __init__."""
    code = (
        "import sys, simulator.drill_truth\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('gateway', 'drivers')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=Path(truth.__file__).parent.parent)
    assert out.stdout.strip() == "[]"


def test_saturating_fit_recovers_a_curve_it_is_given() -> None:
    """The old truth's fit, kept for reference (no drill uses it any more)."""
    known = SaturatingCurve(a=5000.0, b=-5400.0, w=60.0)
    ws = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0]
    fit = fit_saturating(ws, [known.flow_g_min(w) for w in ws])
    for w in ws:
        assert fit.flow_g_min(w) == pytest.approx(known.flow_g_min(w), rel=1e-3)


@pytest.mark.parametrize("crop", ["rapeseed", "wheat"])
def test_discharge_is_built_per_turn_with_underfill_and_a_knee(crop: str) -> None:
    """Issue 25: not the controller's quadratic shifted: grams per turn fall at a crawl
    (under-fill) and past a knee, and the flow is anchored to eq. (6) at one point only."""
    lo, hi = PAPER_A_SET_POINTS_RPM[crop][0], PAPER_A_SET_POINTS_RPM[crop][-1]
    mid = (lo + hi) / 2
    for knee in (0.03, 0.06, 0.12):
        curve = truth.fill_curve(crop, knee=knee, knee_at=0.5, underfill=0.06,
                                 underfill_rpm=3.0)
        assert curve.flow_g_min(mid) == pytest.approx(_eq6(crop, mid), rel=1e-9)
        per_turn_knee = curve.per_turn_g(curve.knee_rpm - 5 * truth.KNEE_SMOOTH_RPM)
        assert curve.per_turn_g(hi) / per_turn_knee == pytest.approx(1 - knee, abs=0.01)
        assert curve.per_turn_g(0.5) < curve.per_turn_g(lo + 5.0) * 0.96  # under-fill
        ws = [0.5 * i for i in range(1, 101)]  # 0.5 .. 50 r/min: rising everywhere
        flows = [curve.flow_g_min(w) for w in ws]
        assert all(b > a for a, b in itertools.pairwise(flows))
    # a quadratic through the set points misses a 12 % knee by more than the weighing noise
    curve = truth.fill_curve(crop, knee=0.12)
    pts = [lo + (hi - lo) * i / 20 for i in range(21)]
    coef = np.polyfit(pts, [curve.flow_g_min(w) for w in pts], 2)
    worst = max(abs(np.polyval(coef, w) / curve.flow_g_min(w) - 1) for w in pts)
    assert worst > 0.005
    assert curve.flow_g_min(0.0) == 0.0
    assert curve.flow_g_min(-3.0) == 0.0


def test_with_knee_changes_only_the_knee() -> None:
    d = field_drills("wheat", 4, seed=13)[0]
    k = truth.with_knee(d, 0.12)
    assert isinstance(k.curve, truth.FillCurve)
    assert k.curve.knee == 0.12
    assert k.curve.knee_rpm == d.curve.knee_rpm  # type: ignore[union-attr]
    assert replace(k, curve=d.curve) == d


def test_motor_dead_band_line_and_ceiling() -> None:
    slope, offset, startup = PAPER_A_MOTOR["wheat"]
    d = reference_drill("wheat", 1)
    assert d.steady_rpm(startup - 1.0, turning=False) == 0.0  # stiction: does not start
    assert d.steady_rpm(60.0, turning=False) == pytest.approx(slope * 60.0 + offset)
    assert d.steady_rpm(100.0, turning=True) <= MAX_SHAFT_RPM
    assert d.steady_rpm(0.0, turning=True) == 0.0
    assert d.steady_rpm(-offset / slope - 0.5, turning=True) == 0.0  # the dead band


def test_motor_saturates_and_slips_with_load() -> None:
    """Issue 25: not a straight line: tanh saturation and slip growing with the load."""
    slope, offset, _ = PAPER_A_MOTOR["wheat"]
    d = replace(reference_drill("wheat", 1), motor_saturation_rpm=100.0, motor_slip=0.03)
    line = [slope * k + offset for k in (40.0, 60.0, 80.0, 95.0)]
    got = [d.steady_rpm(k, turning=True) for k in (40.0, 60.0, 80.0, 95.0)]
    shortfall = [1 - g / ln for g, ln in zip(got, line, strict=True)]
    assert all(b > a for a, b in itertools.pairwise(shortfall))  # bends away more and more
    assert 0.03 < shortfall[-1] < 0.15
    assert all(b > a for a, b in itertools.pairwise(got))  # still monotonic


def test_meter_lags_a_duty_step_and_integrates_turns_and_grams() -> None:
    d = replace(reference_drill("wheat", 1), lag_s=0.3, discharge_cv=0.0)
    m = d.meter(noise_seed=1)
    target = d.steady_rpm(80.0, turning=False)
    for _ in range(15):  # 0.3 s = one time constant
        m.step(80.0, 0.02)
    assert m.rpm == pytest.approx(target * (1 - 2.718281828 ** -1), rel=0.02)
    for _ in range(3000):  # a minute more at steady speed
        m.step(80.0, 0.02)
    assert m.revolutions == pytest.approx(target * (60.3 - 0.3) / 60.0, rel=0.01)
    assert m.mass_g == pytest.approx(d.flow_g_min(target) * 60.0 / 60.0, rel=0.01)


def test_equal_noise_seeds_give_equal_discharge() -> None:
    d = reference_drill("rapeseed", 2)
    a, b, c = d.meter(5), d.meter(5), d.meter(6)
    for _ in range(500):
        a.step(40.0, 0.02)
        b.step(40.0, 0.02)
        c.step(40.0, 0.02)
    assert a.mass_g == b.mass_g != c.mass_g


def test_discharge_factor_and_lot_drift_scale_the_flow() -> None:
    d = reference_drill("wheat", 3)
    w = 35.0
    assert replace(d, discharge_factor=1.08).flow_g_min(w) == pytest.approx(d.flow_g_min(w) * 1.08)
    drifting = replace(d, lot_drift=0.03)
    assert drifting.flow_g_min(w, progress=0.0) == pytest.approx(d.flow_g_min(w))
    assert drifting.flow_g_min(w, progress=1.0) == pytest.approx(d.flow_g_min(w) * 1.03)


def test_radar_reads_the_true_speed_times_its_bias_plus_noise() -> None:
    d = replace(reference_drill("wheat", 1), radar_bias=0.02)
    rng = random.Random(4)
    readings = [d.radar_kmh(4.0, rng.gauss(0.0, 1.0)) for _ in range(4000)]
    assert statistics.fmean(readings) == pytest.approx(4.0 * 1.02, rel=0.003)
    # the surface's scale on top of the mounting bias, the drill's or given per reading
    assert replace(d, surface=0.04).radar_kmh(4.0, 0.0) == pytest.approx(4.0 * 1.02 * 1.04)
    assert d.radar_kmh(4.0, 0.0, surface=0.08) == pytest.approx(4.0 * 1.02 * 1.08)
    assert statistics.stdev(readings) / statistics.fmean(readings) == pytest.approx(
        d.radar_cv, rel=0.1)
    assert d.radar_kmh(0.0, 1.5) == 0.0


@pytest.mark.parametrize("crop", ["rapeseed", "wheat"])
def test_field_drills_span_every_range_and_are_reproducible(crop: str) -> None:
    drills = field_drills(crop, 6, seed=13)
    assert drills == field_drills(crop, 6, seed=13)
    assert drills != field_drills(crop, 6, seed=14)
    slope0, offset0, _ = PAPER_A_MOTOR[crop]
    spans = {
        "discharge": ([d.discharge_factor - 1 for d in drills], DISCHARGE_FACTOR_RANGE),
        "slope": ([d.motor_slope / slope0 - 1 for d in drills], MOTOR_SLOPE_RANGE),
        "offset": ([d.motor_offset_rpm - offset0 for d in drills], MOTOR_OFFSET_RANGE_RPM),
        "radar": ([d.radar_bias for d in drills], RADAR_BIAS_RANGE),
    }
    for name, (values, bound) in spans.items():
        assert all(abs(v) <= bound + 1e-12 for v in values), name
        # one value in each sixth of the range: both ends are reached
        assert min(values) < -bound * 2 / 3 and max(values) > bound * 2 / 3, name
    assert {abs(d.lot_drift) for d in drills} == {truth.LOT_DRIFT}
    knees = [d.curve.knee for d in drills]  # type: ignore[union-attr]
    lo, hi = truth.KNEE_RANGE
    assert all(lo <= k <= hi for k in knees)
    assert min(knees) < lo + (hi - lo) / 3 and max(knees) > hi - (hi - lo) / 3
    assert all(100.0 <= d.motor_saturation_rpm <= 200.0 for d in drills)
