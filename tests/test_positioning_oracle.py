"""The benchmarks' positioning oracle: the truth's expected point plus exactly the receiver's
error, nothing else."""

from __future__ import annotations

import pytest

from benchmarks.positioning_oracle import EpochError, interpolated_error, oracle_landing


def test_without_receiver_error_the_oracle_is_the_expected_point() -> None:
    errs = [EpochError(t, 0.0, 0.0, 0.0) for t in (0.9, 1.0, 1.1)]
    assert oracle_landing((3.0, -2.0), (1.0, 1.0), 1.05, errs) == pytest.approx((3.0, -2.0))


def test_the_position_error_is_interpolated_between_the_bracketing_epochs() -> None:
    errs = [EpochError(1.0, 0.02, 0.0, 0.0), EpochError(1.1, 0.0, -0.02, 0.0)]
    got = oracle_landing((5.0, 5.0), (0.0, 0.0), 1.05, errs)
    assert got == pytest.approx((5.01, 4.99), abs=1e-12)


def test_outside_the_epochs_the_nearest_error_is_used() -> None:
    errs = [EpochError(1.0, 0.01, 0.0, 0.0), EpochError(1.1, 0.03, 0.0, 0.0)]
    assert interpolated_error(0.5, errs)[0] == pytest.approx(0.01)
    assert interpolated_error(2.0, errs)[0] == pytest.approx(0.03)


def test_a_heading_error_turns_the_outlet_clockwise_around_the_antenna() -> None:
    """An outlet 3 m north of the antenna, the heading reads 90° too much: the oracle puts it
    3 m east (clockwise), as a method trusting that heading would."""
    errs = [EpochError(0.0, 0.0, 0.0, 90.0), EpochError(1.0, 0.0, 0.0, 90.0)]
    got = oracle_landing((10.0, 23.0), (10.0, 20.0), 0.5, errs)
    assert got == pytest.approx((13.0, 20.0), abs=1e-12)


def test_an_oracle_without_epochs_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one epoch"):
        oracle_landing((0.0, 0.0), (0.0, 0.0), 1.0, [])
