"""NMEA parsing: what sowgate accepts from a receiver, and how precisely it says no."""

from __future__ import annotations

from datetime import UTC, datetime, time, timedelta

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from protocol.errors import ChecksumError, FieldError, FrameError, ProtocolError
from protocol.nmea import (
    KMH_PER_KNOT,
    MAX_NMEA_LINE_CHARS,
    MS_PER_DAY,
    Gga,
    Hdt,
    MissingFieldError,
    Rmc,
    Ths,
    TruncatedError,
    UnknownSentenceError,
    Vtg,
    encode_nmea,
    nmea_checksum,
    parse_nmea,
    utc_ms_of_day,
)
from simulator.um982 import um982_sentences

TALKERS = ["GP", "GN", "GL", "GA", "GB", "BD"]

utcs = st.datetimes(
    min_value=datetime(2000, 1, 1), max_value=datetime(2068, 12, 31), timezones=st.just(UTC)
).map(lambda d: d.replace(microsecond=d.microsecond // 10_000 * 10_000))
lats = st.floats(-89.9, 89.9)
lons = st.floats(-179.9, 179.9)


def _rmc_gga(utc: datetime, lat: float, lon: float, **kw: object) -> tuple[str, str]:
    lines = um982_sentences(
        utc, lat, lon, kw.pop("alt_m", 123.4567), kw.pop("speed_kmh", 7.5),  # type: ignore[arg-type]
        kw.pop("course_deg", 45.0), 45.0, **kw,  # type: ignore[arg-type]
    )
    return lines[0], lines[1]


@given(utc=utcs, lat=lats, lon=lons, speed=st.floats(0, 60), course=st.floats(0, 359.9))
def test_generated_rmc_round_trips_position_speed_course_and_date(
    utc: datetime, lat: float, lon: float, speed: float, course: float
) -> None:
    """Position survives to 1e-9° (0.1 mm), speed to the 3 decimals of knots sent."""
    rmc_line, _ = _rmc_gga(utc, lat, lon, speed_kmh=speed, course_deg=course)
    rmc = parse_nmea(rmc_line)
    assert isinstance(rmc, Rmc)
    assert rmc.valid and rmc.mode == "R" and rmc.talker == "GN"
    assert rmc.utc == utc.time().replace(tzinfo=None) and rmc.date == utc.date()
    assert rmc.lat == pytest.approx(lat, abs=1e-9)
    assert rmc.lon == pytest.approx(lon, abs=1e-9)
    assert rmc.speed_kmh == pytest.approx(speed, abs=0.0006 * KMH_PER_KNOT)
    assert rmc.course_deg == pytest.approx(course % 360.0, abs=0.051)


@given(utc=utcs, lat=lats, lon=lons, alt=st.floats(-400, 8000))
def test_generated_gga_round_trips_quality_satellites_and_height(
    utc: datetime, lat: float, lon: float, alt: float
) -> None:
    _, gga_line = _rmc_gga(utc, lat, lon, alt_m=alt, fix="rtk_float", num_sv=17)
    gga = parse_nmea(gga_line)
    assert isinstance(gga, Gga)
    assert gga.quality == 5 and gga.num_sv == 17
    assert gga.lat == pytest.approx(lat, abs=1e-9) and gga.lon == pytest.approx(lon, abs=1e-9)
    assert gga.alt_m == pytest.approx(alt, abs=5e-5)


@pytest.mark.parametrize("talker", TALKERS)
@pytest.mark.parametrize("sentence", ["RMC", "GGA", "VTG", "HDT", "THS"])
def test_any_constellation_talker_is_accepted(talker: str, sentence: str) -> None:
    """A receiver configured for GPS-only (GP) or BeiDou (BD/GB) must work the same."""
    bodies = {
        "RMC": "RMC,120000.00,A,4500.00000000,N,00700.00000000,E,1.000,90.0,010124,,,R,V",
        "GGA": "GGA,120000.00,4500.00000000,N,00700.00000000,E,4,20,0.6,100.0000,M,40.0000,M,,",
        "VTG": "VTG,90.0,T,,M,1.000,N,1.852,K,R",
        "HDT": "HDT,123.45,T",
        "THS": "THS,123.4500,A",
    }
    event = parse_nmea(encode_nmea(talker + bodies[sentence]))
    assert event.talker == talker and event.kind == sentence


def test_vtg_hdt_and_ths_fields() -> None:
    vtg = parse_nmea(encode_nmea("GNVTG,271.5,T,,M,5.400,N,10.001,K,A"))
    assert vtg == Vtg("GN", 271.5, None, 5.4, 10.001, "A")
    assert parse_nmea(encode_nmea("GPHDT,359.99,T")) == Hdt("GP", 359.99)
    ths = parse_nmea(encode_nmea("GNTHS,12.3400,V"))
    assert isinstance(ths, Ths) and ths.heading_deg == 12.34 and not ths.valid
    assert parse_nmea(encode_nmea("GNTHS,12.3400,A")).valid  # type: ignore[union-attr]


def test_southern_and_western_hemispheres_are_negative() -> None:
    line = encode_nmea("GNGGA,000001.00,3352.12345678,S,15112.87654321,W,1,08,1.2,5.0,M,,M,,")
    gga = parse_nmea(line)
    assert isinstance(gga, Gga)
    assert gga.lat == pytest.approx(-(33 + 52.12345678 / 60), abs=1e-9)
    assert gga.lon == pytest.approx(-(151 + 12.87654321 / 60), abs=1e-9)


def test_receiver_without_fix_sends_empty_position_which_is_not_an_error() -> None:
    rmc = parse_nmea(encode_nmea("GNRMC,,V,,,,,,,,,,N,V"))
    assert isinstance(rmc, Rmc)
    assert not rmc.valid and rmc.lat is None and rmc.utc is None and rmc.mode == "N"
    gga = parse_nmea(encode_nmea("GNGGA,101010.00,,,,,0,00,99.9,,M,,M,,"))
    assert isinstance(gga, Gga) and gga.quality == 0 and gga.lat is None


def test_checksum_mismatch_names_expected_and_received_values() -> None:
    good = encode_nmea("GPHDT,274.07,T")
    expected = nmea_checksum("GPHDT,274.07,T")
    wrong = f"{(int(expected, 16) + 1) % 256:02X}"
    with pytest.raises(ChecksumError) as err:
        parse_nmea(good[:-2] + wrong)
    assert str(err.value) == f"checksum mismatch: expected {expected}, got {wrong}"


@given(data=st.data(), utc=utcs, lat=lats, lon=lons)
def test_any_single_character_corruption_is_detected(
    data: st.DataObject, utc: datetime, lat: float, lon: float
) -> None:
    """XOR over the body catches every single-character change; so must the parser."""
    line = _rmc_gga(utc, lat, lon)[data.draw(st.integers(0, 1))]
    i = data.draw(st.integers(0, len(line) - 1))
    new = data.draw(st.characters(min_codepoint=32, max_codepoint=126))
    assume(new.upper() != line[i].upper())
    with pytest.raises(ProtocolError):
        parse_nmea(line[:i] + new + line[i + 1 :])


def test_every_truncation_of_a_sentence_is_rejected() -> None:
    """A line cut anywhere (reconnect mid-sentence) never decodes to a wrong value."""
    utc = datetime(2024, 5, 1, 10, 0, 0, tzinfo=UTC)
    for line in _rmc_gga(utc, 45.0, 7.0):
        for cut in range(len(line)):
            with pytest.raises(ProtocolError):
                parse_nmea(line[:cut])


def test_missing_trailer_is_reported_as_truncation() -> None:
    with pytest.raises(TruncatedError, match="truncated"):
        parse_nmea("$GNRMC,120000.00,A,4500.0000,N")


def test_status_a_without_position_is_a_missing_field() -> None:
    with pytest.raises(MissingFieldError, match="lat"):
        parse_nmea(encode_nmea("GNRMC,120000.00,A,,,,,1.0,90.0,010124,,,A"))


def test_rtk_quality_without_position_is_a_missing_field() -> None:
    with pytest.raises(MissingFieldError, match="lat"):
        parse_nmea(encode_nmea("GNGGA,120000.00,,,,,4,20,0.6,100.0,M,40.0,M,,"))


def test_too_few_fields_is_a_missing_field() -> None:
    with pytest.raises(ProtocolError):
        parse_nmea(encode_nmea("GNGGA,120000.00,4500.000,N"))


def test_malformed_latitude_names_the_field_and_value() -> None:
    line = encode_nmea("GNGGA,120000.00,45x00.000,N,00700.000,E,1,08,1.0,1.0,M,1.0,M,,")
    with pytest.raises(FieldError, match=r"lat.*45x00\.000"):
        parse_nmea(line)


def test_bad_rmc_status_is_a_field_error() -> None:
    with pytest.raises(FieldError, match="status"):
        parse_nmea(encode_nmea("GNRMC,120000.00,X,4500.0,N,00700.0,E,1.0,90.0,010124,,,A"))


@pytest.mark.parametrize(
    "sentence", ["GNGSV,1,1,00", "GNGSA,A,3,,,,,,,,,,,,,1.0,1.0,1.0", "KSXT,1"]
)
def test_well_framed_sentences_we_do_not_use_are_unknown(sentence: str) -> None:
    with pytest.raises(UnknownSentenceError) as err:
        parse_nmea(encode_nmea(sentence))
    assert err.value.sentence == sentence.split(",")[0]


@pytest.mark.parametrize("address", ["PQTMEPE", "KSXT", "GNGSV"])
def test_a_sentence_we_do_not_use_is_unknown_even_when_longer_than_the_limit(address: str) -> None:
    sentence = encode_nmea(address + "," + ",".join(["12.345"] * 40))
    assert len(sentence) > MAX_NMEA_LINE_CHARS
    with pytest.raises(UnknownSentenceError) as err:
        parse_nmea(sentence)
    assert err.value.sentence == address


def test_an_overlong_sentence_we_decode_is_still_malformed() -> None:
    sentence = encode_nmea("GNRMC,120000.00,A,4500.0,N,00700.0,E,1.0,90.0,010124,,,A" + "0" * 200)
    with pytest.raises(FrameError, match="too long") as err:
        parse_nmea(sentence)
    assert not isinstance(err.value, UnknownSentenceError)


def test_sentence_time_keeps_hundredths() -> None:
    utc = datetime(2024, 5, 1, 23, 59, 59, 900_000, tzinfo=UTC)
    rmc = parse_nmea(_rmc_gga(utc, 1.0, 2.0)[0])
    assert isinstance(rmc, Rmc)
    assert rmc.utc is not None and rmc.utc.microsecond == 900_000
    assert (datetime.combine(rmc.date, rmc.utc, UTC) - utc) == timedelta(0)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("content", "field"),
    [
        ("GNRMC,120000.00,A,4500.0,N,00700.0,E,-2.5,90.0,010124,,,R", "spd"),
        ("GNRMC,120000.00,A,4500.0,N,00700.0,E,2.5,361.0,010124,,,R", "cog"),
        ("GNRMC,120000.00,A,4500.0,N,00700.0,E,2.5,-0.5,010124,,,R", "cog"),
        ("GNVTG,90.0,T,,M,-1.0,N,-1.9,K,A", "sogn"),
        ("GNVTG,400.0,T,,M,1.0,N,1.9,K,A", "cogt"),
        ("GNHDT,360.5,T", "headingT"),
        ("GNHDT,-10.0,T", "headingT"),
        ("GNTHS,720.0,A", "headt"),
    ],
)
def test_speeds_and_angles_out_of_range_are_bad_fields_not_values(
    content: str, field: str
) -> None:
    # a negative speed or a 400° heading would otherwise be clamped or wrapped into a
    # plausible-looking, wrong seed position
    with pytest.raises(FieldError, match=rf"field {field}: .* (out of range|must be >=)"):
        parse_nmea(encode_nmea(content))


@given(heading=st.floats(0.0, 360.0))
def test_every_heading_in_range_is_accepted(heading: float) -> None:
    hdt = parse_nmea(encode_nmea(f"GNHDT,{heading:.4f},T"))
    assert isinstance(hdt, Hdt) and hdt.heading_deg == pytest.approx(heading, abs=1e-4)


@given(st.integers(0, 99))
def test_a_leap_second_is_second_60_of_23_59_not_a_bad_field(centis: int) -> None:
    """``235960.xx`` is UTC's leap second: 23:59:59 + the fraction, flagged, after 23:59:59.99
    on the day's millisecond count and before the next day's 00:00:00."""
    for kind in ("RMC", "GGA"):
        body = (f"GNRMC,235960.{centis:02d},A,5327.03598945,N,00214.41467156,W,0.097,125.7,"
                "311226,0.2,W,A,C") if kind == "RMC" else (
                f"GNGGA,235960.{centis:02d},5327.03598945,N,00214.41467156,W,4,08,0.7,"
                "36.3017,M,51.6775,M,1.0,0001")
        msg = parse_nmea(encode_nmea(body))
        assert isinstance(msg, Rmc | Gga)
        assert msg.leap_second and msg.utc == time(23, 59, 59, centis * 10_000)
        assert utc_ms_of_day(time(23, 59, 59, 990_000)) < utc_ms_of_day(msg.utc, True)
        assert utc_ms_of_day(msg.utc, True) < MS_PER_DAY + 1000


def test_second_60_outside_23_59_is_a_bad_field_naming_the_sentence() -> None:
    line = encode_nmea("GNGGA,120060.00,5327.03598945,N,00214.41467156,W,1,08,7.5,36.3017,M,"
                       "51.6775,M,,")
    with pytest.raises(FieldError, match=r"GNGGA: field time '120060.00': second 60 exists only"):
        parse_nmea(line)
