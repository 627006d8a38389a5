"""The simulated hopper on load cells: the true mass follows the drill's true discharge and
the refills; a reading adds vibration, and the transmitter answers on the bus beside the
other devices only when the machine has one."""

from __future__ import annotations

import random
import statistics

import pytest

from gateway.config import HopperScaleSection
from simulator.modbus_devices import Rs485Simulator
from simulator.plant import HopperTruth


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
