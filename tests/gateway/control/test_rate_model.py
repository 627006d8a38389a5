"""Paper A's rate chain, checked against the worked examples in seeds.md."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config.machine import default_crops
from gateway.control.rate_model import (
    duty_for_omega,
    flow_at,
    flow_for_rate,
    max_speed_kmh,
    omega_for_flow,
    plan_duty,
    rate_for_flow,
    required_duty,
)
from gateway.core.errors import OutsideCalibrationError, TooFastError

CROPS = default_crops()
WHEAT, RAPE = CROPS["wheat"], CROPS["rapeseed"]


def test_wheat_225_at_5_kmh_needs_about_87_7_percent() -> None:
    assert flow_for_rate(225, 2.0, 5.0) == pytest.approx(3750.0)
    assert omega_for_flow(3750.0, WHEAT) == pytest.approx(38.65, abs=0.01)
    assert required_duty(225, 2.0, 5.0, WHEAT) == pytest.approx(87.7, abs=0.05)


def test_rapeseed_6_at_5_kmh_needs_about_48_1_percent() -> None:
    assert flow_for_rate(6, 2.0, 5.0) == pytest.approx(100.0)
    assert omega_for_flow(100.0, RAPE) == pytest.approx(19.93, abs=0.01)
    assert required_duty(6, 2.0, 5.0, RAPE) == pytest.approx(48.1, abs=0.05)


def test_wheat_225_at_6_kmh_is_too_fast_and_names_the_max_speed() -> None:
    with pytest.raises(TooFastError, match=r"too fast for target rate, max 5\.8 km/h"):
        required_duty(225, 2.0, 6.0, WHEAT)
    plan = plan_duty(225, 2.0, 6.0, WHEAT)
    assert plan.duty_pct == 100.0  # keeps sowing as close as it can
    assert isinstance(plan.problem, TooFastError)


def test_max_speed_is_where_duty_reaches_100_percent() -> None:
    v = max_speed_kmh(225, 2.0, WHEAT)
    assert plan_duty(225, 2.0, v - 0.01, WHEAT).duty_pct < 100.0
    assert plan_duty(225, 2.0, v + 0.05, WHEAT).duty_pct == 100.0


def test_shaft_speed_below_fitted_range_is_reported() -> None:
    with pytest.raises(OutsideCalibrationError, match="outside calibrated range"):
        required_duty(4.5, 2.0, 0.8, RAPE)


def test_flow_beyond_the_parabola_peak_is_too_fast_not_a_math_error() -> None:
    plan = plan_duty(7.5, 2.0, 200.0, RAPE)
    assert isinstance(plan.problem, TooFastError)


def test_zero_speed_meters_nothing() -> None:
    assert plan_duty(225, 2.0, 0.0, WHEAT).duty_pct == 0.0
    assert rate_for_flow(100.0, 2.0, 0.0) == 0.0


@given(st.floats(min_value=5.0, max_value=30.0))
def test_inverse_of_eq6_is_exact_on_the_rising_branch(omega: float) -> None:
    assert omega_for_flow(flow_at(omega, RAPE), RAPE) == pytest.approx(omega, rel=1e-9)


@given(
    st.floats(min_value=120, max_value=225),
    st.floats(min_value=2.0, max_value=5.5),
)
def test_commanded_duty_reproduces_the_target_rate(rate: float, speed: float) -> None:
    plan = plan_duty(rate, 2.0, speed, WHEAT)
    if plan.problem is None:
        omega = WHEAT.motor_slope * plan.duty_pct + WHEAT.motor_intercept
        assert rate_for_flow(flow_at(omega, WHEAT), 2.0, speed) == pytest.approx(rate, rel=1e-9)
        assert duty_for_omega(omega, WHEAT) == pytest.approx(plan.duty_pct)
