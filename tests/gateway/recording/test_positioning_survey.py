"""Re-positioning stored seeds and fitting delay and lever arm to surveyed seeds."""

from __future__ import annotations

import math
import random

import pytest

from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning import Landing, LocalFrame, SeedPositioner
from gateway.recording.positioning.survey import (
    MIN_SPEED_SPREAD_KMH,
    MIN_SURVEY_SEEDS,
    SurveyError,
    apply_fit,
    fit_survey,
    reposition,
    shift_latlon,
)
from simulator.plant import Drive, Leg
from tests.gateway.recording.test_positioning import FRAME, MONO0, arrivals, run, settings


def drops_of(s: PositioningSection, drive: Drive, edges: list[tuple[int, float]],
             until: float) -> list[SeedDrop]:
    pos = SeedPositioner(s)
    return [la.drop for la in run(pos, drive, FRAME, edges, until=until) + pos.flush()]


# 5 then 12 km/h, with a tractor's acceleration between them (0.6 m/s²)
TWO_SPEEDS = Drive(legs=[Leg(5.0, 5.0), Leg(5.0, 12.0)], start_heading_deg=37.0)
EDGES = [(1 + k % 6, 0.5 + k * 0.101) for k in range(90)]
TRUE = settings(outlet_behind_antenna_m=1.2, delay_correction_ms=12.0)
# what the fitter configured: outlets 5 cm too far back, lateral 2 cm off, no delay correction
CONFIGURED = apply_fit(TRUE, -12.0, 0.05, 0.02)


@pytest.mark.parametrize("lat", [0.0, 45.75, 70.0])
def test_a_shift_in_metres_matches_the_local_frame_on_the_ellipsoid(lat: float) -> None:
    frame = LocalFrame(lat, 126.63, 0.0)
    got = shift_latlon(lat, 126.63, 3.0, -4.0)
    # flat steps: off by the Earth's curvature, d²/2R = 2 µm at 5 m
    assert frame.to_enu(*got, 0.0)[:2] == pytest.approx((3.0, -4.0), abs=1e-5)


def test_a_record_repositioned_with_the_model_it_was_made_with_stays_where_it_is() -> None:
    """To a millimetre or two: re-positioning looks the fall time up at the speed at landing,
    the positioner at the epoch before the edge (they differ while accelerating)."""
    for drop in drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0):
        lat, lon = reposition(drop, CONFIGURED)
        e, n, _ = FRAME.to_enu(lat, lon)
        e0, n0, _ = FRAME.to_enu(drop.lat, drop.lon)
        assert math.hypot(e - e0, n - n0) < 0.002


def test_repositioning_with_another_model_gives_what_that_model_would_have_recorded() -> None:
    made = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)
    direct = drops_of(TRUE, TWO_SPEEDS, EDGES, until=10.0)
    for old, want in zip(made, direct, strict=True):
        e, n, _ = FRAME.to_enu(*reposition(old, TRUE))
        we, wn, _ = FRAME.to_enu(want.lat, want.lon)
        assert math.hypot(e - we, n - wn) < 0.002


def survey(drops: list[SeedDrop], noise_m: float = 0.01, seed: int = 1
           ) -> list[tuple[float, float]]:
    """The truth of each seed (the TRUE model's position) with rover noise."""
    rng = random.Random(seed)
    out = []
    for d in drops:
        lat, lon = reposition(d, TRUE)
        out.append(shift_latlon(lat, lon, rng.gauss(0, noise_m), rng.gauss(0, noise_m)))
    return out


def test_the_fit_recovers_delay_and_lever_arm_and_reports_paper_c_statistics() -> None:
    drops = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)
    fit = fit_survey(drops, survey(drops), CONFIGURED)
    assert fit.delay_ms == pytest.approx(12.0, abs=3.0)
    assert fit.behind_m == pytest.approx(-0.05, abs=0.01)
    assert fit.right_m == pytest.approx(-0.02, abs=0.005)
    assert fit.before.mean_m > 0.05 and fit.after.mean_m < 0.02
    assert fit.after.cv_pct == pytest.approx(100 * fit.after.sd_m / fit.after.mean_m)
    assert fit.problems() == []
    fitted = fit.settings(CONFIGURED)
    assert fitted.outlet_behind_antenna_m == pytest.approx(1.2, abs=0.01)


def test_a_few_mismatched_seeds_do_not_pull_the_robust_fit() -> None:
    drops = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)
    points = survey(drops)
    for i in (3, 30, 60):  # three seeds surveyed a metre off (the wrong seed dug up)
        points[i] = shift_latlon(*points[i], 0.7, 0.7)
    fit = fit_survey(drops, points, CONFIGURED)
    assert fit.behind_m == pytest.approx(-0.05, abs=0.01)
    assert fit.outliers >= 3


def test_too_few_seeds_are_refused_naming_the_minimum() -> None:
    drops = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)[:MIN_SURVEY_SEEDS - 1]
    with pytest.raises(SurveyError, match=f"at least {MIN_SURVEY_SEEDS}"):
        fit_survey(drops, survey(drops), CONFIGURED)


def test_seeds_of_one_speed_are_refused_for_the_delay_but_fit_the_lever_arm() -> None:
    one_speed = Drive(legs=[Leg(10.0, 8.0)], start_heading_deg=37.0, accel_ms2=1000.0)
    drops = drops_of(CONFIGURED, one_speed, EDGES, until=10.0)
    with pytest.raises(SurveyError, match=f"at least {MIN_SPEED_SPREAD_KMH:g} km/h"):
        fit_survey(drops, survey(drops), CONFIGURED)
    fit = fit_survey(drops, survey(drops), CONFIGURED, fit_delay=False)
    assert not fit.delay_fitted and fit.delay_ms == 0.0
    # the delay error shows up as a lever-arm shift of v·Δt at that one speed: right there
    assert fit.behind_m == pytest.approx(-0.05 - 8.0 / 3.6 * 0.012, abs=0.01)
    assert fit.after.mean_m < 0.02


def test_records_without_raw_data_are_refused() -> None:
    drops = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)
    old = [d.model_copy(update={"delay_ms": None}) for d in drops]
    with pytest.raises(SurveyError, match="lack the raw data"):
        fit_survey(old, survey(drops), CONFIGURED)


def test_a_positioner_recalibrated_while_running_positions_the_next_seeds_with_it() -> None:
    """sowgate calibrate positions saved while the daemon runs (live calibration): the seeds
    whose edges come after the switch are where a positioner built with the calibration puts
    them; those resolved before stay as the old model put them."""
    events = arrivals(TWO_SPEEDS, FRAME, EDGES, until=10.0)
    switch = MONO0 + 5.0
    pos = SeedPositioner(CONFIGURED)
    out: list[Landing] = []
    switched = False
    for t, kind, what in events:
        if not switched and t >= switch:
            before = len(out)
            pos.recalibrate(TRUE)
            switched = True
        out += pos.add_epoch(what) if kind == "epoch" else pos.add_edge(what, t)  # type: ignore[arg-type]
    out += pos.flush()
    old = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)
    new = drops_of(TRUE, TWO_SPEEDS, EDGES, until=10.0)
    assert len(out) == len(EDGES) and 0 < before < len(EDGES)
    late = [i for i, (_, t) in enumerate(EDGES) if MONO0 + t > switch + 0.01]
    assert late
    for i in range(len(EDGES)):
        want = old[i] if i < before else new[i] if i in late else None
        if want is None:  # edge before the switch, resolved after: old delay, new lever arm
            continue
        got = out[i].drop
        e, n, _ = FRAME.to_enu(got.lat, got.lon)
        we, wn, _ = FRAME.to_enu(want.lat, want.lon)
        assert math.hypot(e - we, n - wn) < 1e-6
        assert got.delay_ms == pytest.approx(want.delay_ms)


def test_a_recalibration_for_another_row_count_is_refused() -> None:
    pos = SeedPositioner(CONFIGURED)
    with pytest.raises(ValueError, match="rows"):
        pos.recalibrate(CONFIGURED.model_copy(update={"row_lateral_m": [0.0, 0.75]}))
