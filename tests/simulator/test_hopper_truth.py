"""The simulated hopper on load cells: the true mass follows the drill's true discharge and
the refills; a reading adds vibration, and the transmitter answers on the bus beside the
other devices only when the machine has one."""

from __future__ import annotations

import math
import random
import statistics

import pytest

from gateway.config import HopperScaleSection
from simulator.modbus_devices import Rs485Simulator
from simulator.plant import HopperDisturbances, HopperTruth


def test_the_mass_is_the_fill_plus_refills_minus_the_true_discharge() -> None:
    hopper = HopperTruth(initial_kg=500.0, refills=((60.0, 300.0),))
    assert hopper.mass_kg(10.0, discharged_kg=12.5) == 487.5
    assert hopper.mass_kg(60.0, discharged_kg=40.0) == 760.0


def test_a_reading_carries_the_configured_vibration() -> None:
    hopper = HopperTruth(initial_kg=500.0, noise_kg=2.0, rng=random.Random(1))
    readings = [hopper.reading_kg(0.0, 0.0) for _ in range(4000)]
    assert statistics.fmean(readings) == pytest.approx(500.0, abs=0.15)
    assert statistics.pstdev(readings) == pytest.approx(2.0, rel=0.05)


async def test_the_transmitter_is_on_the_bus_only_with_a_hopper() -> None:
    async with Rs485Simulator(radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0) as plain:
        assert "hopper_scale" not in plain.device_ids
    section = HopperScaleSection(enabled=True, device_id=9)
    async with Rs485Simulator(radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0,
                              hopper_kg=lambda: 1.0, hopper=section) as sim:
        assert sim.device_ids["hopper_scale"] == 9


def test_its_id_must_not_clash_with_another_device() -> None:
    with pytest.raises(ValueError, match="distinct"):
        Rs485Simulator(radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0, hopper_kg=lambda: 1.0,
                       hopper=HopperScaleSection(device_id=3))


# ---- a field's disturbances (off by default) ----------------------------------------------


def _lag_corr(xs: list[float], lag: int) -> float:
    m = statistics.fmean(xs)
    num = sum((a - m) * (b - m) for a, b in zip(xs, xs[lag:], strict=False))
    return num / sum((a - m) ** 2 for a in xs)


def test_without_disturbances_the_readings_are_the_plain_white_noise() -> None:
    plain = HopperTruth(initial_kg=500.0, noise_kg=2.0, rng=random.Random(4))
    off = HopperTruth(initial_kg=500.0, noise_kg=2.0, rng=random.Random(4),
                      disturbances=HopperDisturbances())
    assert [plain.reading_kg(t / 3, 0.0) for t in range(50)] == [
        off.reading_kg(t / 3, 0.0, accel_ms2=0.6, fan_pct=100.0) for t in range(50)]


def test_correlated_vibration_is_gauss_markov_with_its_sigma_and_correlation_time() -> None:
    hopper = HopperTruth(initial_kg=500.0, noise_kg=0.0,
                         disturbances=HopperDisturbances(vibration_kg=1.5, vibration_tau_s=10.0))
    xs = [hopper.reading_kg(i / 3.0, 0.0) - 500.0 for i in range(60_000)]
    assert statistics.pstdev(xs) == pytest.approx(1.5, rel=0.1)
    # one correlation time (30 readings at 3 Hz) apart the correlation is e^-1
    assert _lag_corr(xs, 30) == pytest.approx(math.exp(-1.0), abs=0.06)
    assert _lag_corr(xs, 3) > 0.85  # neighbours are not independent: that is the point


def test_slope_load_transfer_is_a_share_of_the_mass_and_acceleration_tilts_it_too() -> None:
    spec = HopperDisturbances(slope_transfer_pct=2.0, slope_tau_s=30.0)
    heavy = HopperTruth(initial_kg=800.0, noise_kg=0.0, disturbances=spec)
    xs = [heavy.reading_kg(i / 3.0, 0.0) - 800.0 for i in range(60_000)]
    assert statistics.pstdev(xs) == pytest.approx(16.0, rel=0.15)  # 2 % of 800 kg
    braking = HopperTruth(initial_kg=800.0, noise_kg=0.0,
                          disturbances=HopperDisturbances(accel_transfer_pct_per_ms2=2.0))
    assert braking.reading_kg(0.0, 0.0, accel_ms2=-0.6) == pytest.approx(800.0 * (1 - 0.012))


def test_drift_pressure_and_bumps() -> None:
    drifting = HopperTruth(initial_kg=500.0, noise_kg=0.0,
                           disturbances=HopperDisturbances(drift_kg_per_h=1.0))
    assert drifting.reading_kg(1800.0, 0.0) == pytest.approx(500.5)
    pressurised = HopperTruth(initial_kg=500.0, noise_kg=0.0,
                              disturbances=HopperDisturbances(pressure_kg=4.0))
    assert pressurised.reading_kg(0.0, 0.0, fan_pct=50.0) == pytest.approx(502.0)
    bumpy = HopperTruth(initial_kg=500.0, noise_kg=0.0,
                        disturbances=HopperDisturbances(bumps_per_min=2.0, bump_kg=20.0))
    xs = [bumpy.reading_kg(i / 3.0, 0.0) for i in range(3 * 3600)]  # an hour
    spikes = [x for x in xs if x != 500.0]
    assert 90 <= len(spikes) <= 150  # 2 a minute
    assert statistics.fmean(abs(x - 500.0) for x in spikes) == pytest.approx(20.0, rel=0.25)


def test_a_faulty_transmitter_reports_the_injected_value() -> None:
    hopper = HopperTruth(initial_kg=500.0)
    hopper.fault_kg = math.nan
    assert math.isnan(hopper.reading_kg(0.0, 0.0))
    hopper.fault_kg = None
    assert abs(hopper.reading_kg(0.0, 0.0) - 500.0) < 10.0


def test_a_disturbance_figure_out_of_range_is_refused() -> None:
    with pytest.raises(ValueError, match="vibration_kg"):
        HopperDisturbances(vibration_kg=-1.0)
    with pytest.raises(ValueError, match="correlation"):
        HopperDisturbances(slope_tau_s=0.0)
