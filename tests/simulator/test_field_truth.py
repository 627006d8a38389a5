"""The independent field truth: its physics behave as stated, and it owes nothing to gateway/."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from simulator.field_truth import (
    FLAT,
    DriveSpec,
    FieldConfig,
    FieldDrive,
    FitterErrors,
    Furrow,
    Machine,
    Multipath,
    Receiver,
    SeedLot,
    Terrain,
    Timing,
    Tube,
    antenna_positions,
    body_to_enu,
    gauss_markov,
    mean_fall_time_s,
    outlet_positions,
    simulate,
    tube_flight,
)

SLOPE = Terrain(cross_slope_deg=3.0, along_slope_deg=0.0, undulation_m=0.0)
QUIET = Receiver(rtk_sigma_m=0.0, white_sigma_m=0.0, heading_sigma_deg=0.0,
                 pitch_sigma_deg=0.0, speed_sigma_kmh=0.0)


def short_field(**kw: object) -> FieldConfig:
    """Two 25 m passes (north, then south after a U-turn) on a 3° cross slope."""
    cfg = FieldConfig(drive=DriveSpec(speeds_kmh=(8.0, 8.0), pass_length_m=25.0, weave_deg=0.0),
                      terrain=SLOPE, receiver=QUIET)
    return replace(cfg, **kw)


def test_importing_the_truth_loads_nothing_from_gateway_protocol_or_drivers() -> None:
    """Its sentences come from the simulator's own encoder (simulator.gnss_sentences), so the
    decoders of protocol/ and the readers of drivers/ judge them instead of sharing code."""
    code = (
        "import sys, simulator.field_truth; "
        "print(sorted(m for m in sys.modules "
        "if m.split('.')[0] in ('gateway', 'protocol', 'drivers')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"


def test_positive_roll_puts_the_right_side_down_and_tilts_the_mast_right() -> None:
    # heading north: right is east
    e, n, u = body_to_enu(0.0, 1.0, 0.0, 0.0, 0.0, 5.0)  # the right-hand side
    assert float(u) < 0 and float(e) == pytest.approx(math.cos(math.radians(5.0)))
    e, n, u = body_to_enu(0.0, 0.0, 1.0, 0.0, 0.0, 5.0)  # the mast
    assert float(e) == pytest.approx(math.sin(math.radians(5.0)))
    e, n, u = body_to_enu(0.0, 0.0, 1.0, 0.0, 5.0, 0.0)  # nose up: the mast leans back
    assert float(n) == pytest.approx(-math.sin(math.radians(5.0)))


@pytest.mark.parametrize("heading", [0.0, 180.0])
def test_a_cross_slope_moves_the_antenna_downhill_by_h_sin_roll(heading: float) -> None:
    """Ground rising to the east: going north the left side is down (roll −3°), going south
    the right side (+3°); either way the antenna, 2.5 m up, sits h·sin 3° = 13 cm downhill."""
    cfg = short_field()
    drive = FieldDrive(cfg.drive, cfg.machine)
    t = np.array([10.0 if heading == 0.0 else 38.0])
    e, n, h, _v, _hi = drive.at(t)
    assert float(h[0]) % 360.0 == pytest.approx(heading, abs=1e-6)
    (pe, pn, _pu), _sec, _h, pitch, roll = antenna_positions(cfg, drive, t)
    assert float(roll[0]) == pytest.approx(-3.0 if heading == 0.0 else 3.0)
    assert float(pitch[0]) == pytest.approx(0.0, abs=1e-9)
    assert float(pe[0] - e[0]) == pytest.approx(-2.5 * math.sin(math.radians(3.0)), abs=1e-9)
    assert float(pn[0] - n[0]) == pytest.approx(0.0, abs=1e-9)


def test_headinga_pitch_of_side_by_side_antennas_is_minus_the_roll() -> None:
    run = simulate(short_field())
    going_north = [ep for ep in run.epochs if 8.0 < ep.t < 12.0]
    assert going_north
    for ep in going_north:
        # roll −3° (left side down): the secondary antenna, on the right, is higher
        assert ep.pitch_deg == pytest.approx(3.0, abs=1e-6)
        assert ep.heading_deg == pytest.approx(90.0, abs=1e-6)  # the baseline points right


def test_gauss_markov_has_the_configured_sigma_and_correlation_time() -> None:
    dt, tau, sigma = 0.1, 5.0, 0.012
    x = gauss_markov(sigma, tau, dt, 200_000, seed=3)
    assert float(np.std(x)) == pytest.approx(sigma, rel=0.1)
    lag = round(tau / dt)
    rho = float(np.corrcoef(x[:-lag], x[lag:])[0, 1])
    assert rho == pytest.approx(math.exp(-1.0), abs=0.05)
    assert float(np.corrcoef(x[:-1], x[1:])[0, 1]) == pytest.approx(math.exp(-dt / tau),
                                                                     abs=0.01)


def _fall(tube: Tube, ground_ms: float = 2.0) -> float:
    t, _v = tube_flight(np.array([ground_ms]), np.array([0.008]), np.array([0.55]),
                        SeedLot(), tube)
    return float(t[0])


def test_fall_time_grows_with_release_height_and_shrinks_with_airflow() -> None:
    base = Tube()
    assert _fall(replace(base, sensor_to_outlet_m=0.30)) > _fall(base)
    assert _fall(replace(base, airflow_ms=8.0)) < _fall(base)
    # the disc throws seeds faster at higher ground speed: they get there sooner
    assert _fall(base, ground_ms=4.0) < _fall(base, ground_ms=1.0)


def test_free_fall_without_drag_or_friction_matches_the_textbook() -> None:
    lot = SeedLot(drag_coefficient=0.0)
    tube = Tube(angle_from_horizontal_deg=90.0, release_speed_ms=0.0,
                release_per_ground_ms=0.0, sensor_to_outlet_m=0.2)
    t, v = tube_flight(np.array([0.0]), np.array([0.008]), np.array([0.0]), lot, tube)
    assert float(t[0]) == pytest.approx(math.sqrt(2 * 0.2 / 9.81), abs=1e-4)
    assert float(v[0]) == pytest.approx(math.sqrt(2 * 9.81 * 0.2), abs=1e-3)


def test_this_lot_is_not_paper_cs_table() -> None:
    """The truth's fall time comes from its physics: ~126 ms at 4 km/h, ~100 ms at 16."""
    cfg = FieldConfig()
    t = mean_fall_time_s(cfg, np.array([4.0, 16.0])) * 1000.0
    assert 120.0 < float(t[0]) < 132.0 and 95.0 < float(t[1]) < 105.0


def test_the_trailed_implement_is_straight_behind_on_a_straight_line() -> None:
    cfg = FieldConfig(drive=DriveSpec(speeds_kmh=(10.0,), pass_length_m=60.0, weave_deg=0.0),
                      terrain=FLAT)
    drive = FieldDrive(cfg.drive, cfg.machine)
    t = np.linspace(5.0, 20.0, 50)
    e, n, h, _v, hi = drive.at(t)
    assert np.max(np.abs(hi - h)) < 1e-9
    oe, on, _ = outlet_positions(cfg, drive, t, np.full(50, 6, dtype=np.intp))
    # the rigid lever arm: 3.0 m behind, row 6 at 1.875 m right (heading north: right = east)
    assert np.allclose(oe - e, 1.875) and np.allclose(on - n, -3.0)


def test_on_a_curve_the_trailed_implement_articulates_by_the_steady_state_angle() -> None:
    radius = 40.0
    m = Machine()
    cfg = FieldConfig(
        drive=DriveSpec(speeds_kmh=(8.0,), pass_length_m=60.0, weave_deg=0.0,
                        pass_curvature_per_m=1.0 / radius),
        terrain=FLAT,
    )
    drive = FieldDrive(cfg.drive, cfg.machine)
    _e, _n, h, _v, hi = drive.at(np.array([20.0]))
    a, wheels = m.hitch_behind_m, m.implement_wheels_behind_hitch_m
    r_hitch = math.hypot(radius, a)
    expected = math.degrees(math.atan(a / radius) + math.asin(wheels / r_hitch))
    assert abs(float(hi[0] - h[0])) == pytest.approx(expected, abs=0.1)


def test_seeds_are_sown_only_on_the_passes_and_slide_further_the_faster_the_drive() -> None:
    run = simulate(short_field())
    assert run.seeds and all(s.pass_index >= 0 for s in run.seeds)
    slide = Furrow().mean_slide_m(np.array([1.0, 2.0, 4.0]))
    assert 0.0 < slide[0] < slide[1] < slide[2]


def test_switching_one_error_source_leaves_the_other_draws_alone() -> None:
    a = simulate(short_field())
    b = simulate(short_field(furrow=Furrow(bounce_along_sd_m=0.05)))
    assert [ep.lat for ep in a.epochs] == [ep.lat for ep in b.epochs]
    assert [s.t_host for s in a.seeds] == [s.t_host for s in b.seeds]
    assert [s.east for s in a.seeds] != [s.east for s in b.seeds]


def test_float_windows_are_flagged_and_dropouts_send_nothing() -> None:
    rx = replace(QUIET, float_windows=((5.0, 2.0),), dropout_windows=((9.0, 1.0),))
    run = simulate(short_field(receiver=rx))
    fixes = {round(ep.t, 1): ep.fix for ep in run.epochs}
    assert fixes[6.0] == "rtk_float" and fixes[4.0] == "rtk_fixed"
    assert 9.5 not in fixes and 8.9 in fixes and 10.0 in fixes


def test_the_host_clock_drifts_and_edges_arrive_after_the_beam_is_broken() -> None:
    timing = Timing(host_drift_ppm=100.0)
    assert float(timing.host(1000.0)) - timing.host_t0 == pytest.approx(1000.1)
    run = simulate(short_field(timing=timing))
    for s in run.seeds[:50]:
        lag = s.t_host - float(timing.host(s.t_edge))
        assert timing.sensor_latency_s + timing.line_s <= lag
        assert lag <= timing.sensor_latency_s + timing.line_s + timing.edge_jitter_s


def test_a_fitter_configures_the_lever_arm_and_latency_off_by_the_stated_errors() -> None:
    m, timing = Machine(), Timing()
    conf = FitterErrors(behind_m=0.03, lateral_m=-0.02, gnss_latency_s=0.01).configured(m, timing)
    assert conf.outlet_behind_antenna_m == pytest.approx(m.outlet_behind_antenna_m + 0.03)
    assert conf.row_lateral_m[0] == pytest.approx(m.row_lateral_m[0] - 0.02)
    assert conf.gnss_output_latency_ms == pytest.approx(50.0)


# ------------------------------------------------------------------ multipath (issue 25)


def test_multipath_bursts_have_their_stated_sizes_and_durations_and_come_and_go() -> None:
    mp = Multipath()
    bursts = mp.bursts(seed=3, until_s=3600.0)
    assert len(bursts) > 40  # an hour at one burst every 30–100 s
    for a, b in itertools.pairwise(bursts):
        assert b.start_s > a.start_s + a.duration_s  # one reflection at a time
    for b in bursts:
        assert 10.0 <= b.duration_s <= 40.0
        step = math.hypot(b.east_m, b.north_m)
        assert 0.02 <= step <= 0.05
        assert abs(b.up_m) == pytest.approx(1.5 * step)
        assert 0.2 <= abs(b.heading_deg) <= 0.6 and 0.2 <= abs(b.pitch_deg) <= 0.6
    # random direction and sign, not a fixed offset a calibration could take out
    assert min(b.east_m for b in bursts) < 0 < max(b.east_m for b in bursts)
    assert min(b.heading_deg for b in bursts) < 0 < max(b.heading_deg for b in bursts)
    inside = sum(b.duration_s for b in bursts) / 3600.0
    assert 0.2 < inside < 0.6


def test_multipath_puts_its_step_on_the_epochs_while_the_receiver_says_fixed() -> None:
    mp = Multipath(gap_s=(4.0, 4.0), duration_s=(6.0, 8.0))
    cfg = short_field(receiver=replace(QUIET, multipath=mp), terrain=FLAT)
    run = simulate(cfg)
    bursts = mp.bursts(cfg.seed, run.epochs[-1].t)
    assert bursts
    on_plateau = outside = 0
    for ep in run.epochs:
        assert ep.fix == "rtk_fixed"
        b = next((b for b in bursts if b.start_s <= ep.t <= b.start_s + b.duration_s), None)
        if b is None:
            outside += 1
            assert abs(ep.err_east_m) < 1e-9 and abs(ep.err_heading_deg) < 1e-6
        elif b.start_s + mp.ramp_s <= ep.t <= b.start_s + b.duration_s - mp.ramp_s:
            on_plateau += 1
            assert ep.err_east_m == pytest.approx(b.east_m, abs=1e-6)
            assert ep.err_north_m == pytest.approx(b.north_m, abs=1e-6)
            assert ep.err_heading_deg == pytest.approx(b.heading_deg, abs=1e-6)
    assert on_plateau > 50 and outside > 10


def test_multipath_is_off_by_default_and_moves_no_other_draw() -> None:
    assert Receiver().multipath is None
    a = simulate(short_field(receiver=replace(Receiver(), multipath=None)))
    b = simulate(short_field(receiver=replace(Receiver(), multipath=Multipath(gap_s=(4.0, 4.0)))))
    assert [s.east for s in a.seeds] == [s.east for s in b.seeds]
    assert [s.t_host for s in a.seeds] == [s.t_host for s in b.seeds]
    assert [ep.t_host for ep in a.epochs] == [ep.t_host for ep in b.epochs]
    assert [ep.lat for ep in a.epochs] != [ep.lat for ep in b.epochs]


def test_multipath_position_only_and_attitude_only_split_the_burst() -> None:
    pos = Multipath(attitude=False).bursts(seed=5, until_s=600.0)
    att = Multipath(position=False).bursts(seed=5, until_s=600.0)
    assert [b.start_s for b in pos] == [b.start_s for b in att]
    assert all(b.heading_deg == 0 and b.pitch_deg == 0 and b.east_m != 0 for b in pos)
    assert all(b.east_m == 0 and b.up_m == 0 and b.heading_deg != 0 for b in att)
