"""Config keys of the speed filter's physical bound and the PWM module's watchdog."""

from __future__ import annotations

import pytest

from gateway.config import parse_config
from gateway.core.errors import ConfigError


def test_defaults_are_the_documented_ones() -> None:
    s = parse_config({})
    assert s.speed.max_accel_mps2 == 1.5
    assert s.actuators.comm_timeout_s == 2.0
    assert s.actuators.comm_timeout_register == 0x0010


@pytest.mark.parametrize(
    ("data", "line"),
    [
        (
            {"actuators": {"comm_timeout_s": 0}},
            "actuators.comm_timeout_s: Input should be greater than or equal to 0.5 (got 0)",
        ),
        (
            {"actuators": {"comm_timeout_s": 61}},
            "actuators.comm_timeout_s: Input should be less than or equal to 60 (got 61)",
        ),
        (
            {"actuators": {"comm_timeout_register": 1}},
            "actuators.comm_timeout_register: must differ from motor_register and "
            "fan_register (got 1)",
        ),
        (
            {"speed": {"max_accel_mps2": 0}},
            "speed.max_accel_mps2: Input should be greater than or equal to 0.2 (got 0)",
        ),
    ],
)
def test_bad_values_name_the_key_and_the_allowed_range(data: dict[str, object], line: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    assert info.value.problems == [line]


def test_the_controller_bounds_the_radar_trend_filter_by_the_configured_acceleration() -> None:
    from gateway.control.controller import Controller
    from gateway.control.speed import TrendFilter
    from gateway.core.alarms import AlarmBoard

    settings = parse_config({"speed": {"max_accel_mps2": 0.8, "stale_after_s": 1.5}})
    radar = Controller(settings, AlarmBoard("m1")).sources["radar"].filter
    assert isinstance(radar, TrendFilter)
    assert radar.max_slope_kmh_per_s == pytest.approx(0.8 * 3.6)
    assert radar.restart_after_s == 1.5
