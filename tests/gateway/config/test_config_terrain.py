"""The terrain compensation and trailed-implement keys of [positioning]: each bad value names
its key and the allowed range, and the check-config exit is 78."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.app.cli import main
from gateway.config import ConfigError, parse_config


@pytest.mark.parametrize(
    ("positioning", "key", "allowed"),
    [
        ({"antenna_height_m": 7.0}, "positioning.antenna_height_m", "less than or equal to 6"),
        ({"antenna_height_m": -1.0}, "positioning.antenna_height_m", "greater than or equal to 0"),
        ({"attitude_source": "imu"}, "positioning.attitude_source",
         "'none', 'dual_antenna' or 'inclinometer'"),
        ({"delay_correction_ms": 400}, "positioning.delay_correction_ms",
         "less than or equal to 300"),
        ({"hitch": {"behind_antenna_m": 1.0, "outlets_behind_hitch_m": 0}},
         "positioning.hitch.outlets_behind_hitch_m", "greater than 0"),
        ({"pitch_from_track_m": -1.0}, "positioning.pitch_from_track_m",
         "greater than or equal to 0"),
        ({"pitch_from_track_m": 60.0}, "positioning.pitch_from_track_m",
         "less than or equal to 50"),
        ({"hitch": {"behind_antenna_m": 1.0, "outlets_behind_hitch_m": 3.0, "height_m": 4}},
         "positioning.hitch.height_m", "less than or equal to 3"),
        ({"hitch": {"behind_antenna_m": 1.0, "outlets_behind_hitch_m": 3.0, "drawbar": 1}},
         "positioning.hitch.drawbar", "Extra inputs"),
    ],
)
def test_a_bad_terrain_or_hitch_key_names_itself_and_its_range(
    positioning: dict[str, object], key: str, allowed: str
) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"positioning": positioning})
    [problem] = info.value.problems
    assert problem.startswith(f"{key}: ") and allowed in problem


def test_the_inclinometer_as_attitude_source_needs_the_rs485_bus() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"rs485": {"enabled": False}, "speed": {"source": "gnss"}, "gnss": {},
                      "positioning": {"attitude_source": "inclinometer"}})
    assert "positioning.attitude_source is inclinometer" in " ".join(info.value.problems)


def test_check_config_exits_78_on_a_bad_antenna_height(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text("[positioning]\nantenna_height_m = 12\n")
    assert main(["check-config", str(f)]) == 78
    assert "positioning.antenna_height_m: " in capsys.readouterr().err


def test_terrain_and_hitch_keys_load() -> None:
    s = parse_config({"positioning": {
        "antenna_height_m": 2.5, "attitude_source": "dual_antenna", "attitude_invert": True,
        "pitch_from_track_m": 4.0,
        "hitch": {"behind_antenna_m": 1.5, "outlets_behind_hitch_m": 4.0, "height_m": 0.5},
    }})
    assert s.positioning.antenna_height_m == 2.5
    assert s.positioning.pitch_from_track_m == 4.0
    assert s.positioning.hitch is not None and s.positioning.hitch.outlets_behind_hitch_m == 4.0
    assert s.positioning.hitch.height_m == 0.5


def test_an_antenna_height_without_an_attitude_source_is_an_error_naming_both_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It passed check-config and corrected nothing: on a 3 deg slope every seed 13 cm off."""
    with pytest.raises(ConfigError) as info:
        parse_config({"positioning": {"antenna_height_m": 2.5}})
    (problem,) = info.value.problems
    assert problem.startswith("positioning.antenna_height_m: corrects nothing without "
                              "positioning.attitude_source"), problem
    assert "(got 2.5)" in problem
    f = tmp_path / "sowgate.toml"
    f.write_text('[positioning]\nantenna_height_m = 2.5\nattitude_source = "none"\n')
    assert main(["check-config", str(f)]) == 78
    assert "positioning.antenna_height_m: corrects nothing" in capsys.readouterr().err
    # with a source it is what terrain compensation needs
    ok = parse_config({"positioning": {"antenna_height_m": 2.5, "attitude_source": "dual_antenna"}})
    assert ok.positioning.antenna_height_m == 2.5
