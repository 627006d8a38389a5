"""CAN driver on python-can's virtual interface: frames, timeouts, reconnects, ISOBUS decoding.

Which ISOBUS reading the machine acts on is tested in tests/gateway/metering/test_isobus.py."""

from __future__ import annotations

import asyncio
import struct
import uuid
from collections.abc import AsyncIterator
from typing import Any

import can
import pytest

from drivers.backoff import Backoff
from drivers.can_bus import CanBus, IsobusListener, MeteringCanLink
from drivers.errors import DeviceUnavailable, DriverError
from protocol import can_metering as cm
from protocol import isobus as ib
from protocol.errors import FieldError
from tests.helpers import eventually

FAST = Backoff(initial_s=0.01, cap_s=0.05)


@pytest.fixture
def channel() -> str:
    return f"test-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def opened() -> list[can.BusABC]:
    """Every python-can interface the ``bus`` fixture opened, the current one last."""
    return []


@pytest.fixture
async def bus(channel: str, opened: list[can.BusABC]) -> AsyncIterator[CanBus]:
    def open_interface(**kwargs: Any) -> can.BusABC:
        opened.append(can.Bus(**kwargs))
        return opened[-1]

    async with CanBus("virtual", channel, backoff=FAST, open_interface=open_interface) as b:
        yield b


@pytest.fixture
async def peer(channel: str) -> AsyncIterator[CanBus]:
    """The other end of the wire (a controller or a tractor)."""
    async with CanBus("virtual", channel, backoff=FAST) as b:
        yield b


async def test_frames_cross_the_virtual_bus_both_ways(bus: CanBus, peer: CanBus) -> None:
    await bus.send(0x201, bytes(range(8)))
    msg = await peer.recv(max_wait_s=2.0)
    assert msg is not None and msg.arbitration_id == 0x201 and bytes(msg.data) == bytes(range(8))
    await peer.send(0x18FE49F0, bytes(8), extended=True)
    back = await bus.recv(max_wait_s=2.0)
    assert back is not None and back.is_extended_id and back.arbitration_id == 0x18FE49F0


async def test_recv_times_out_with_none(bus: CanBus) -> None:
    assert await bus.recv(max_wait_s=0.05) is None


async def test_close_stops_the_notifier_thread_and_is_idempotent(channel: str) -> None:
    """The leak guard fails this test if the notifier's reader thread survives close()."""
    b = CanBus("virtual", channel)
    await b.open()
    assert b.connected
    b.close()
    b.close()
    assert not b.connected


async def test_bus_reopens_after_the_interface_fails(
    bus: CanBus, peer: CanBus, opened: list[can.BusABC]
) -> None:
    """Shutting the interface under the notifier is what an unplugged adapter looks like."""
    opened[-1].shutdown()
    # the notifier thread hits the closed bus, reports the error, recv() reconnects
    assert await bus.recv(max_wait_s=0.5) is None
    assert bus.stats.reconnects >= 1 and bus.connected
    await peer.send(0x281, bytes(8))
    msg = await bus.recv(max_wait_s=2.0)
    assert msg is not None and msg.arbitration_id == 0x281


async def test_unknown_interface_is_a_clear_driver_error() -> None:
    b = CanBus("no-such-interface", "x")
    with pytest.raises(DriverError, match="no-such-interface"):
        await b.open()
    b.close()


async def test_link_sends_each_node_target_with_rising_sequence(bus: CanBus, peer: CanBus) -> None:
    link = MeteringCanLink(bus, [1, 2], command_hz=50)
    link.set_target(1, 37.5)
    link.set_target(2, 0.0)
    task = asyncio.create_task(link.run(), name="link-under-test")
    try:
        seen: dict[int, list[cm.SpeedCommand]] = {1: [], 2: []}
        while min(len(v) for v in seen.values()) < 3:
            msg = await peer.recv(max_wait_s=2.0)
            assert msg is not None, "no command frames arrived"
            cmd = cm.decode_command(msg.arbitration_id, bytes(msg.data))
            seen[cmd.node_id].append(cmd)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert all(c.target_rpm == 37.5 and c.enable for c in seen[1])
    assert all(c.target_rpm == 0 and not c.enable for c in seen[2])
    seqs = [c.sequence for c in seen[1]]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)


async def test_link_delivers_typed_status_and_skips_bad_frames(bus: CanBus, peer: CanBus) -> None:
    link = MeteringCanLink(bus, [4], command_hz=20)
    got: list[cm.MeterStatus] = []
    task = asyncio.create_task(link.run(lambda s, t: got.append(s)), name="link-under-test")
    try:
        await peer.send(0x284, bytes(5))  # wrong DLC
        await peer.send(0x285, bytes(8))  # status of a node we do not drive
        await peer.send(0x2FF, bytes(8))  # unknown id
        frame_id, data = cm.encode_status(
            cm.MeterStatus(4, 21.5, True, True, False, False, cm.FaultCode.NONE, 0, 3, 40.0)
        )
        await peer.send(frame_id, data)
        await eventually(lambda: got, 2.0, "the one good status", interval=0.01)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert [s.measured_rpm for s in got] == [21.5]
    assert bus.stats.bad_frames == 1
    latest = link.status(4)
    assert latest is not None and latest[0].at_target


def test_link_refuses_unaddressable_nodes() -> None:
    b = CanBus("virtual", "unused")
    with pytest.raises(FieldError):
        MeteringCanLink(b, [0])


def speed_msg(pgn: int, raw: int, direction: int = 1) -> can.Message:
    data = struct.pack("<HIBB", raw, 0, 0xFF, 0xFC | direction)
    return can.Message(arbitration_id=ib.build_can_id(pgn, 0xF0), data=data, is_extended_id=True)


def hitch_msg(raw_pos: int, in_work_bits: int) -> can.Message:
    data = bytes([raw_pos, (in_work_bits << 6) | 0x3F, 255, 255, 255, 255, 255, 255])
    return can.Message(arbitration_id=ib.build_can_id(65093, 0xF0), data=data,
                       is_extended_id=True)


def test_isobus_listener_keeps_each_sources_latest_message_with_its_arrival_time() -> None:
    """Decoding only: every source is kept, however old; which one counts is the gateway's."""
    lis = IsobusListener(clock=lambda: 99.0)
    lis.feed(speed_msg(65097, 1389), now=10.0)
    lis.feed(speed_msg(65097, 1500), now=10.1)  # a newer ground-based speed replaces the old
    lis.feed(speed_msg(61474, 0xFE00), now=10.2)  # an error value is kept as what was said
    lis.feed(hitch_msg(20, 0b01))  # stamped by the listener's clock
    ground = lis.latest_speed(ib.PGN_GROUND_SPEED)
    assert ground is not None and ground.at == 10.1
    assert ground.message.speed_kmh == pytest.approx(5.4)
    selected = lis.latest_speed(ib.PGN_MACHINE_SELECTED_SPEED)
    assert selected is not None and selected.at == 10.2 and selected.message.speed_kmh is None
    assert lis.latest_speed(ib.PGN_WHEEL_SPEED) is None
    hitch = lis.latest_hitch()
    assert hitch is not None and hitch.at == 99.0 and hitch.message.in_work is ib.InWork.IN_WORK


def test_isobus_listener_ignores_garbage_and_standard_frames() -> None:
    lis = IsobusListener()
    lis.feed(can.Message(arbitration_id=ib.build_can_id(65097, 1), data=bytes(3),
                         is_extended_id=True), now=0.0)
    lis.feed(can.Message(arbitration_id=0x201, data=bytes(8), is_extended_id=False), now=0.0)
    assert lis.bad_frames == 1
    assert lis.latest_speed(ib.PGN_GROUND_SPEED) is None and lis.latest_hitch() is None


async def test_isobus_listener_runs_on_the_bus(bus: CanBus, peer: CanBus) -> None:
    lis = IsobusListener(bus)
    task = asyncio.create_task(lis.run(), name="isobus-under-test")
    try:
        msg = speed_msg(65097, 2500)
        await peer.send(msg.arbitration_id, bytes(msg.data), extended=True)
        await eventually(lambda: lis.latest_speed(ib.PGN_GROUND_SPEED) is not None, 1.0,
                         "the speed", interval=0.005)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    heard = lis.latest_speed(ib.PGN_GROUND_SPEED)
    assert heard is not None and heard.message.speed_kmh == pytest.approx(9.0)


async def test_send_on_a_failed_bus_reports_unavailable_then_recovers(
    bus: CanBus, peer: CanBus, opened: list[can.BusABC]
) -> None:
    opened[-1].shutdown()
    with pytest.raises(DeviceUnavailable, match="send failed"):
        await bus.send(0x201, bytes(8))
    await bus.send(0x202, bytes(8))  # reopened by the failed send
    msg = await peer.recv(max_wait_s=2.0)
    assert msg is not None and msg.arbitration_id == 0x202
