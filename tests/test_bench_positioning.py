"""The positioning benchmark's plumbing: the gateway and the independent truth agree where
nothing is wrong, an injected error shows up where it should, and the survey hook hands out
usable pairs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from benchmarks.bench_positioning import (
    FitterErrors,
    baseline_offset_deg,
    calibrate,
    clean_config,
    gateway_inputs,
    landing_errors,
    measured_fall_table,
    replay,
    section,
    survey_pairs,
)
from simulator.field_truth import DriveSpec, FieldConfig, FieldRun, Terrain, simulate


def short(cfg: FieldConfig, speeds: tuple[float, ...] = (6.0, 12.0)) -> FieldConfig:
    return replace(cfg, drive=replace(cfg.drive, speeds_kmh=speeds, pass_length_m=20.0))


def sowgate(run: FieldRun, fitter: FitterErrors | None = None, terrain: bool = False,
            pitch_track_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    fitter = fitter or FitterErrors()
    cfg = run.config
    inputs = gateway_inputs(run)
    settings = section(fitter.configured(cfg.machine, cfg.timing), measured_fall_table(cfg),
                       terrain=terrain, pitch_track_m=pitch_track_m)
    err = landing_errors(run, replay(settings, "interpolated", inputs, baseline_offset_deg(run)))
    return err.along, err.across


def test_on_a_clean_field_with_the_true_parameters_sowgate_lands_on_the_truth() -> None:
    """Flat, straight, noiseless, exact lever arm and latency, this lot's table: the truth and
    the position model share no code, so agreement here checks both sets of conventions."""
    run = simulate(short(clean_config()))
    along, across = sowgate(run)
    assert float(np.mean(np.hypot(along, across))) < 0.003


def test_a_lever_arm_configured_3_cm_right_puts_every_seed_3_cm_right() -> None:
    run = simulate(short(clean_config()))
    _along, across = sowgate(run, FitterErrors(lateral_m=0.03))
    assert float(np.mean(across)) == pytest.approx(0.03, abs=0.002)


def test_the_gateways_terrain_compensation_removes_most_of_a_cross_slope() -> None:
    """antenna_height_m + attitude_source = "dual_antenna", roll from the decoded #HEADINGA
    pitch: the 131 mm of a 2.5 m antenna's lean on 3° go. What is left is the truth's
    implement hanging from a point 0.5 m up (26 mm downhill), which a configuration without
    ``[positioning.hitch]`` cannot express."""
    cfg = short(replace(clean_config(), terrain=Terrain(cross_slope_deg=3.0, along_slope_deg=0.0,
                                                        undulation_m=0.0)))
    run = simulate(cfg)
    _a, raw = sowgate(run)
    _a, comp = sowgate(run, terrain=True)
    assert float(np.mean(np.abs(raw))) > 0.09
    assert float(np.mean(np.abs(comp))) == pytest.approx(0.5 * np.sin(np.radians(3.0)),
                                                         abs=0.003)


def test_a_trailed_implements_raised_hitch_is_compensated_when_configured() -> None:
    """The truth's hitch is 0.5 m up: configured (``[positioning.hitch] height_m``) the
    implement's 26 mm swing downhill on 3° goes too."""
    base = clean_config()
    cfg = short(replace(base, terrain=Terrain(cross_slope_deg=3.0, along_slope_deg=0.0,
                                              undulation_m=0.0),
                        machine=replace(base.machine, trailed=True)))
    run = simulate(cfg)
    _a, at_ground = sowgate(run, FitterErrors(hitch_height_m=-0.5), terrain=True)
    _a, comp = sowgate(run, terrain=True)
    assert float(np.mean(np.abs(at_ground))) > 0.02
    assert float(np.mean(np.abs(comp))) < 0.006


def test_pitch_from_the_track_removes_an_along_slope_the_side_by_side_antennas_miss() -> None:
    """3° along the passes (up one way, down the next), trailed implement with its raised
    hitch configured: roll-only compensation leaves the antenna's lean (less the hitch's)
    along the row; the climb over 4 m of track (RTK height noise 15 mm white) takes it out,
    except for the first 4 m sown (no track yet)."""
    base = clean_config()
    cfg = short(replace(base, terrain=Terrain(cross_slope_deg=0.0, along_slope_deg=3.0,
                                              undulation_m=0.0),
                        machine=replace(base.machine, trailed=True),
                        receiver=replace(base.receiver, vertical_white_sigma_m=0.015)))
    run = simulate(cfg)
    along, _ = sowgate(run, terrain=True)
    assert float(np.median(np.abs(along))) > 0.09  # (2.5 − 0.5 m hitch)·sin 3° = 105 mm
    along, _ = sowgate(run, terrain=True, pitch_track_m=4.0)
    assert float(np.median(np.abs(along))) < 0.01
    assert float(np.mean(np.abs(along) > 0.05)) < 0.12


def test_survey_pairs_are_50_seeds_over_every_speed_surveyed_where_they_lie() -> None:
    cfg = short(clean_config(), speeds=(4.0, 8.0, 12.0, 16.0))
    run = simulate(cfg)
    inputs = gateway_inputs(run)
    settings = section(FitterErrors().configured(cfg.machine, cfg.timing))
    landings = replay(settings, "interpolated", inputs)
    pairs, held_out = survey_pairs(run, landings)
    assert len(pairs) == 50 and int((~held_out).sum()) == 50
    chosen = [run.seeds[i] for i in np.flatnonzero(~held_out)]
    assert sorted({s.pass_index for s in chosen}) == [0, 1, 2, 3]
    for pair, s in zip(pairs, chosen, strict=True):
        assert pair.record.row == s.row and pair.edge_t_mono == s.t_host
        e, n = run.to_enu(np.array([pair.surveyed_lat]), np.array([pair.surveyed_lon]))
        assert np.hypot(float(e[0]) - s.east, float(n[0]) - s.north) < 0.025


def test_the_benchmark_drive_covers_4_to_16_kmh() -> None:
    assert DriveSpec().speeds_kmh == (4.0, 8.0, 12.0, 16.0)


def test_the_survey_calibration_fits_out_the_fitters_lever_arm_and_latency() -> None:
    """The gateway's own fit_survey on 50 surveyed seeds' records, then reposition: a lever
    arm 3 cm long and 2 cm right and a latency 10 ms short are fitted out of the other seeds."""
    cfg = short(clean_config(), speeds=(4.0, 8.0, 12.0, 16.0))
    run = simulate(cfg)
    inputs = gateway_inputs(run)
    settings = section(FitterErrors(behind_m=0.03, lateral_m=0.02, gnss_latency_s=-0.010)
                       .configured(cfg.machine, cfg.timing), measured_fall_table(cfg))
    landings = replay(settings, "interpolated", inputs, baseline_offset_deg(run))
    before = landing_errors(run, landings)
    pairs, held_out = survey_pairs(run, landings)
    cal = calibrate(run, landings, settings, pairs)
    assert cal.not_repositionable == 0
    assert cal.fit.behind_m == pytest.approx(-0.03, abs=0.006)
    assert cal.fit.right_m == pytest.approx(-0.02, abs=0.004)
    assert float(np.mean(before.total[held_out])) > 0.03
    assert float(np.mean(cal.errors.total[held_out])) < 0.008
