"""Re-positioning stored seeds and fitting delay and lever arm to surveyed seeds."""

from __future__ import annotations

import math
import random
from datetime import UTC, datetime

import pytest

from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning import Landing, LocalFrame, SeedPositioner
from gateway.recording.positioning.survey import (
    MIN_SPEED_SPREAD_KMH,
    MIN_SURVEY_SEEDS,
    Sown,
    SurveyError,
    apply_fit,
    fit_survey,
    reposition,
    shift_latlon,
    survey_coverage,
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


# -- surveys that cannot tell the parameters apart: warned, saying what to survey next


def seed_at(east: float, north: float, heading: float, speed: float) -> SeedDrop:
    lat, lon = shift_latlon(45.75, 126.63, east, north)
    return SeedDrop(row=1, utc=datetime(2026, 5, 2, 6, tzinfo=UTC), lat=lat, lon=lon,
                    fix="rtk_fixed", speed_kmh=speed, heading_deg=heading % 360.0)


def passes(speeds: list[float], spacing_m: float = 6.0, length_m: float = 80.0,
           step_m: float = 2.0) -> list[SeedDrop]:
    """North–south passes, one a speed, ``spacing_m`` apart, alternating direction."""
    out = []
    for i, v in enumerate(speeds):
        heading = 0.0 if i % 2 == 0 else 180.0
        out += [seed_at(i * spacing_m, k * step_m, heading, v)
                for k in range(int(length_m / step_m))]
    return out


def sown_of(drops: list[SeedDrop]) -> Sown:
    sown = Sown.empty()
    for d in drops:
        sown.add(d)
    return sown


FIELD = passes([4.0, 8.0, 12.0, 16.0, 4.0, 8.0, 12.0, 16.0])


def test_a_survey_over_the_whole_field_both_ways_and_every_speed_is_not_warned() -> None:
    chosen = FIELD[::13]
    assert survey_coverage(chosen, sown_of(FIELD)) == []


def test_a_survey_driven_one_way_is_warned_naming_the_heading_to_survey_next() -> None:
    one_way = [d for d in FIELD if d.heading_deg == 0.0][::7]
    (warning,) = [w for w in survey_coverage(one_way, sown_of(FIELD)) if "one way" in w]
    assert "driving one way (heading 0°)" in warning and "heading 180°" in warning
    # and fit_survey passes it on (the CLI prints it): TWO_SPEEDS is driven one way
    drops = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)
    fit = fit_survey(drops, survey(drops), CONFIGURED, sown=sown_of(drops))
    assert any("heading 217°" in w for w in fit.coverage_warnings)


def test_sown_speeds_beyond_the_surveyed_band_are_warned_naming_the_speed_to_survey() -> None:
    fast = [d for d in FIELD if d.speed_kmh >= 12.0][::7]  # both ways, 12 and 16 km/h only
    warnings = survey_coverage(fast, sown_of(FIELD))
    speed = [w for w in warnings if "extrapolated" in w]
    assert speed == ["the seeds were sown at 4–16 km/h, the surveyed ones at 12–16 km/h: the "
                     "delay is extrapolated to 4 km/h; survey seeds sown at 4 km/h too"]


def test_a_survey_on_one_side_of_the_field_is_warned_saying_how_far_across_to_survey() -> None:
    west = [d for d in FIELD if east_of(d) < 20.0][::5]  # the first four passes, 18 m
    warnings = survey_coverage(west, sown_of(FIELD))
    (side,) = [w for w in warnings if "one side" in w]
    assert "of the field's 42 m across the passes" in side
    assert "survey seeds from the passes about" in side


def east_of(d: SeedDrop) -> float:
    """East coordinate of a drop, metres from the field's corner."""
    return LocalFrame(45.75, 126.63, 0.0).to_enu(d.lat, d.lon, 0.0)[0]


# -- a delay that changes with speed (a truth unlike the model's constant table offset)

FOUR_SPEEDS = Drive(legs=[Leg(4.0, 4.0), Leg(4.0, 8.0), Leg(4.0, 12.0), Leg(4.0, 16.0)],
                    start_heading_deg=37.0)
EDGES_16S = [(1 + k % 6, 0.5 + k * 0.101) for k in range(150)]


def sliding_truth(drops: list[SeedDrop], per_kmh2_m: float = 0.0002) -> list[tuple[float, float]]:
    """Where the seeds are: the TRUE model's point plus a slide forward in the furrow that
    grows with the square of the speed (5 cm at 16 km/h), which no table offset is."""
    out = []
    for d in drops:
        lat, lon = reposition(d, TRUE)
        assert d.heading_deg is not None
        h = math.radians(d.heading_deg)
        slide = per_kmh2_m * d.speed_kmh ** 2
        out.append(shift_latlon(lat, lon, slide * math.sin(h), slide * math.cos(h)))
    return out


def test_a_delay_growing_with_speed_is_fitted_into_the_fall_time_table(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    drops = drops_of(CONFIGURED, FOUR_SPEEDS, EDGES_16S, until=17.0)
    truth = sliding_truth(drops)
    fit = fit_survey(drops, truth, CONFIGURED)
    assert fit.delay_ms_per_kmh > 0.5 and fit.speed_ref_kmh > 0  # faster: slides further
    fitted = fit.settings(CONFIGURED)
    assert len(fitted.fall_time_table) > len(CONFIGURED.fall_time_table)
    # re-positioned with the fit, the seeds land on the truth within a few millimetres
    for d, (lat, lon) in zip(drops, truth, strict=True):
        e, n, _ = FRAME.to_enu(*reposition(d, fitted))
        te, tn, _ = FRAME.to_enu(lat, lon)
        assert math.hypot(e - te, n - tn) < 0.006
    # a constant delay (the former fit) cannot follow it
    monkeypatch.setattr("gateway.recording.positioning.survey.MIN_SPREAD_FOR_SLOPE_KMH", 1e9)
    constant = fit_survey(drops, truth, CONFIGURED)
    assert constant.delay_ms_per_kmh == 0.0
    assert fit.after.mean_m < 0.5 * constant.after.mean_m


def test_a_slope_fitted_where_the_truth_has_none_stays_near_zero_and_costs_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Four speeds: the slope is fitted even when it is not told from the rover's noise
    (every real lot has one); where the truth has none it comes out near 0 and the seeds
    land as well as with the constant delay."""
    drops = drops_of(CONFIGURED, FOUR_SPEEDS, EDGES_16S, until=17.0)
    fit = fit_survey(drops, survey(drops), CONFIGURED)
    assert abs(fit.delay_ms_per_kmh) < 0.3
    assert fit.delay_ms == pytest.approx(12.0, abs=3.0)
    monkeypatch.setattr("gateway.recording.positioning.survey.MIN_SPREAD_FOR_SLOPE_KMH", 1e9)
    constant = fit_survey(drops, survey(drops), CONFIGURED)
    assert fit.after.mean_m < constant.after.mean_m + 0.001
