"""The hopper scale's weight transmitter on the simulated RS485 bus, over real ptys: every
register format decodes to kg, and a value no load cell reports is a named BadReading."""

from __future__ import annotations

import math

import pytest

from drivers.errors import DeviceUnavailable
from drivers.modbus_bus import ModbusBus
from drivers.rs485_devices import BadReading, HopperScale, Radar
from gateway.config import HopperScaleSection, RadarSection
from simulator.modbus_devices import Rs485Simulator

TIMEOUT_S = 0.15


def make_bus(path: str) -> ModbusBus:
    return ModbusBus(path, timeout_s=TIMEOUT_S, retries=0, reconnect_max_s=0.2)


class Hopper:
    kg = 612.4


@pytest.mark.parametrize(
    ("data_type", "word_order", "scale", "resolution_kg"),
    [
        ("int32", "big", 1.0, 0.001),  # the default: grams, high word first
        ("int32", "little", 10.0, 0.01),
        ("uint16", "big", 100.0, 0.1),
        ("int16", "big", 50.0, 0.05),
        ("float32", "big", 1000.0, 1e-4),
        ("float32", "little", 1000.0, 1e-4),
    ],
)
async def test_each_register_format_reads_the_hopper_mass(
    data_type: str, word_order: str, scale: float, resolution_kg: float
) -> None:
    section = HopperScaleSection(
        enabled=True, data_type=data_type, word_order=word_order, scale=scale, register=7
    )
    hopper = Hopper()
    async with (
        Rs485Simulator(radar_kmh=lambda: 5.0, tilt_deg=lambda: 0.0,
                       hopper_kg=lambda: hopper.kg, hopper=section) as sim,
        make_bus(sim.device_path) as bus,
    ):
        scale_dev = HopperScale(bus, section)
        assert await scale_dev.read() == pytest.approx(612.4, abs=resolution_kg)
        hopper.kg = 3.25 if data_type != "int16" else -1.5
        expected = hopper.kg
        assert await scale_dev.read() == pytest.approx(expected, abs=resolution_kg)
        # on the same bus, polled with the radar
        assert await Radar(bus, RadarSection()).read() == pytest.approx(5.0)
        assert sim.requests_seen[section.device_id] == 2
        assert scale_dev.available


@pytest.mark.parametrize("value", [math.nan, math.inf, 99_999.0, -500.0])
async def test_a_reading_no_load_cell_gives_is_a_bad_reading(value: float) -> None:
    section = HopperScaleSection(enabled=True, data_type="float32", scale=1000.0,
                                 capacity_kg=3000.0)
    async with (
        Rs485Simulator(radar_kmh=lambda: 5.0, tilt_deg=lambda: 0.0,
                       hopper_kg=lambda: value, hopper=section) as sim,
        make_bus(sim.device_path) as bus,
    ):
        scale = HopperScale(bus, section)
        with pytest.raises(BadReading, match=r"hopper_scale \(id 4\)"):
            await scale.read()
        with pytest.raises(BadReading):
            await scale.read()
        assert scale.bad_readings == 2  # counted (the daemon's alarm message shows it)


async def test_a_silent_scale_is_unavailable_and_the_bus_goes_on() -> None:
    section = HopperScaleSection(enabled=True)
    async with (
        Rs485Simulator(radar_kmh=lambda: 5.0, tilt_deg=lambda: 0.0,
                       hopper_kg=lambda: 100.0, hopper=section) as sim,
        make_bus(sim.device_path) as bus,
    ):
        scale_dev = HopperScale(bus, section)
        sim.set_silent(section.device_id, True)
        with pytest.raises(DeviceUnavailable, match="hopper_scale"):
            await scale_dev.read()
        assert not scale_dev.available
        assert await Radar(bus, RadarSection()).read() == pytest.approx(5.0)
        sim.set_silent(section.device_id, False)
        assert await scale_dev.read() == pytest.approx(100.0)
