"""The monotone curve the rate model inverts: through its points, rising, exact inverse."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config import ConfigError, parse_config
from gateway.core.monotone import MonotoneCurve

KNEE = [(20.0, 1800.0), (25.0, 2500.0), (30.0, 3050.0), (35.0, 3300.0), (40.0, 3480.0),
        (45.0, 3600.0)]


def test_it_passes_through_its_points_and_is_exact_on_a_straight_line() -> None:
    curve = MonotoneCurve.through(KNEE)
    for x, y in KNEE:
        assert curve(x) == pytest.approx(y)
    line = MonotoneCurve.through([(0, 1), (1, 3), (2, 5), (4, 9)])
    assert line(3.0) == pytest.approx(7.0)
    assert line(5.0) == pytest.approx(11.0)  # straight on beyond the ends


def test_it_rises_between_points_even_past_a_sharp_knee() -> None:
    curve = MonotoneCurve.through(KNEE)
    values = [curve(20.0 + i * 0.05) for i in range(501)]
    assert all(b > a for a, b in itertools.pairwise(values))


@given(st.lists(st.tuples(st.floats(0.1, 10.0), st.floats(0.1, 500.0)), min_size=2,
                max_size=12), st.floats(0.0, 1.0))
def test_the_inverse_finds_the_only_x_for_each_y(steps: list[tuple[float, float]],
                                                  where: float) -> None:
    x, y, pts = 0.0, 0.0, []
    for dx, dy in steps:
        x, y = x + dx, y + dy
        pts.append((x, y))
    curve = MonotoneCurve.through(pts)
    target = pts[0][1] + where * (pts[-1][1] - pts[0][1])
    assert curve(curve.inverse(target)) == pytest.approx(target, rel=1e-9, abs=1e-9)


def test_points_that_do_not_rise_are_refused() -> None:
    with pytest.raises(ValueError, match="must rise in both coordinates"):
        MonotoneCurve.through([(20, 100), (25, 90), (30, 120)])


def test_a_config_curve_that_falls_names_the_key() -> None:
    crop = {"code": 9, "rate_min_kg_ha": 1, "rate_max_kg_ha": 9, "default_rate_kg_ha": 5,
            "motor_slope": 0.6, "motor_intercept": -20, "startup_duty_pct": 30,
            "meter_a": 0, "meter_b": 100, "meter_c": 0, "omega_min_rpm": 20,
            "omega_max_rpm": 45, "fan_high_pct": 80, "fan_low_pct": 20,
            "meter_curve": [[20, 100], [30, 90], [40, 120]]}
    with pytest.raises(ConfigError, match="meter_curve"):
        parse_config({"control": {"crop": "bean", "crops": {"bean": crop}}})
