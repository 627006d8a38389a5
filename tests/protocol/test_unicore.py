"""Unicore #HEADINGA / #UNIHEADINGA: CRC, both header layouts, and heading validity."""

from __future__ import annotations

import zlib
from datetime import UTC, datetime, timedelta

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.errors import ChecksumError, FieldError, FrameError, ProtocolError
from protocol.nmea import MissingFieldError, TruncatedError, UnknownSentenceError
from protocol.unicore import (
    GPS_UTC_LEAP_S,
    MAX_UNICORE_LINE_CHARS,
    Heading,
    encode_headinga,
    encode_uniheadinga,
    gps_to_utc,
    parse_unicore,
    place_in_leap_second,
    unicore_crc32,
    utc_to_gps,
)

OWN_LOG_CONTENT = (
    b"HEADINGA,COM1,7,42.0,FINE,2300,123456.700,00000000,0,1;SOL_COMPUTED,NARROW_INT,"
    b'1.2000,90.5000,-0.2500,0.0000,0.0500,0.1000,"0",30,24,24,20,0,01,3,f3'
)


def _framed(content: str) -> str:
    return f"#{content}*{unicore_crc32(content.encode()):08x}"


def test_crc_known_answer_for_a_log_written_here() -> None:
    """Regression anchor: computed once with this implementation (itself checked against
    published receiver captures during development) and against the zlib identity below."""
    assert unicore_crc32(OWN_LOG_CONTENT) == 0x902FB956


@given(st.binary(max_size=300))
def test_crc_equals_zlib_crc_with_the_initial_and_final_inversion_undone(data: bytes) -> None:
    """CRC-32 is affine in its initial value: crc_init0(d) = zlib(d) ^ zlib(zeros(len(d))).
    An independent oracle for the table, and proof that it differs from plain zlib.crc32."""
    assert unicore_crc32(data) == zlib.crc32(data) ^ zlib.crc32(bytes(len(data)))


def test_crc_is_not_zlib_crc32() -> None:
    assert unicore_crc32(OWN_LOG_CONTENT) != zlib.crc32(OWN_LOG_CONTENT)


@given(data=st.binary(min_size=1, max_size=200), where=st.integers(0), flip=st.integers(1, 255))
def test_changing_any_one_byte_changes_the_crc(data: bytes, where: int, flip: int) -> None:
    i = where % len(data)
    changed = data[:i] + bytes([data[i] ^ flip]) + data[i + 1 :]
    assert unicore_crc32(changed) != unicore_crc32(data)


weeks = st.integers(1000, 4000)
tows = st.integers(0, 604_799_999).map(lambda ms: ms / 1000.0)
headings = st.floats(0, 359.9999)
pitches = st.floats(-89, 89)


@given(week=weeks, tow=tows, hdg=headings, pitch=pitches, base=st.floats(0.1, 30))
def test_legacy_headinga_round_trips(
    week: int, tow: float, hdg: float, pitch: float, base: float
) -> None:
    h = parse_unicore(encode_headinga(week, tow, hdg, pitch, base, hdg_std=0.07))
    assert h.log == "HEADINGA" and h.leap_s is None
    assert (h.gps_week, h.gps_tow_s) == (week, pytest.approx(tow, abs=5e-4))
    assert h.heading_deg == pytest.approx(hdg, abs=5e-5)
    assert h.pitch_deg == pytest.approx(pitch, abs=5e-5)
    assert h.baseline_m == pytest.approx(base, abs=5e-5)
    assert h.hdg_std == pytest.approx(0.07) and h.valid


@given(week=weeks, tow=tows, hdg=headings)
def test_n4_uniheadinga_round_trips_with_leap_seconds(week: int, tow: float, hdg: float) -> None:
    h = parse_unicore(encode_uniheadinga(week, tow, hdg, leap_s=19))
    assert h.log == "UNIHEADINGA" and h.leap_s == 19
    assert (h.gps_week, h.gps_tow_s) == (week, pytest.approx(tow, abs=5e-4))
    assert h.heading_deg == pytest.approx(hdg, abs=5e-5)
    assert h.utc() == gps_to_utc(week, tow, 19)


@pytest.mark.parametrize(
    ("sol", "pos", "valid", "quality"),
    [
        ("SOL_COMPUTED", "NARROW_INT", True, "fixed"),
        ("SOL_COMPUTED", "L1_INT", True, "fixed"),
        ("SOL_COMPUTED", "WIDE_INT", True, "fixed"),
        ("SOL_COMPUTED", "NARROW_FLOAT", False, "float"),
        ("SOL_COMPUTED", "L1_FLOAT", False, "float"),
        ("SOL_COMPUTED", "SINGLE", False, "none"),
        ("INSUFFICIENT_OBS", "NONE", False, "none"),
        ("COLD_START", "NARROW_INT", False, "none"),
    ],
)
def test_heading_is_valid_only_when_computed_with_fixed_ambiguities(
    sol: str, pos: str, valid: bool, quality: str
) -> None:
    h = parse_unicore(encode_headinga(2300, 1000.0, 10.0, sol_status=sol, pos_type=pos))
    assert (h.valid, h.quality) == (valid, quality)


def test_crc_mismatch_names_expected_and_received_values() -> None:
    line = encode_headinga(2300, 1.0, 10.0)
    good = line[-8:]
    bad = f"{int(good, 16) ^ 1:08x}"
    with pytest.raises(ChecksumError) as err:
        parse_unicore(line[:-8] + bad)
    assert str(err.value) == f"CRC mismatch: expected {good}, got {bad}"


def test_upper_case_crc_digits_are_accepted() -> None:
    line = encode_headinga(2300, 1.0, 10.0)
    assert isinstance(parse_unicore(line[:-8] + line[-8:].upper()), Heading)


def test_every_truncation_is_rejected() -> None:
    line = encode_uniheadinga(2300, 345.6, 271.0)
    for cut in range(len(line)):
        with pytest.raises(ProtocolError):
            parse_unicore(line[:cut])


def test_missing_crc_is_truncation() -> None:
    with pytest.raises(TruncatedError):
        parse_unicore(encode_headinga(2300, 1.0, 10.0)[:-9])


def test_other_unicore_logs_are_unknown_not_errors_of_the_link() -> None:
    line = _framed("BESTNAVA,90,GPS,FINE,2300,1000,0,0,18,10;SOL_COMPUTED,SINGLE,1,2,3")
    with pytest.raises(UnknownSentenceError, match="BESTNAVA"):
        parse_unicore(line)


def test_an_unknown_log_longer_than_the_limit_is_unknown_not_malformed() -> None:
    line = _framed("OBSVMA,90,GPS,FINE,2300,1000,0,0,18,10;" + ",".join(["123456.789"] * 80))
    assert len(line) > MAX_UNICORE_LINE_CHARS
    with pytest.raises(UnknownSentenceError, match="OBSVMA"):
        parse_unicore(line)


def test_an_overlong_heading_log_is_still_malformed() -> None:
    line = _framed(OWN_LOG_CONTENT.decode() + ",0" * 400)
    with pytest.raises(FrameError, match="too long") as err:
        parse_unicore(line)
    assert not isinstance(err.value, UnknownSentenceError)


def test_short_body_is_a_missing_field() -> None:
    with pytest.raises(MissingFieldError, match="body has 3"):
        parse_unicore(_framed("HEADINGA,COM1,0,50.0,FINE,2300,1.000,0,0,1;SOL_COMPUTED,NARROW_INT,1"))


def test_non_numeric_heading_names_the_field() -> None:
    content = (
        "HEADINGA,COM1,0,50.0,FINE,2300,1.000,0,0,1;SOL_COMPUTED,NARROW_INT,1.0,9O.5,0,0,0.1,0.2"
    )
    with pytest.raises(FieldError, match=r"heading.*9O\.5"):
        parse_unicore(_framed(content))


def test_heading_out_of_range_is_rejected() -> None:
    content = (
        "HEADINGA,COM1,0,50.0,FINE,2300,1.000,0,0,1;SOL_COMPUTED,NARROW_INT,1.0,361.0,0,0,0.1,0.2"
    )
    with pytest.raises(FieldError, match="out of range"):
        parse_unicore(_framed(content))


def test_missing_header_separator_is_a_frame_error() -> None:
    with pytest.raises(FrameError, match="';'"):
        parse_unicore(_framed("HEADINGA,COM1,0,50.0,FINE,2300,1.000,0,0,1"))


def test_gps_time_is_18_seconds_ahead_of_utc() -> None:
    utc = datetime(2024, 3, 1, 12, 0, 0, 300_000, tzinfo=UTC)
    week, tow = utc_to_gps(utc)
    assert GPS_UTC_LEAP_S == 18
    assert gps_to_utc(week, tow) == utc
    # 2024-03-01 is a Friday: 5 days + 12 h + 18 s into GPS week 2303
    assert week == 2303
    assert tow == pytest.approx(5 * 86400 + 12 * 3600 + 18.3)


@given(st.datetimes(min_value=datetime(1990, 1, 1), max_value=datetime(2100, 1, 1),
                    timezones=st.just(UTC)))
def test_utc_gps_conversion_round_trips_to_the_millisecond(utc: datetime) -> None:
    utc = utc.replace(microsecond=utc.microsecond // 1000 * 1000)
    assert gps_to_utc(*utc_to_gps(utc)) == utc


@given(week=st.integers(1357, 4000), tow=tows, hdg=headings, leap=st.sampled_from([18, 4]))
def test_n4_log_in_beidou_time_gives_the_same_instant_as_in_gps_time(
    week: int, tow: float, hdg: float, leap: int
) -> None:
    """A receiver set to BDT stamps 14 s and 1356 weeks lower; the parsed time must not move.

    The leap count is accepted either as GPS-UTC (18) or as BDT-UTC (4): both give one UTC.
    """
    gps = parse_unicore(encode_uniheadinga(week, tow, hdg))
    bds = parse_unicore(encode_uniheadinga(week, tow, hdg, time_ref="BDS", leap_s=leap))
    assert bds.time_ref == "BDS" and gps.time_ref == "GPS"
    assert (bds.gps_week, bds.gps_tow_s) == (gps.gps_week, pytest.approx(gps.gps_tow_s))
    assert bds.utc() == gps.utc()
    assert bds.leap_s == GPS_UTC_LEAP_S


def test_beidou_header_carries_beidou_week_and_seconds() -> None:
    line = encode_uniheadinga(2300, 10.0, 91.0, time_ref="BDS")
    # 10 s into GPS week 2300 is 4 s before the end of BDT week 2300 - 1356 - 1
    assert line.startswith("#UNIHEADINGA,80,BDS,FINE,943,604796000,")


def test_unknown_time_reference_is_a_field_error_not_a_wrong_time() -> None:
    content = encode_uniheadinga(2300, 100.0, 91.0)[1:].split("*")[0].replace(",GPS,", ",GLO,")
    with pytest.raises(FieldError, match=r"time reference: 'GLO' not supported"):
        parse_unicore(_framed(content))


@given(st.integers(0, 999))
def test_a_heading_log_of_the_leap_second_is_placed_in_second_60(ms: int) -> None:
    """GPS time runs through the leap second: with the old count the log reads 00:00:00.x;
    while the NMEA says a leap second ends at that midnight it is 23:59:60.x."""
    midnight = datetime(2027, 1, 1, tzinfo=UTC)
    week, tow = utc_to_gps(midnight + timedelta(milliseconds=ms), GPS_UTC_LEAP_S)
    heading = parse_unicore(encode_headinga(week, tow, 90.0))
    utc = heading.utc(GPS_UTC_LEAP_S)
    assert place_in_leap_second(utc, midnight) == (
        midnight - timedelta(seconds=1) + timedelta(milliseconds=ms), True
    )
    assert place_in_leap_second(utc, None) == (utc, False)  # no leap second in progress
    after = utc + timedelta(seconds=1)
    assert place_in_leap_second(after, midnight) == (after, False)
