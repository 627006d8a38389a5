"""Speed filter, Doppler relation and the raised/lowered decision."""

from __future__ import annotations

import pytest

from gateway.attitude import Attitude, zeroed_tilt
from gateway.speed import MovingAverage, doppler_to_kmh


def test_moving_average_uses_what_it_has_until_full() -> None:
    f = MovingAverage(12)
    assert f.add(3.0) == 3.0
    assert f.add(6.0) == 4.5
    for _ in range(20):
        f.add(10.0)
    assert f.value == 10.0
    assert len(f) == 12


def test_doppler_equation_one() -> None:
    # V = c*fd/(2 cos(theta) fi); at theta = 60 deg, cos = 0.5 -> V = c*fd/fi
    assert doppler_to_kmh(100.0, 60.0) == pytest.approx(1.079e9 * 100 / 24e9)


def test_zeroing_subtracts_the_level_ground_reading_and_wraps() -> None:
    assert zeroed_tilt(-1.25, -1.25) == 0.0
    assert zeroed_tilt(179.0, -179.0) == pytest.approx(-2.0)


@pytest.mark.parametrize(
    ("sensor", "raised"),
    # paper A Table 5 "sensor" column; +0.15 (level, sensor offset) must count as working
    [(10.13, True), (5.14, True), (0.15, False), (-4.86, False)],
)
def test_table5_is_classified_correctly_with_hysteresis(sensor: float, raised: bool) -> None:
    a = Attitude(critical_angle_deg=0.0, hysteresis_deg=0.5)
    assert a.update(sensor) is raised


def test_hysteresis_holds_state_inside_the_band() -> None:
    a = Attitude(0.0, 0.5)
    assert a.update(3.0) is True
    assert a.update(0.2) is True  # still raised until it falls below the critical angle
    assert a.update(-0.1) is False
    assert a.update(0.4) is False  # vibration inside the band does not raise it
    assert a.update(0.6) is True


def test_trend_filter_follows_a_ramp_without_lag_where_the_mean_lags() -> None:
    from gateway.speed import TrendFilter

    trend, mean = TrendFilter(12), MovingAverage(12)
    for i in range(12):
        t = i / 3
        trend.add(2.0 * t, t)
        mean.add(2.0 * t, t)
    assert trend.value == pytest.approx(2.0 * 11 / 3)
    assert mean.value == pytest.approx(2.0 * 5.5 / 3)  # ~1.8 s behind


def test_trend_filter_never_reports_negative_speed() -> None:
    from gateway.speed import TrendFilter

    f = TrendFilter(12)
    for i, v in enumerate([3.0, 2.0, 1.0, 0.0]):
        f.add(v, float(i))
    assert f.value == 0.0
