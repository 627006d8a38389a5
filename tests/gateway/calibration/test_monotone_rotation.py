"""The rotation test keeps the drill's own shape (issue 25 §3).

The truth drills here are deliberately *not* the controller's model: discharge is grams per
turn times an under-fill at low speed (a logistic: the rotor's cells fill less while the seed
barely moves) times a knee past which each turn delivers less (a soft-plus bend: the cells no
longer fill at speed); the motor's speed against duty bends too (two straight pieces). Paper
A's quadratic and straight line cannot take that shape; a monotone curve through the set
points can. Each drill is judged as the controller would sow it: for targets across the
calibrated range, the duty it commands on its fitted curves, and the truth's discharge there.
"""

from __future__ import annotations

import math
import random
import statistics
from dataclasses import dataclass
from pathlib import Path

import pytest

from gateway.calibration import fits as cal
from gateway.calibration.apply import apply_calibrations
from gateway.config import parse_config
from gateway.control.rate_model import duty_for_omega, omega_for_flow
from gateway.core.errors import RateError
from tests.gateway.calibration.test_fits import run as run_cli

WEIGHING_CV = 0.01  # 60 s runs: paper A's discharge CV is below 1.2 %
RPM_CV = 0.002  # shaft turns counted over 60 s
SET_POINTS = 8  # duties spread over the working range
REPEATS = 3  # paper A: "60 s weighings, 3 repeats" per set point


@dataclass(frozen=True)
class KneeDrill:
    """A drill unlike eq. (5)/(6): logistic under-fill × soft knee; a bent motor line."""

    grams_per_rev: float
    underfill: float  # fill fraction missing at standstill
    underfill_rpm: float  # where half of it has gone
    underfill_width: float
    knee_rpm: float
    knee_loss: float  # fraction of each further turn not delivered past the knee
    knee_width: float
    motor_slope: float  # r/min per % duty below the bend
    motor_dead_pct: float  # duty where the shaft starts
    bend_pct: float
    slope_after_bend: float  # ratio of the slope above the bend

    def flow_g_min(self, rpm: float) -> float:
        if rpm <= 0.0:
            return 0.0
        z = (rpm - self.knee_rpm) / self.knee_width
        softplus = z if z > 30 else math.log1p(math.exp(z))
        turns = rpm - self.knee_loss * self.knee_width * softplus
        fill = 1.0 - self.underfill / (1.0 + math.exp((rpm - self.underfill_rpm)
                                                       / self.underfill_width))
        return self.grams_per_rev * turns * fill

    def rpm(self, duty: float) -> float:
        if duty <= self.motor_dead_pct:
            return 0.0
        below = self.motor_slope * (min(duty, self.bend_pct) - self.motor_dead_pct)
        above = self.motor_slope * self.slope_after_bend * max(0.0, duty - self.bend_pct)
        return below + above


CROPS = {  # crop: (g/rev, working r/min lo, hi, duty lo, hi)
    "wheat": (100.0, 20.0, 45.0),
    "rapeseed": (5.0, 5.0, 30.0),
}


def knee_drill(crop: str, rng: random.Random) -> KneeDrill:
    gpr, lo, hi = CROPS[crop]
    span = hi - lo
    return KneeDrill(
        grams_per_rev=gpr * rng.uniform(0.92, 1.08),
        underfill=rng.uniform(0.05, 0.20),
        underfill_rpm=lo + rng.uniform(-0.1, 0.3) * span,
        underfill_width=rng.uniform(0.04, 0.12) * span,
        knee_rpm=lo + rng.uniform(0.35, 0.8) * span,
        knee_loss=rng.uniform(0.2, 0.5),
        knee_width=rng.uniform(0.02, 0.08) * span,
        motor_slope=rng.uniform(0.62, 0.72),
        motor_dead_pct=rng.uniform(8.0, 14.0) if crop == "rapeseed" else rng.uniform(26, 32),
        bend_pct=rng.uniform(45.0, 75.0),
        slope_after_bend=rng.uniform(0.8, 1.1),
    )


def rotation_test(drill: KneeDrill, crop: str,
                  rng: random.Random) -> tuple[list[float], list[float], list[float]]:
    """The operator's test: SET_POINTS duties spanning the crop's working shaft speeds,
    each weighed REPEATS times (the repeats also give the test its own noise)."""
    _, lo, hi = CROPS[crop]
    d_lo = next(d / 10 for d in range(0, 1001) if drill.rpm(d / 10) >= lo)
    d_hi = next((d / 10 for d in range(0, 1001) if drill.rpm(d / 10) >= hi), 100.0)
    duties = [d_lo + (d_hi - d_lo) * i / (SET_POINTS - 1) for i in range(SET_POINTS)
              for _ in range(REPEATS)]
    rpm = [drill.rpm(d) * (1 + rng.gauss(0, RPM_CV)) for d in duties]
    flows = [drill.flow_g_min(drill.rpm(d)) * (1 + rng.gauss(0, WEIGHING_CV)) for d in duties]
    return duties, rpm, flows


def crop_model(crop: str, **fit: object):  # type: ignore[no-untyped-def]
    settings = parse_config({"control": {"crop": crop}})
    base = settings.control.crops[crop]
    return base.model_validate({**base.model_dump(), **fit})


def sowing_error_pct(drill: KneeDrill, model, rpm: list[float]) -> float:  # type: ignore[no-untyped-def]
    """Mean |true / wanted - 1| over 25 targets across the calibrated discharge range."""
    q_lo, q_hi = drill.flow_g_min(min(rpm)), drill.flow_g_min(max(rpm))
    errs = []
    for i in range(25):
        wanted = q_lo + (q_hi - q_lo) * i / 24
        duty = duty_for_omega(omega_for_flow(wanted, model), model)
        errs.append(abs(drill.flow_g_min(drill.rpm(duty)) / wanted - 1.0))
    return 100.0 * statistics.fmean(errs)


def monotone_model(crop: str, duties: list[float], rpm: list[float], flows: list[float]):  # type: ignore[no-untyped-def]
    motor = cal.fit_monotone(duties, rpm, "motor")
    meter = cal.fit_monotone(rpm, flows, "meter", groups=duties)
    return crop_model(crop, meter_curve=list(meter.points), motor_curve=list(motor.points),
                      omega_min_rpm=min(rpm), omega_max_rpm=max(rpm))


def quadratic_model(crop: str, duties: list[float], rpm: list[float],
                    flows: list[float]):  # type: ignore[no-untyped-def]
    line = cal.fit_motor_line(duties, rpm)
    quad = cal.fit_meter_quadratic(rpm, flows)
    return crop_model(crop, motor_slope=line.slope, motor_intercept=line.intercept,
                      meter_a=quad.a, meter_b=quad.b, meter_c=quad.c,
                      omega_min_rpm=min(rpm), omega_max_rpm=max(rpm))


@pytest.mark.parametrize("crop", sorted(CROPS))
def test_drills_with_knees_sow_within_1_pct_at_p90_on_their_own_curve(crop: str) -> None:
    """24 drills per crop: the p90 of the rate error is at most 1 %, and no monotone drill
    is refused. (Paper A's line and quadratic on the same tests: printed for the record,
    asserted worse on the median.)"""
    rng = random.Random(25 if crop == "wheat" else 52)
    own, quad, refused = [], [], 0
    for _ in range(24):
        drill = knee_drill(crop, rng)
        duties, rpm, flows = rotation_test(drill, crop, rng)
        own.append(sowing_error_pct(drill, monotone_model(crop, duties, rpm, flows), rpm))
        try:
            quad.append(sowing_error_pct(drill, quadratic_model(crop, duties, rpm, flows),
                                         rpm))
        except (cal.CalibrationError, RateError):  # refused, or its parabola peaks too soon
            refused += 1
    p90 = statistics.quantiles(own, n=10)[-1]
    print(f"{crop}: own curve median {statistics.median(own):.2f} % p90 {p90:.2f} % worst "
          f"{max(own):.2f} %; quadratic median {statistics.median(quad):.2f} % p90 "
          f"{statistics.quantiles(quad, n=10)[-1]:.2f} %, {refused} refused")
    assert p90 <= 1.0
    assert statistics.median(own) < statistics.median(quad)


def test_a_fall_within_the_weighing_noise_is_pooled_not_refused() -> None:
    rpm = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0]
    flows = [2000.0, 2500.0, 2900.0, 2890.0, 3300.0, 3600.0]  # -0.3 %: noise at 2 % CV
    fit = cal.fit_monotone(rpm, flows, "meter")
    assert fit.pooled == ((30.0, 35.0),)
    assert [p[0] for p in fit.points] == [20.0, 25.0, 32.5, 40.0, 45.0]
    assert fit.predict(32.5) == pytest.approx(2895.0)


def test_a_fall_beyond_the_noise_is_refused_naming_the_set_points_to_repeat() -> None:
    rpm = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0]
    flows = [2000.0, 2500.0, 2900.0, 2500.0, 3300.0, 3600.0]  # -14 %: a weighing mistake
    with pytest.raises(cal.CalibrationError, match=r"repeat set point\(s\) 30, 35"):
        cal.fit_monotone(rpm, flows, "meter")


def test_repeated_set_points_give_the_tests_own_noise() -> None:
    duty = [40, 40, 50, 50, 60, 60, 70, 70, 80, 80]
    flows = [1000, 1004, 1500, 1497, 2000, 2003, 1990, 1994, 2500, 2496]
    fit = cal.fit_monotone(duty, flows, "meter")
    assert fit.run_cv == pytest.approx(0.005)  # the floor: repeats agree within 0.2 %
    with pytest.raises(cal.CalibrationError, match="repeat set point"):
        # a 2 % fall that the default 2 % noise would pool is beyond this test's own noise
        cal.fit_monotone(duty, [*flows[:6], 1960, 1964, 2500, 2496], "meter")
    assert cal.fit_monotone([40, 50, 60, 70, 80], [1000, 1500, 2001, 1962, 2500],
                            "meter").pooled == ((60.0, 70.0),)


def test_fewer_than_5_set_points_keep_paper_a_s_quadratic() -> None:
    with pytest.raises(cal.CalibrationError, match="at least 5 distinct set points"):
        cal.fit_monotone([20, 30, 40, 45], [1, 2, 3, 4], "meter")


def test_the_cli_saves_the_drills_own_curves_and_the_daemon_sows_on_them(
        tmp_path: Path) -> None:
    """``sowgate calibrate rotation`` with 8 set points on a knee drill: the entry says its
    model and keeps the line and quadratic for older readers; applied, the crop sows on the
    curves (within 1 % of the truth where the quadratic was 2 % off)."""
    rng = random.Random(7)
    drill = knee_drill("wheat", rng)
    duties, rpm, flows = rotation_test(drill, "wheat", rng)
    code, out = run_cli(["calibrate", "--state-dir", str(tmp_path), "rotation", "--channel",
                         "wheat", "--model", "paper_a", "--no-wait", "--seconds", "60",
                         "--duties", ",".join(f"{d:.3f}" for d in duties),
                         "--rpm", ",".join(f"{w:.4f}" for w in rpm),
                         "--mass", ",".join(f"{q:.2f}" for q in flows)])
    assert code == 0, out
    entry = cal.CalibrationStore(tmp_path).get("rotation.wheat")
    assert entry is not None
    result = entry["result"]
    assert result["meter_model"] == "monotone_cubic"
    assert len(result["meter_curve"]) == SET_POINTS
    assert {"a", "b", "c"} <= set(result["meter"])  # older readers still find eq. 6
    settings = parse_config({"control": {"crop": "wheat"}})
    assert apply_calibrations(settings, tmp_path) == [
        "wheat metering model refitted (its own monotone curve)"]
    model = settings.control.crops["wheat"]
    assert sowing_error_pct(drill, model, rpm) < 1.0


def test_an_older_calibration_file_without_curves_still_loads_on_the_quadratic(
        tmp_path: Path) -> None:
    store = cal.CalibrationStore(tmp_path)
    store.save("rotation.wheat", {"saved_at": "2026-05-01T08:00:00+00:00", "model": "paper_a",
                                  "result": {"motor": {"slope": 0.7, "intercept": -19.0},
                                             "meter": {"a": -0.6, "b": 130.0, "c": -390.0},
                                             "omega_range": [20.0, 45.0]}})
    settings = parse_config({"control": {"crop": "wheat"}})
    assert apply_calibrations(settings, tmp_path) == ["wheat metering model refitted"]
    model = settings.control.crops["wheat"]
    assert model.meter_curve is None and model.motor_curve is None
    assert omega_for_flow(-0.6 * 900 + 130.0 * 30 - 390.0, model) == pytest.approx(30.0)


def test_weighings_too_noisy_for_the_rate_name_the_set_points_to_repeat(
        tmp_path: Path) -> None:
    """Rapeseed on a knee drill (not the controller's model): catches of 25–150 g on a
    σ 2 g scale leave the low set points' means known to several %; the test names them,
    with how many runs each needs, and still saves (the readings are consistent). On a
    σ 0.2 g scale nothing is named."""
    rng = random.Random(11)
    drill = knee_drill("rapeseed", rng)
    duties, rpm, _ = rotation_test(drill, "rapeseed", rng)
    duties = [round(d, 3) for d in duties]  # as typed at the CLI below
    true = [drill.flow_g_min(drill.rpm(d)) for d in duties]  # 60 s runs: g/min = g caught
    coarse = [q + rng.gauss(0.0, 2.0) for q in true]
    fine = [q + rng.gauss(0.0, 0.2) for q in true]
    vague = cal.imprecise_set_points(duties, coarse)
    assert vague, "σ 2 g on 25 g catches must be named"
    lowest = min(duties)
    assert any(v.set_point == lowest for v in vague)
    assert all(v.se_pct > cal.SET_POINT_SE_LIMIT_PCT and v.runs_needed > v.runs == REPEATS
               for v in vague)
    assert cal.imprecise_set_points(duties, fine) == []
    code, out = run_cli(["calibrate", "--state-dir", str(tmp_path), "rotation", "--channel",
                         "rapeseed", "--model", "paper_a", "--no-wait", "--seconds", "60",
                         "--duties", ",".join(f"{d:.3f}" for d in duties),
                         "--rpm", ",".join(f"{w:.4f}" for w in rpm),
                         "--mass", ",".join(f"{q:.2f}" for q in coarse)])
    assert code == 0, out
    flat = " ".join(out.split())
    assert "the runs were too short for this scale" in flat
    assert f"rapeseed at {lowest:.4g} % duty:" in flat
    assert cal.CalibrationStore(tmp_path).get("rotation.rapeseed") is not None
