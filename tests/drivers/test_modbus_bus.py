"""ModbusBus and the typed RS485 devices against the simulated bus, over real ptys.

Each fault a seeder's RS485 bus produces in the field (dead device, bad CRC, line noise,
unplugged adapter, a register the device does not have) must end as a named DriverError,
be counted, and leave the bus usable.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from drivers.errors import DeviceRejected, DeviceUnavailable
from drivers.modbus_bus import ModbusBus
from drivers.rs485_devices import Inclinometer, PwmModule, Radar
from gateway.config import ActuatorsSection, InclinometerSection, RadarSection, Rs485Section
from protocol.errors import FieldError
from simulator.modbus_devices import Rs485Simulator
from tests.helpers import WAIT_S, Plant, eventually

TIMEOUT_S = 0.15


@pytest.fixture
def plant() -> Plant:
    return Plant(kmh=6.4, tilt=8.75)


def make_bus(path: str, retries: int = 0) -> ModbusBus:
    return ModbusBus(path, timeout_s=TIMEOUT_S, retries=retries, reconnect_max_s=0.2)


@pytest.fixture
async def bus(sim: Rs485Simulator) -> AsyncIterator[ModbusBus]:
    async with make_bus(sim.device_path) as b:
        assert b.connected
        yield b


@pytest.fixture
def radar(bus: ModbusBus) -> Radar:
    return Radar(bus, RadarSection())


@pytest.fixture
def inclinometer(bus: ModbusBus) -> Inclinometer:
    return Inclinometer(bus, InclinometerSection())


@pytest.fixture
def pwm(bus: ModbusBus) -> PwmModule:
    return PwmModule(bus, ActuatorsSection())


# --- normal operation ---------------------------------------------------------------------


async def test_radar_reads_speed_in_kmh(radar: Radar, bus: ModbusBus, plant: Plant) -> None:
    assert await radar.read() == pytest.approx(6.4)
    plant.kmh = 11.93
    assert await radar.read() == pytest.approx(11.93)
    stats = bus.device_stats("radar")
    assert (stats.ok, stats.failures, stats.available) == (2, 0, True)
    assert radar.available


async def test_doppler_radar_applies_equation_1(plant: Plant) -> None:
    """A radar reporting the Doppler shift (0.1 Hz per count) reads back as ground speed."""
    section = RadarSection(
        data_type="uint32", scale=0.1, unit="doppler_hz", mount_angle_deg=49.5
    )
    async with (
        Rs485Simulator(radar_kmh=lambda: plant.kmh, tilt_deg=lambda: 0.0, radar=section) as s,
        make_bus(s.device_path) as b,
    ):
        assert await Radar(b, section).read() == pytest.approx(6.4, abs=0.01)


@pytest.mark.parametrize("layout", ["witmotion16", "witmotion32"])
@pytest.mark.parametrize("axis", ["roll", "pitch"])
async def test_inclinometer_reads_the_configured_axis(
    plant: Plant, layout: str, axis: str
) -> None:
    section = InclinometerSection(layout=layout, axis=axis)
    async with (
        Rs485Simulator(
            radar_kmh=lambda: 0.0, tilt_deg=lambda: plant.tilt, inclinometer=section
        ) as s,
        make_bus(s.device_path) as b,
    ):
        incl = Inclinometer(b, section)
        assert await incl.read() == pytest.approx(8.75, abs=0.006)
        plant.tilt = -1.25
        assert await incl.read() == pytest.approx(-1.25, abs=0.006)


async def test_pwm_duty_writes_reach_the_module(
    pwm: PwmModule, sim: Rs485Simulator, plant: Plant
) -> None:
    await pwm.write_duty("motor", 87.7)
    await pwm.write_duty("fan", 85.0)
    assert plant.duties == [("motor", 87.7), ("fan", 85.0)]
    assert await pwm.read_duty("motor") == pytest.approx(87.7)
    assert pwm.available


async def test_pwm_comm_loss_timeout_is_written_and_read_back(
    pwm: PwmModule, sim: Rs485Simulator
) -> None:
    assert await pwm.set_comm_timeout(2.0) == 2.0
    assert sim.comm_timeout_s == 2.0 and sim.comm_timeout_writes == 1


async def test_a_pwm_module_without_the_watchdog_is_rejected_by_name(plant: Plant) -> None:
    async with (
        Rs485Simulator(
            radar_kmh=lambda: plant.kmh, tilt_deg=lambda: plant.tilt, pwm_watchdog=False
        ) as s,
        make_bus(s.device_path) as b,
    ):
        with pytest.raises(DeviceRejected, match=r"pwm \(id 3\) rejected write 20 to register 16"):
            await PwmModule(b, ActuatorsSection()).set_comm_timeout(2.0)


async def test_out_of_range_duty_is_refused_before_touching_the_bus(
    pwm: PwmModule, bus: ModbusBus, plant: Plant
) -> None:
    with pytest.raises(FieldError, match=r"pwm motor: duty 100\.5 % outside"):
        await pwm.write_duty("motor", 100.5)
    with pytest.raises(ValueError, match="unknown channel 'pump'"):
        await pwm.write_duty("pump", 10.0)  # type: ignore[arg-type]
    assert plant.duties == []
    assert "pwm" not in bus.stats


async def test_bad_request_arguments_are_named(bus: ModbusBus) -> None:
    with pytest.raises(ValueError, match=r"radar: count must be 1\.\.125"):
        await bus.read_holding("radar", 1, 0, 0)
    with pytest.raises(ValueError, match=r"radar: device_id must be 1\.\.247"):
        await bus.read_holding("radar", 0, 0, 1)
    with pytest.raises(ValueError, match=r"pwm: register value must be 0\.\.65535"):
        await bus.write_register("pwm", 3, 0, 70000)


async def test_requests_from_concurrent_tasks_never_interleave(
    radar: Radar, inclinometer: Inclinometer, pwm: PwmModule, plant: Plant
) -> None:
    """Poll loop, duty writes and HMI refresh share one half-duplex line."""
    calls = []
    for i in range(6):
        calls += [radar.read(), inclinometer.read(), pwm.write_duty("motor", float(i))]
    results = await asyncio.gather(*calls)
    speeds = results[0::3]
    tilts = results[1::3]
    assert speeds == pytest.approx([6.4] * 6)
    assert tilts == pytest.approx([8.75] * 6, abs=0.006)
    assert [d for _, d in plant.duties] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]


# --- faults -------------------------------------------------------------------------------


async def test_silent_device_times_out_by_name_while_the_others_keep_working(
    sim: Rs485Simulator, bus: ModbusBus, radar: Radar, inclinometer: Inclinometer,
    pwm: PwmModule,
) -> None:
    sim.set_silent(1, True)
    with pytest.raises(DeviceUnavailable, match=r"radar \(id 1\): no reply .* within 0.15 s"):
        await radar.read()
    assert await inclinometer.read() == pytest.approx(8.75, abs=0.006)
    await pwm.write_duty("fan", 20.0)
    stats = bus.device_stats("radar")
    assert (stats.timeouts, stats.available, stats.consecutive_failures) == (1, False, 1)
    assert "no reply" in (stats.last_error or "")
    assert inclinometer.available and pwm.available
    sim.set_silent(1, False)
    assert await radar.read() == pytest.approx(6.4)
    assert radar.available and bus.device_stats("radar").consecutive_failures == 0


async def test_corrupted_crc_is_counted_as_garbled_and_the_next_request_is_fine(
    sim: Rs485Simulator, bus: ModbusBus, radar: Radar
) -> None:
    sim.corrupt_next_crc(1)
    with pytest.raises(DeviceUnavailable, match=r"radar \(id 1\): garbled reply .*CRC"):
        await radar.read()
    assert await radar.read() == pytest.approx(6.4)
    stats = bus.device_stats("radar")
    assert (stats.garbled, stats.timeouts, stats.ok) == (1, 0, 1)


async def test_retries_absorb_a_single_bad_crc(sim: Rs485Simulator, plant: Plant) -> None:
    """With retries=1 pymodbus re-asks once; the caller never sees the bad frame."""
    async with make_bus(sim.device_path, retries=1) as b:
        sim.corrupt_next_crc(1)
        assert await Radar(b, RadarSection()).read() == pytest.approx(6.4)
        assert sim.requests_seen[1] == 2


async def test_line_noise_before_a_reply_is_recovered_from(
    sim: Rs485Simulator, bus: ModbusBus, radar: Radar
) -> None:
    """Noise that hides the reply is reported as garbled; the following request works."""
    sim.inject_bytes(b"\x00\x00\x00")  # (0x00, 0x01) looks like a frame start to pymodbus
    with pytest.raises(DeviceUnavailable, match="garbled reply"):
        await radar.read()
    assert await radar.read() == pytest.approx(6.4)
    for _ in range(4):  # random noise: at most the one request it lands on is lost
        sim.inject_garbage(12)
        try:
            assert await radar.read() == pytest.approx(6.4)
        except DeviceUnavailable as exc:
            assert "radar" in str(exc)
        assert await radar.read() == pytest.approx(6.4)
    assert bus.device_stats("radar").garbled >= 1


async def test_exception_response_raises_device_rejected(
    sim: Rs485Simulator, bus: ModbusBus, pwm: PwmModule
) -> None:
    with pytest.raises(
        DeviceRejected, match=r"radar \(id 1\) rejected read .*exception 2 \(illegal data address"
    ):
        await bus.read_holding("radar", 1, 5, 1)
    with pytest.raises(DeviceRejected, match=r"pwm \(id 3\) rejected write 1001.*exception 3"):
        await bus.write_register("pwm", 3, 0, 1001)
    assert bus.device_stats("radar").exceptions == 1
    assert not bus.available("radar")
    await pwm.write_duty("motor", 10.0)  # the bus is fine afterwards


async def test_device_failure_in_the_sensor_is_rejected_not_hung(plant: Plant) -> None:
    def broken() -> float:
        return math.nan

    async with (
        Rs485Simulator(radar_kmh=broken, tilt_deg=lambda: 0.0) as s,
        make_bus(s.device_path) as b,
    ):
        with pytest.raises(DeviceRejected, match="device failure"):
            await Radar(b, RadarSection()).read()


async def test_vanished_port_fails_fast_then_reconnects_by_itself(
    sim: Rs485Simulator, bus: ModbusBus, radar: Radar, pwm: PwmModule
) -> None:
    assert await radar.read() == pytest.approx(6.4)
    sim.vanish()
    await eventually(lambda: not bus.connected, what="the bus to notice the vanished port")
    started = time.monotonic()
    with pytest.raises(DeviceUnavailable, match=r"radar \(id 1\): .*port .* is down"):
        await radar.read()
    with pytest.raises(DeviceUnavailable, match=r"pwm \(id 3\)"):
        await pwm.write_duty("motor", 0.0)
    assert time.monotonic() - started < TIMEOUT_S * 2  # no timeout wait while unplugged
    assert bus.device_stats("radar").port_errors == 1
    await asyncio.sleep(0.3)  # a few reconnect attempts fail meanwhile
    sim.restore()
    await eventually(lambda: bus.connected, what="the bus to reopen the restored port")
    assert await radar.read() == pytest.approx(6.4)
    assert bus.reconnects == 1 and radar.available


async def test_port_missing_at_start_is_not_fatal(tmp_path: Path, plant: Plant) -> None:
    """The daemon starts before the USB adapter enumerates; the bus picks it up later."""
    link = tmp_path / "ttyRS485"
    async with make_bus(str(link)) as b:
        assert not b.connected
        with pytest.raises(DeviceUnavailable, match=r"radar \(id 1\).*does not exist"):
            await Radar(b, RadarSection()).read()
        async with Rs485Simulator(
            radar_kmh=lambda: plant.kmh, tilt_deg=lambda: 0.0, link_path=link
        ):
            assert await b.wait_connected(WAIT_S)
            assert await Radar(b, RadarSection()).read() == pytest.approx(6.4)


async def test_a_dead_device_is_logged_once_not_per_request(
    sim: Rs485Simulator, bus: ModbusBus, radar: Radar, caplog: pytest.LogCaptureFixture
) -> None:
    sim.set_silent(1, True)
    with caplog.at_level(logging.INFO):
        for _ in range(4):
            with pytest.raises(DeviceUnavailable):
                await radar.read()
        sim.set_silent(1, False)
        await radar.read()
    ours = [r for r in caplog.records if r.name == "drivers.modbus_bus"]
    warnings = [r for r in ours if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "radar (id 1)" in warnings[0].getMessage()
    assert any("answering again after 4" in r.getMessage() for r in ours)
    assert not [r for r in caplog.records if "No response received" in r.getMessage()]
    # nor pymodbus's own marker for the duplicate it would have logged (it flooded the fault
    # matrix's serial rows on a loaded machine)
    with caplog.at_level(logging.INFO):
        logging.getLogger("pymodbus.logging").warning("Repeating....")
    assert not [r for r in caplog.records if "Repeating...." in r.getMessage()]
    assert bus.device_stats("radar").timeouts == 4


async def test_from_config_and_close_are_clean(sim: Rs485Simulator) -> None:
    b = ModbusBus.from_config(Rs485Section(port=sim.device_path, timeout_s=TIMEOUT_S))
    await b.start()
    assert b.connected
    await b.close()
    await b.close()
    assert not b.connected
    with pytest.raises(DeviceUnavailable, match=r"down \(bus closed\)"):
        await b.read_holding("radar", 1, 0, 1)


def test_invalid_bus_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="parity"):
        ModbusBus("/dev/null", parity="X")
    with pytest.raises(ValueError, match="stopbits"):
        ModbusBus("/dev/null", stopbits=3)
