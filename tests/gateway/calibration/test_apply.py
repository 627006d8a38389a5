"""Calibrations made in the field take precedence over the factory config at start-up."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.calibration import fits as cal
from gateway.calibration.apply import apply_calibrations
from gateway.config import parse_config
from gateway.control.rate_model import required_duty


def test_paper_a_refit_replaces_the_crop_model_and_changes_the_duty(tmp_path: Path) -> None:
    store = cal.CalibrationStore(tmp_path)
    duties = [30.0, 45.0, 60.0, 75.0, 90.0]
    rpm = [0.7 * d - 20.0 for d in duties]
    rates = [-0.6 * w * w + 130.0 * w - 400.0 for w in rpm]
    line = cal.fit_motor_line(duties, rpm)
    quad = cal.fit_meter_quadratic(rpm, rates, (min(rpm), max(rpm)))
    store.save(
        "rotation.wheat",
        cal.to_entry(
            {"motor": line.__dict__, "meter": quad.__dict__, "omega_range": [1.0, 43.0]},
            channel="wheat",
            model="paper_a",
        ),
    )
    settings = parse_config({})
    before = required_duty(200, 2.0, 4.0, settings.control.crops["wheat"])
    notes = apply_calibrations(settings, tmp_path)
    assert notes == ["wheat metering model refitted"]
    wheat = settings.control.crops["wheat"]
    assert wheat.motor_slope == pytest.approx(0.7)
    assert wheat.meter_b == pytest.approx(130.0)
    assert required_duty(200, 2.0, 4.0, wheat) != pytest.approx(before)


def test_speed_and_tilt_calibrations_apply(tmp_path: Path) -> None:
    store = cal.CalibrationStore(tmp_path)
    store.save("speed.radar", cal.to_entry(cal.speed_correction("radar", 50.0, 48.0)))
    store.save("tilt.inclinometer", cal.to_entry(cal.tilt_lowered_critical([5.2, 5.3, 5.4])))
    settings = parse_config({"inclinometer": {"zero_offset_deg": 1.0}})
    apply_calibrations(settings, tmp_path)
    assert settings.speed.correction["radar"] == pytest.approx(50.0 / 48.0)
    assert settings.inclinometer.critical_angle_deg == pytest.approx(4.3)


def test_an_entry_for_an_unknown_channel_is_reported_not_fatal(tmp_path: Path) -> None:
    store = cal.CalibrationStore(tmp_path)
    runs = [cal.RotationRun(n, 30.0, 11.2 * n / 2) for n in (20, 30, 40)]
    store.save(
        "rotation.ghost",
        cal.to_entry(cal.grams_per_rev(runs), channel="ghost", model="grams_per_rev"),
    )
    notes = apply_calibrations(parse_config({}), tmp_path)
    assert notes == ["rotation.ghost: not applied (no crop or channel named 'ghost' in the config)"]


def test_a_corrupt_calibration_file_is_ignored_with_a_message(tmp_path: Path) -> None:
    (tmp_path / "calibration.json").write_text("{not json")
    settings = parse_config({})
    notes = apply_calibrations(settings, tmp_path)
    assert len(notes) == 1 and notes[0].startswith("calibration file ignored")
    assert settings.inclinometer.zero_offset_deg == 0.0
