"""What ``sowgate demo`` tells the user about the applied rate, from the simulator's truth."""

from __future__ import annotations

import pytest

from gateway.demo import summary, truth_report
from simulator.machine import STARTUP_TRANSIENT_S, Truth

WIDTH_M = 2.0
STEP_S = 0.1
SPEED_MS = 1.0  # 3.6 km/h


def _sow(truth: Truth, seconds: float, kg_ha: float) -> None:
    """Sow ``seconds`` at 1 m/s, discharging exactly ``kg_ha``."""
    for _ in range(round(seconds / STEP_S)):
        moved = SPEED_MS * STEP_S
        grams = kg_ha * 1000 * moved * WIDTH_M / 1e4
        truth.record(grams, moved, STEP_S, sowing=True, width_m=WIDTH_M)


def _stand(truth: Truth, seconds: float) -> None:
    for _ in range(round(seconds / STEP_S)):
        truth.record(0.0, 0.0, STEP_S, sowing=False, width_m=WIDTH_M)


def test_start_of_every_pass_is_kept_apart_from_settled_sowing() -> None:
    truth = Truth()
    for _ in range(2):  # two passes, each starting under-dosed while catching up
        _sow(truth, STARTUP_TRANSIENT_S, 3.0)
        _sow(truth, 20.0, 6.0)
        _stand(truth, 2.0)
    assert truth.sown_m == pytest.approx(2 * (STARTUP_TRANSIENT_S + 20.0))
    assert truth.settled_m == pytest.approx(40.0)
    assert truth.settled_kg_ha() == pytest.approx(6.0)
    assert truth.applied_kg_ha() == pytest.approx((5 * 3.0 + 20 * 6.0) / 25)
    report = truth_report(truth, 6.0)
    assert report["settled_rate_error_pct"] == pytest.approx(0.0, abs=1e-9)
    assert report["rate_error_pct"] == pytest.approx(-10.0)
    line = summary(report, 6.0)
    assert line.startswith("demo finished: 50.0 m sown, applied 5.40 kg/ha")
    assert "(target 6, error -10.00 %)" in line
    assert f"after the first {STARTUP_TRANSIENT_S:g} s of each pass 6.00 kg/ha" in line
    assert "error +0.00 % over 40.0 m" in line


def test_nothing_sown_is_said_not_reported_as_zero_error() -> None:
    truth = Truth()
    _stand(truth, 4.0)
    line = summary(truth_report(truth, 6.0), 6.0)
    assert "nothing sown yet" in line
    assert "%" not in line  # the old line read "applied 0.00 kg/ha ..., error +0.00 %"


def test_a_run_that_never_left_the_start_up_is_flagged_not_representative() -> None:
    truth = Truth()
    _stand(truth, 4.0)
    _sow(truth, 2.0, 1.0)
    report = truth_report(truth, 6.0)
    assert report["settled_kg_ha"] is None
    line = summary(report, 6.0)
    assert "2.0 m sown" in line and "error -83.33 %" in line
    assert "not representative" in line and "--duration 60" in line
