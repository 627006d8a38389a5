"""ISO 11783-7 tractor messages, built byte by byte from the layouts in the standard."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import isobus as ib
from protocol.errors import FrameError, ProtocolError


def can_id(priority: int, pgn: int, sa: int, da: int = 0xFF) -> int:
    """29-bit id by hand: priority(3) | EDP,DP (2) | PF (8) | PS (8) | SA (8)."""
    pf = (pgn >> 8) & 0xFF
    ps = pgn & 0xFF if pf >= 240 else da
    return (priority << 26) | ((pgn >> 16) & 3) << 24 | pf << 16 | ps << 8 | sa


def speed_bytes(raw_speed: int, raw_dist: int, byte8: int) -> bytes:
    """Bytes 1-2 speed LE, 3-6 distance LE, 7 unused (0xFF), 8 direction bits 1-2."""
    return bytes([
        raw_speed & 0xFF, raw_speed >> 8,
        raw_dist & 0xFF, (raw_dist >> 8) & 0xFF, (raw_dist >> 16) & 0xFF, raw_dist >> 24,
        0xFF, byte8,
    ])


def test_ground_based_speed_pgn_65097_decodes_speed_distance_direction() -> None:
    """1.389 m/s = raw 1389 = 0x056D -> bytes 6D 05; forward = 01 in byte 8 bits 1-2."""
    data = speed_bytes(1389, 123456, 0b11111101)
    msg = ib.decode(can_id(3, 65097, 0xF0), data)
    assert isinstance(msg, ib.SpeedMessage)
    assert msg.pgn == ib.PGN_GROUND_SPEED and msg.source_address == 0xF0
    assert msg.speed_mps == pytest.approx(1.389)
    assert msg.speed_kmh == pytest.approx(5.0004)
    assert msg.distance_m == pytest.approx(123.456)
    assert msg.direction is ib.Direction.FORWARD
    assert msg.validity is ib.Validity.VALID


def test_wheel_based_speed_pgn_65096_reverse() -> None:
    msg = ib.decode(can_id(3, 65096, 0x1C), speed_bytes(500, 0, 0b11111100))
    assert isinstance(msg, ib.SpeedMessage)
    assert msg.pgn == 65096 and msg.speed_mps == pytest.approx(0.5)
    assert msg.direction is ib.Direction.REVERSE


def test_machine_selected_speed_pgn_61474_is_pdu2_broadcast() -> None:
    """61474 = 0xF022: PF 0xF0 >= 240, so PS 0x22 is part of the PGN, not a destination."""
    cid = can_id(3, 61474, 0x80)
    assert (cid >> 8) & 0xFFFF == 0xF022
    msg = ib.decode(cid, speed_bytes(2000, 0, 0b01))
    assert isinstance(msg, ib.SpeedMessage)
    assert msg.pgn == ib.PGN_MACHINE_SELECTED_SPEED and msg.speed_mps == pytest.approx(2.0)


@pytest.mark.parametrize(
    ("raw", "validity"),
    [(64255, ib.Validity.VALID), (64256, ib.Validity.RESERVED), (0xFE00, ib.Validity.ERROR),
     (0xFEFF, ib.Validity.ERROR), (0xFF00, ib.Validity.NOT_AVAILABLE),
     (0xFFFF, ib.Validity.NOT_AVAILABLE)],
)
def test_speed_above_64255_is_never_a_number(raw: int, validity: ib.Validity) -> None:
    msg = ib.decode(can_id(3, 65097, 1), speed_bytes(raw, 0, 1))
    assert isinstance(msg, ib.SpeedMessage)
    assert msg.validity is validity
    assert (msg.speed_mps is None) == (validity is not ib.Validity.VALID)
    if validity is ib.Validity.VALID:
        assert msg.speed_mps == pytest.approx(64.255)


@pytest.mark.parametrize(
    ("byte8", "direction"),
    [(0b00, ib.Direction.REVERSE), (0b01, ib.Direction.FORWARD), (0b10, ib.Direction.ERROR),
     (0b11, ib.Direction.NOT_AVAILABLE), (0b11111110, ib.Direction.ERROR)],
)
def test_direction_is_bits_1_2_of_byte_8(byte8: int, direction: ib.Direction) -> None:
    msg = ib.decode(can_id(3, 65096, 1), speed_bytes(100, 0, byte8))
    assert isinstance(msg, ib.SpeedMessage) and msg.direction is direction


@pytest.mark.parametrize(
    ("byte2", "in_work"),
    [(0b00111111, ib.InWork.OUT_OF_WORK), (0b01111111, ib.InWork.IN_WORK),
     (0b10000000, ib.InWork.ERROR), (0b11000000, ib.InWork.NOT_AVAILABLE)],
)
def test_rear_hitch_pgn_65093_in_work_is_bits_7_8_of_byte_2(byte2: int,
                                                            in_work: ib.InWork) -> None:
    """Position byte 1: 0.4 %/bit, so 125 = 50 %."""
    msg = ib.decode(can_id(3, 65093, 0xF0), bytes([125, byte2, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF]))
    assert isinstance(msg, ib.HitchStatus)
    assert msg.position_pct == pytest.approx(50.0)
    assert msg.in_work is in_work


@pytest.mark.parametrize(("raw", "pct"), [(0, 0.0), (250, 100.0), (251, None), (0xFE, None),
                                          (0xFF, None)])
def test_hitch_position_range(raw: int, pct: float | None) -> None:
    msg = ib.decode_hitch(1, bytes([raw, 0x7F, 0, 0, 0, 0, 0, 0]))
    assert msg.position_pct == (None if pct is None else pytest.approx(pct))


def test_pdu1_pgn_excludes_destination_address() -> None:
    """PF < 240: PS is a destination; two frames to different ECUs have the same PGN."""
    a = ib.parse_can_id(can_id(6, 0xEA00, 0x80, da=0x26))
    b = ib.parse_can_id(can_id(6, 0xEA00, 0x80, da=0xFF))
    assert a.pgn == b.pgn == 0xEA00
    assert a.destination_address == 0x26 and a.priority == 6


def test_data_page_bit_is_part_of_the_pgn() -> None:
    cid = (3 << 26) | (1 << 24) | (0xFE << 16) | (0x49 << 8) | 0x01  # DP=1: PGN 130633
    assert ib.parse_can_id(cid).pgn == 65097 + 65536
    assert ib.decode(cid, bytes(8)) is None  # not a tractor speed


def test_other_pgns_are_ignored_not_errors() -> None:
    assert ib.decode(can_id(3, 65262, 0), bytes(8)) is None  # engine temperature


@pytest.mark.parametrize("n", [0, 7, 9])
def test_short_or_long_payload_is_a_frame_error(n: int) -> None:
    with pytest.raises(FrameError, match="8 data bytes"):
        ib.decode(can_id(3, 65097, 1), bytes(n))


def test_identifier_wider_than_29_bits_is_rejected() -> None:
    with pytest.raises(FrameError, match="29-bit"):
        ib.parse_can_id(1 << 29)


def test_encoders_match_the_hand_built_layout() -> None:
    assert ib.encode_speed(ib.PGN_GROUND_SPEED, 1.389, ib.Direction.FORWARD, 123.456) == (
        speed_bytes(1389, 123456, 0xFD)
    )
    assert ib.encode_hitch(50.0, ib.InWork.IN_WORK)[:2] == bytes([125, 0x7F])
    assert ib.build_can_id(65097, 0xF0) == can_id(3, 65097, 0xF0)


@given(pgn=st.sampled_from(ib.KNOWN_PGNS), sa=st.integers(0, 255), prio=st.integers(0, 7))
def test_can_id_round_trips(pgn: int, sa: int, prio: int) -> None:
    parts = ib.parse_can_id(ib.build_can_id(pgn, sa, prio))
    assert (parts.pgn, parts.source_address, parts.priority) == (pgn, sa, prio)


@given(cid=st.integers(0, 0x1FFFFFFF), data=st.binary(max_size=12))
def test_garbage_decodes_or_raises_protocol_error(cid: int, data: bytes) -> None:
    try:
        out = ib.decode(cid, data)
    except ProtocolError:
        return
    if out is not None:
        assert len(data) == 8
        if isinstance(out, ib.SpeedMessage) and out.speed_mps is not None:
            assert 0 <= out.speed_mps <= 64.255
