"""The simulated RS485 bus, checked with a plain pymodbus master over real ptys, and the pty
helper it is built on."""

from __future__ import annotations

import asyncio
import os
import select
import termios
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusSerialClient
from pymodbus.exceptions import ModbusIOException

from gateway.config import ActuatorsSection, InclinometerSection, RadarSection
from protocol.registers import (
    PWM_COMM_TIMEOUT_REGISTER,
    RadarFormat,
    decode_angle,
    encode_angle,
)
from simulator.modbus_devices import FAULTS, Fault, Rs485Simulator
from simulator.pty_link import PtyPair
from tests.helpers import Plant, eventually

TIMEOUT_S = 0.15


@pytest.fixture
def plant() -> Plant:
    """Values the simulated devices report; tests change them between requests."""
    return Plant(kmh=5.25, tilt=-1.25)


@pytest.fixture
async def master(sim: Rs485Simulator) -> AsyncIterator[AsyncModbusSerialClient]:
    client = AsyncModbusSerialClient(
        sim.device_path, baudrate=9600, timeout=TIMEOUT_S, retries=0, reconnect_delay=0
    )
    assert await client.connect()
    yield client
    client.close()


def path_exists(path: str) -> bool:
    """Whether ``path`` resolves (a dangling symlink does not)."""
    return os.path.exists(path)


def link_exists(path: str) -> bool:
    """Whether ``path`` itself is there, dangling or not."""
    return os.path.lexists(path)


# --- PtyPair ------------------------------------------------------------------------------


def test_pty_pair_is_raw_and_carries_bytes_both_ways(tmp_path: Path) -> None:
    """No echo, no newline translation: a pty must behave like a cable."""
    with PtyPair(tmp_path / "ttyX") as pair:
        assert os.path.realpath(pair.device_path) == pair.slave_path
        fd = os.open(pair.device_path, os.O_RDWR | os.O_NOCTTY)
        try:
            attrs = termios.tcgetattr(fd)
            assert not attrs[3] & termios.ECHO
            os.write(fd, b"\x01\x03\n\r")
            select.select([pair.master_fd], [], [], 1.0)
            assert os.read(pair.master_fd, 64) == b"\x01\x03\n\r"
            os.write(pair.master_fd, b"\x00\xff\n")
            select.select([fd], [], [], 1.0)
            assert os.read(fd, 64) == b"\x00\xff\n"
        finally:
            os.close(fd)


def test_closing_a_pty_pair_removes_its_link_and_breaks_the_peer(tmp_path: Path) -> None:
    """The daemon's fd then fails with EIO, as with an unplugged USB adapter."""
    pair = PtyPair(tmp_path / "ttyX")
    fd = os.open(pair.device_path, os.O_RDWR | os.O_NOCTTY)
    try:
        pair.close()
        pair.close()  # idempotent
        assert not os.path.lexists(tmp_path / "ttyX")
        readable, _, _ = select.select([fd], [], [], 1.0)
        assert readable == [fd]  # hang-up: readable at once ...
        try:
            data: bytes | None = os.read(fd, 1)
        except OSError:  # ... and the read fails (EIO) or hits end of file
            data = None
        assert not data
        with pytest.raises(OSError, match="closed"):
            _ = pair.master_fd
    finally:
        os.close(fd)


def test_pty_pair_without_link_uses_the_pts_path() -> None:
    with PtyPair() as pair:
        assert pair.device_path == pair.slave_path
        assert pair.device_path.startswith("/dev/pts/")


# --- device values ------------------------------------------------------------------------


async def test_radar_reports_the_plant_speed(
    sim: Rs485Simulator, master: AsyncModbusSerialClient, plant: Plant
) -> None:
    """Default radar: uint16 at register 0, 0.01 km/h per count."""
    rr = await master.read_holding_registers(0, count=1, device_id=1)
    assert rr.registers == [525]
    plant.kmh = 7.9
    rr = await master.read_holding_registers(0, count=1, device_id=1)
    assert rr.registers == [790]


async def test_radar_follows_the_configured_format(plant: Plant) -> None:
    """A Doppler radar with float32 little-endian words at register 10, id 7."""
    section = RadarSection(
        device_id=7, address=10, data_type="float32", word_order="little", scale=1.0,
        unit="doppler_hz", mount_angle_deg=45.0,
    )
    async with Rs485Simulator(
        radar_kmh=lambda: plant.kmh, tilt_deg=lambda: 0.0, radar=section
    ) as simulator:
        client = AsyncModbusSerialClient(simulator.device_path, timeout=TIMEOUT_S, retries=0)
        try:
            assert await client.connect()
            rr = await client.read_holding_registers(10, count=2, device_id=7)
            fmt = RadarFormat("float32", "little", 1.0, "doppler_hz", 45.0)
            assert fmt.decode_kmh(rr.registers) == pytest.approx(5.25, rel=1e-6)
        finally:
            client.close()


async def test_inclinometer_puts_the_tilt_on_the_configured_axis_only(
    master: AsyncModbusSerialClient, plant: Plant
) -> None:
    rr = await master.read_holding_registers(0x3D, count=3, device_id=0x50)
    roll, pitch, yaw = (decode_angle([r], "witmotion16") for r in rr.registers)
    assert pitch == pytest.approx(-1.25, abs=0.006)
    assert roll == 0.0 and yaw == 0.0


async def test_inclinometer_witmotion32_layout(plant: Plant) -> None:
    section = InclinometerSection(layout="witmotion32", axis="roll")
    async with Rs485Simulator(
        radar_kmh=lambda: 0.0, tilt_deg=lambda: plant.tilt, inclinometer=section
    ) as simulator:
        client = AsyncModbusSerialClient(simulator.device_path, timeout=TIMEOUT_S, retries=0)
        try:
            assert await client.connect()
            rr = await client.read_holding_registers(0x3D, count=2, device_id=0x50)
            assert rr.registers == encode_angle(-1.25, "witmotion32")
        finally:
            client.close()


async def test_pwm_writes_reach_on_duty(
    sim: Rs485Simulator, master: AsyncModbusSerialClient, plant: Plant
) -> None:
    await master.write_register(0, 877, device_id=3)
    await master.write_register(1, 250, device_id=3)
    assert plant.duties == [("motor", 87.7), ("fan", 25.0)]
    assert sim.duty_pct == {"motor": 87.7, "fan": 25.0}
    rr = await master.read_holding_registers(0, count=2, device_id=3)
    assert rr.registers == [877, 250]


async def test_pwm_refuses_more_than_100_percent(
    sim: Rs485Simulator, master: AsyncModbusSerialClient, plant: Plant
) -> None:
    """Exception 3 (illegal data value) and nothing changes."""
    rr = await master.write_register(0, 1001, device_id=3)
    assert rr.isError() and rr.exception_code == 3
    assert plant.duties == []


async def test_unmapped_register_gives_illegal_address(master: AsyncModbusSerialClient) -> None:
    rr = await master.read_holding_registers(5, count=1, device_id=1)
    assert rr.isError() and rr.exception_code == 2


async def test_a_failing_plant_value_becomes_device_failure(plant: Plant) -> None:
    """A speed the register format cannot hold is answered with exception 4, not a crash."""
    async with Rs485Simulator(radar_kmh=lambda: -3.0, tilt_deg=lambda: 0.0) as simulator:
        client = AsyncModbusSerialClient(simulator.device_path, timeout=TIMEOUT_S, retries=0)
        try:
            assert await client.connect()
            rr = await client.read_holding_registers(0, count=1, device_id=1)
            assert rr.isError() and rr.exception_code == 4
        finally:
            client.close()


def test_duplicate_device_ids_are_refused() -> None:
    with pytest.raises(ValueError, match="distinct"):
        Rs485Simulator(
            radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0, actuators=ActuatorsSection(device_id=1)
        )


# --- faults -------------------------------------------------------------------------------


async def test_unknown_device_id_stays_silent(
    sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    """A real bus says nothing for an id nobody owns (pymodbus alone would answer)."""
    with pytest.raises(ModbusIOException):
        await master.read_holding_registers(0, count=1, device_id=42)
    assert sim.replies_dropped == 1


async def test_silent_device_neither_answers_nor_acts(
    sim: Rs485Simulator, master: AsyncModbusSerialClient, plant: Plant
) -> None:
    sim.set_silent(3, True)
    with pytest.raises(ModbusIOException):
        await master.write_register(0, 500, device_id=3)
    assert plant.duties == []
    rr = await master.read_holding_registers(0, count=1, device_id=1)
    assert rr.registers == [525]  # the others still answer
    sim.set_silent(3, False)
    await master.write_register(0, 500, device_id=3)
    assert plant.duties == [("motor", 50.0)]


async def test_corrupted_crc_reply_is_dropped_by_the_master_then_the_next_is_fine(
    sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    sim.corrupt_next_crc(1)
    with pytest.raises(ModbusIOException):
        await master.read_holding_registers(0, count=1, device_id=1)
    rr = await master.read_holding_registers(0, count=1, device_id=1)
    assert rr.registers == [525]


async def test_noise_before_a_reply_is_skipped_when_it_cannot_start_a_frame(
    sim: Rs485Simulator, master: AsyncModbusSerialClient, plant: Plant
) -> None:
    """pymodbus's framer hunts past bytes that do not look like a frame start: zeros before
    id 0x50 (not a function code) are skipped and the reply still decodes."""
    sim.inject_bytes(b"\x00\x00\x00")
    rr = await master.read_holding_registers(0x3E, count=1, device_id=0x50)
    assert rr.registers == encode_angle(plant.tilt, "witmotion16")


async def test_random_garbage_costs_at_most_one_reply(
    sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    for _ in range(5):
        sim.inject_garbage(9)
        try:
            rr = await master.read_holding_registers(0, count=1, device_id=1)
            assert rr.registers == [525]
        except ModbusIOException:
            pass
        rr = await master.read_holding_registers(0, count=1, device_id=1)
        assert rr.registers == [525]


def test_garbage_size_is_bounded() -> None:
    sim = Rs485Simulator(radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0)
    with pytest.raises(ValueError, match="n_bytes"):
        sim.inject_garbage(0)
    with pytest.raises(ValueError, match="n_bytes"):
        sim.inject_garbage(10_000)


async def test_vanish_breaks_the_open_port_and_restore_brings_the_same_path_back(
    sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    path = sim.device_path
    sim.vanish()
    assert not link_exists(path)
    # the master notices the EIO on its own
    await eventually(lambda: not master.connected, 1.0, "the master to notice", interval=0.02)
    assert not await master.connect()  # nothing to open while unplugged
    sim.restore()
    assert sim.device_path == path and path_exists(path)
    assert await master.connect()
    rr = await master.read_holding_registers(0, count=1, device_id=1)
    assert rr.registers == [525]


async def test_close_removes_the_device_path(plant: Plant) -> None:
    simulator = Rs485Simulator(radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0)
    await simulator.start()
    path = simulator.device_path
    assert path_exists(path)
    await simulator.close()
    await simulator.close()
    assert not link_exists(path)


# --- the fault matrix of one device (set_fault) ---------------------------------------------


@pytest.mark.parametrize("fault", FAULTS)
async def test_every_fault_spoils_each_reply_until_cleared(
    fault: Fault, sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    """The master gets nothing usable from a faulty radar, the other devices are unaffected,
    and clearing the fault brings the radar back."""
    sim.set_fault(1, fault)
    for _ in range(3):
        try:
            rr = await master.read_holding_registers(0, count=1, device_id=1)
        except ModbusIOException:
            continue
        assert fault == "exception", f"{fault}: a reply got through: {rr}"
        assert rr.isError() and rr.exception_code == 4
    rr = await master.read_holding_registers(0x3E, count=1, device_id=0x50)
    assert not rr.isError()
    sim.set_fault(1, None)
    rr = await master.read_holding_registers(0, count=1, device_id=1)
    assert rr.registers == [525]


def test_an_unknown_fault_is_refused() -> None:
    sim = Rs485Simulator(radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0)
    with pytest.raises(ValueError, match="unknown fault"):
        sim.set_fault(1, "gremlins")  # type: ignore[arg-type]


async def test_a_held_radar_reading_overrides_the_plant(
    sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    sim.hold_radar(0.0)
    assert (await master.read_holding_registers(0, count=1, device_id=1)).registers == [0]
    sim.hold_radar(None)
    assert (await master.read_holding_registers(0, count=1, device_id=1)).registers == [525]


# --- the PWM module's communication-loss watchdog -----------------------------------------


async def test_pwm_watchdog_stops_both_outputs_when_the_master_goes_quiet(
    sim: Rs485Simulator, master: AsyncModbusSerialClient, plant: Plant
) -> None:
    await master.write_register(PWM_COMM_TIMEOUT_REGISTER, 5, device_id=3)  # 0.5 s
    assert (await master.read_holding_registers(0x10, count=1, device_id=3)).registers == [5]
    assert sim.comm_timeout_s == 0.5
    await master.write_register(0, 700, device_id=3)
    await master.write_register(1, 600, device_id=3)
    for _ in range(5):  # any request keeps it alive, reads too
        await asyncio.sleep(0.2)
        await master.read_holding_registers(0, count=1, device_id=3)
    assert sim.duty_pct == {"motor": 70.0, "fan": 60.0} and sim.watchdog_trips == 0
    await asyncio.sleep(0.8)
    assert sim.duty_pct == {"motor": 0.0, "fan": 0.0}
    assert plant.duties[-2:] == [("motor", 0.0), ("fan", 0.0)]
    assert sim.watchdog_trips == 1
    rr = await master.read_holding_registers(0, count=2, device_id=3)
    assert rr.registers == [0, 0]  # reads show what the outputs really are


async def test_pwm_watchdog_is_off_until_the_master_sets_it(
    sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    await master.write_register(0, 700, device_id=3)
    await asyncio.sleep(0.5)
    assert sim.duty_pct["motor"] == 70.0 and sim.comm_timeout_s == 0.0


async def test_a_module_without_the_watchdog_refuses_its_register(plant: Plant) -> None:
    async with Rs485Simulator(
        radar_kmh=lambda: 0.0, tilt_deg=lambda: 0.0, pwm_watchdog=False
    ) as simulator:
        client = AsyncModbusSerialClient(simulator.device_path, timeout=TIMEOUT_S, retries=0)
        try:
            assert await client.connect()
            rr = await client.write_register(PWM_COMM_TIMEOUT_REGISTER, 20, device_id=3)
            assert rr.isError() and rr.exception_code == 2
        finally:
            client.close()


async def test_a_changed_surface_scales_the_radar_reading(
    sim: Rs485Simulator, master: AsyncModbusSerialClient
) -> None:
    """Issue 25: the radar's scale moves with the surface after its calibration."""
    sim.set_radar_scale(1.04)
    assert (await master.read_holding_registers(0, count=1, device_id=1)).registers == [546]
    sim.set_radar_scale(1.0)
    assert (await master.read_holding_registers(0, count=1, device_id=1)).registers == [525]
    with pytest.raises(ValueError, match="above 0"):
        sim.set_radar_scale(0.0)
