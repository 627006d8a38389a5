"""Metering controller frames: the DBC is the contract, the module adds typing and checks."""

from __future__ import annotations

import struct
from typing import Any

import cantools
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import can_metering as cm
from protocol.errors import FieldError, FrameError, ProtocolError


def test_dbc_ships_next_to_the_module_and_defines_every_node() -> None:
    """Each node 1..15 has a command and a status message of 8 bytes with 11-bit ids."""
    db: Any = cantools.database.load_file(str(cm.DBC_PATH))
    for node in range(1, 16):
        cmd = db.get_message_by_frame_id(0x200 + node)
        sts = db.get_message_by_frame_id(0x280 + node)
        assert cmd.length == sts.length == 8
        assert not cmd.is_extended_frame and not sts.is_extended_frame
    assert len(db.messages) == 30


def test_command_encodes_target_enable_and_sequence_at_documented_bits() -> None:
    """Target r/min x100 little-endian in bytes 0-1, enable bit 0 of byte 2, sequence byte 3."""
    frame_id, data = cm.encode_command(cm.SpeedCommand(3, 42.37, True, 200))
    assert frame_id == 0x203
    assert struct.unpack_from("<H", data)[0] == 4237
    assert data[2] & 1 == 1
    assert data[3] == 200
    assert cm.decode_command(frame_id, data) == cm.SpeedCommand(3, 42.37, True, 200)


def test_status_round_trips_with_fault_code() -> None:
    st_in = cm.MeterStatus(15, 18.75, True, False, True, True, cm.FaultCode.STALL, 4, 9, 87.5)
    frame_id, data = cm.encode_status(st_in)
    assert frame_id == 0x28F
    out = cm.decode_status(frame_id, data)
    assert out == st_in
    assert out.faulted


def test_status_bytes_built_by_hand_decode() -> None:
    """A controller vendor reading docs/can.md would build this frame for 30.5 r/min, fault 2."""
    data = struct.pack("<HBBBBBB", 3050, 0b1001, 2, 77, 100, 0, 0)
    st_ = cm.decode_status(0x281, data)
    assert st_.measured_rpm == 30.5
    assert st_.enabled and st_.fault_active and not st_.stalled
    assert st_.fault is cm.FaultCode.VALVE
    assert st_.sequence_echo == 77
    assert st_.valve_pct == 50.0


def test_unknown_fault_code_is_still_a_fault() -> None:
    data = struct.pack("<HBBBBBB", 0, 0, 99, 0, 0, 0, 0)
    st_ = cm.decode_status(0x281, data)
    assert st_.fault is cm.FaultCode.UNKNOWN and st_.raw_fault_code == 99
    assert st_.faulted


@pytest.mark.parametrize("dlc", [0, 1, 7, 9, 64])
def test_wrong_dlc_is_a_frame_error(dlc: int) -> None:
    with pytest.raises(FrameError, match="DLC"):
        cm.decode_status(0x281, bytes(dlc))


@pytest.mark.parametrize("frame_id", [0x000, 0x200, 0x280, 0x210, 0x290, 0x7FF, 0x1FFFFFFF])
def test_unknown_ids_are_frame_errors(frame_id: int) -> None:
    with pytest.raises(FrameError, match="unknown"):
        cm.decode(frame_id, bytes(8))


def test_command_frame_is_not_accepted_as_status() -> None:
    with pytest.raises(FrameError, match="command"):
        cm.decode_status(0x201, bytes(8))


@pytest.mark.parametrize("node", [0, 16, -1])
def test_node_outside_1_to_15_is_a_field_error(node: int) -> None:
    with pytest.raises(FieldError, match="node_id"):
        cm.encode_command(cm.SpeedCommand(node, 10.0, True, 0))


@pytest.mark.parametrize("rpm", [-0.01, 655.36, float("nan"), float("inf")])
def test_unencodable_target_speed_is_a_field_error(rpm: float) -> None:
    with pytest.raises(FieldError, match="target speed"):
        cm.encode_command(cm.SpeedCommand(1, rpm, True, 0))


def test_sequence_must_fit_a_byte() -> None:
    with pytest.raises(FieldError, match="sequence"):
        cm.encode_command(cm.SpeedCommand(1, 1.0, True, 256))


@given(
    node=st.integers(1, 15),
    centi_rpm=st.integers(0, 65535),
    enable=st.booleans(),
    seq=st.integers(0, 255),
)
def test_any_valid_command_round_trips(node: int, centi_rpm: int, enable: bool, seq: int) -> None:
    cmd = cm.SpeedCommand(node, centi_rpm / 100, enable, seq)
    assert cm.decode_command(*cm.encode_command(cmd)) == cmd


@given(frame_id=st.integers(0, 0x7FF), data=st.binary(max_size=16))
def test_garbage_frames_decode_or_raise_protocol_errors_only(frame_id: int, data: bytes) -> None:
    """Whatever arrives on the bus, decode either returns a typed frame or a ProtocolError."""
    try:
        out = cm.decode(frame_id, data)
    except ProtocolError:
        return
    assert isinstance(out, cm.SpeedCommand | cm.MeterStatus)
    assert len(data) == 8


@given(data=st.binary(min_size=8, max_size=8))
def test_every_8_byte_status_payload_decodes(data: bytes) -> None:
    """No 8-byte payload makes the status decoder crash: all bit patterns are meaningful."""
    out = cm.decode_status(0x285, data)
    assert 0 <= out.measured_rpm <= cm.SPEED_MAX_RPM
    assert out.node_id == 5
