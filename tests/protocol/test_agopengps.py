"""The AgOpenGPS UDP codec, on frames laid out as AgOpenGPS's own sources build them."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import agopengps as aog
from protocol.errors import ChecksumError, FieldError, FrameError, ProtocolError

OFF16 = (False,) * 16


def with_crc(frame: list[int]) -> bytes:
    """A frame as AgOpenGPS's ``CPGN_*`` arrays hold it, with the crc filled in its way."""
    frame[-1] = sum(frame[2:-1]) & 0xFF
    return bytes(frame)


def test_pgn_254_speed_and_sections_from_agopengps_layout() -> None:
    # CPGN_FE: 80 81 7F FE 08 [speedLo speedHi status angleLo angleHi xte sc1to8 sc9to16] crc
    frame = [0x80, 0x81, 0x7F, 0xFE, 8, 0x55, 0x00, 0, 0, 0, 0, 0b0000_0101, 0b1000_0000, 0xCC]
    msg = aog.decode(with_crc(frame))
    assert msg == aog.SteerData(
        8.5, (True, False, True) + (False,) * 12 + (True,)
    )


def test_pgn_239_lift_tram_geostop_and_the_speed_byte_wraps() -> None:
    # CPGN_EF: uturn=5 speed=6 hydLift=7 tram=8 geoStop=9 sc1to8=11 sc9to16=12
    frame = [0x80, 0x81, 0x7F, 0xEF, 8, 0, 0, 2, 3, 1, 0, 0xFF, 0x01, 0xCC]
    frame[6] = int(27.0 * 10) & 0xFF  # AgOpenGPS: (byte)(avgSpeed * 10)
    msg = aog.decode(with_crc(frame))
    assert isinstance(msg, aog.MachineData)
    assert msg.hyd_lift == aog.HYD_LIFT_RAISE and msg.tram == 3 and msg.geo_stop
    assert msg.sections == (True,) * 9 + (False,) * 7
    assert msg.speed_byte_kmh == pytest.approx(1.4)  # 27 km/h wrapped: why it is not a speed


def test_pgn_229_sixty_four_sections_and_tool_speeds() -> None:
    # CPGN_E5: len 10, sc1to8..sc57to64 = 5..12, toolLSpeed=13, toolRSpeed=14
    frame = [0x80, 0x81, 0x7F, 0xE5, 10, 1, 0, 0, 0, 0, 0, 0, 0x80, 25, 31, 0xCC]
    msg = aog.decode(with_crc(frame))
    assert isinstance(msg, aog.Sections64)
    assert msg.sections[0] and msg.sections[63] and sum(msg.sections) == 2
    assert (msg.left_speed_mps, msg.right_speed_mps) == (2.5, 3.1)


def test_pgn_229_of_eight_bytes_has_sections_without_tool_speeds() -> None:
    msg = aog.decode(aog.encode(0x7F, 229, bytes([0xFF] + [0] * 7)))
    assert isinstance(msg, aog.Sections64)
    assert sum(msg.sections) == 8 and msg.left_speed_mps is None


def test_agio_hello_with_its_fixed_checksum_is_a_hello() -> None:
    hello = bytes.fromhex("80 81 7F C8 03 38 00 00 47")  # UDP.designer.cs helloFromAgIO
    assert hello == aog.hello_from_agio()
    assert sum(hello[2:-1]) & 0xFF != 0x47  # the sum rule would say 0x82
    assert aog.decode(hello) == aog.Hello()
    assert aog.decode(aog.encode(0x7F, 200, bytes([56, 0, 0]))) == aog.Hello()


def test_hello_reply_is_the_eleven_bytes_agio_lists() -> None:
    reply = aog.hello_reply([True, False, True] + [False] * 13)
    assert len(reply) == 11 and reply[3] == 123 and reply[2] == 123
    assert aog.decode_frame(reply).data[:2] == bytes([0b101, 0])


def test_display_text_frame() -> None:
    frame = aog.display_text("Row 7 blocked", seconds=6, colour=1)
    f = aog.decode_frame(frame)
    assert f.pgn == 221 and f.data[0] == 6 and f.data[1] == 1
    assert f.data[2:].decode() == "Row 7 blocked"
    long = aog.decode_frame(aog.display_text("é" * 400))
    assert len(long.data) <= 2 + aog.MAX_TEXT_BYTES
    long.data[2:].decode("utf-8")  # cut at a character boundary


def test_round_trip_of_the_encoders() -> None:
    sections = [i % 3 == 0 for i in range(16)]
    assert aog.decode(aog.encode_steer_data(12.3, sections)) == aog.SteerData(
        12.3, tuple(sections)
    )
    m = aog.decode(aog.encode_machine_data(5.0, sections, hyd_lift=1, geo_stop=True))
    assert isinstance(m, aog.MachineData) and m.sections == tuple(sections) and m.geo_stop


@pytest.mark.parametrize(
    ("datagram", "error", "words"),
    [
        (b"\x80\x81\x7f", FrameError, "shorter"),
        (b"\x24\x81\x7f\xfe\x00\x7d", FrameError, "header"),
        (aog.encode_steer_data(5, OFF16)[:-2] + b"\x00", FrameError, "length byte"),
        (aog.encode_steer_data(5, OFF16)[:-1] + b"\x00", ChecksumError, "checksum"),
        (aog.encode(0x7F, 254, bytes(4)), FrameError, "at least 8"),
        (aog.encode(0x7F, 254, (1500).to_bytes(2, "little") + bytes(6)), FieldError, "km/h"),
        (aog.encode(0x7F, 239, bytes([0, 0, 7, 0, 0, 0, 0, 0])), FieldError, "lift"),
    ],
)
def test_bad_frames_say_why(datagram: bytes, error: type[Exception], words: str) -> None:
    with pytest.raises(error, match=words):
        aog.decode(datagram)


def test_other_pgns_are_recognised_but_unhandled() -> None:
    assert aog.decode(aog.encode(0x7F, 238, bytes(8))) == aog.Unhandled(238)


@given(st.binary(max_size=300))
def test_decoder_never_raises_anything_but_a_protocol_error(data: bytes) -> None:
    with contextlib.suppress(ProtocolError):
        aog.decode(data)


@given(st.sampled_from([254, 239, 229, 200]), st.binary(max_size=20))
def test_decoder_on_well_framed_junk(pgn: int, data: bytes) -> None:
    with contextlib.suppress(ProtocolError):
        aog.decode(aog.encode(0x7F, pgn, data))
