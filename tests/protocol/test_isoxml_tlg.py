"""The ISO 11783-10 time log codec: records and headers round-trip, bad input is refused."""

from __future__ import annotations

import struct
from datetime import UTC, datetime

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.errors import FrameError, ProtocolError
from protocol.isoxml_tlg import (
    POSITION_FIELDS,
    DataLogValue,
    TimeLogError,
    TimeLogLayout,
    TimeLogRecord,
    decode_records,
    degrees_to_tlg,
    encode_record,
    header_xml,
    parse_header_xml,
    tlg_time_to_utc_us,
    tlg_to_degrees,
    utc_us_to_tlg_time,
)

INT32 = st.integers(-(2**31), 2**31 - 1)
FIELD_VALUES = {
    "i": INT32,
    "B": st.integers(0, 255),
    "H": st.integers(0, 65535),
    "I": st.integers(0, 2**32 - 1),
}


@st.composite
def layouts(draw: st.DrawFn) -> TimeLogLayout:
    chosen = draw(st.lists(st.sampled_from(list(POSITION_FIELDS)), unique=True))
    return TimeLogLayout(tuple(n for n in POSITION_FIELDS if n in chosen))


@st.composite
def records(draw: st.DrawFn, layout: TimeLogLayout) -> TimeLogRecord:
    return TimeLogRecord(
        draw(st.integers(0, 86_399_999)),
        draw(st.integers(0, 65535)),
        tuple(draw(FIELD_VALUES[POSITION_FIELDS[n]]) for n in layout.position_fields),
        tuple(draw(st.lists(st.tuples(st.integers(0, 255), INT32), max_size=40))),
    )


@st.composite
def logs(draw: st.DrawFn) -> tuple[TimeLogLayout, list[TimeLogRecord]]:
    layout = draw(layouts())
    return layout, draw(st.lists(records(layout), max_size=20))


@given(logs())
def test_any_records_decode_to_what_was_encoded(
    log: tuple[TimeLogLayout, list[TimeLogRecord]],
) -> None:
    layout, recs = log
    data = b"".join(encode_record(layout, r) for r in recs)
    assert list(decode_records(layout, data)) == recs


@given(logs(), st.data())
def test_a_truncated_log_is_a_frame_error_after_the_whole_records(
    log: tuple[TimeLogLayout, list[TimeLogRecord]], data: st.DataObject
) -> None:
    layout, recs = log
    if not recs:
        return
    blob = b"".join(encode_record(layout, r) for r in recs)
    last = len(encode_record(layout, recs[-1]))
    cut = data.draw(st.integers(len(blob) - last + 1, len(blob) - 1)) if last > 1 else None
    if cut is None:
        return
    got: list[TimeLogRecord] = []
    with pytest.raises(FrameError, match=f"record {len(recs) - 1} at byte"):
        got.extend(decode_records(layout, blob[:cut]))
    assert got == recs[:-1]


def test_the_record_layout_is_the_standards_little_endian_one() -> None:
    layout = TimeLogLayout(("A", "B", "D", "H", "I"))
    rec = TimeLogRecord(1000, 2, (481234567, -151234567, 4, 1000, 2), ((0, 7), (3, -11)))
    expected = struct.pack("<IHiiBIHB", 1000, 2, 481234567, -151234567, 4, 1000, 2, 2)
    expected += struct.pack("<Bi", 0, 7) + struct.pack("<Bi", 3, -11)
    assert encode_record(layout, rec) == expected


def test_times_are_utc_milliseconds_and_days_since_1980() -> None:
    t = datetime(2026, 5, 2, 6, 30, 15, 123456, tzinfo=UTC)
    us = int(t.timestamp()) * 1_000_000 + t.microsecond
    ms, days = utc_us_to_tlg_time(us)
    assert days == (t.date() - datetime(1980, 1, 1, tzinfo=UTC).date()).days
    assert ms == ((6 * 60 + 30) * 60 + 15) * 1000 + 123
    assert tlg_time_to_utc_us(ms, days) == us - 456


def test_before_1980_cannot_be_logged() -> None:
    with pytest.raises(TimeLogError, match="before 1980"):
        utc_us_to_tlg_time(0)


@given(st.floats(-180, 180))
def test_degrees_are_kept_to_half_a_ten_millionth(deg: float) -> None:
    assert abs(tlg_to_degrees(degrees_to_tlg(deg)) - deg) <= 0.5e-7 + 1e-12


@pytest.mark.parametrize(
    ("record", "message"),
    [
        (TimeLogRecord(86_400_000, 0, (0, 0, 0, 0, 0)), "time of day"),
        (TimeLogRecord(0, 70000, (0, 0, 0, 0, 0)), "date"),
        (TimeLogRecord(0, 0, (2**31, 0, 0, 0, 0)), "PTN A"),
        (TimeLogRecord(0, 0, (0, 0, 256, 0, 0)), "PTN D"),
        (TimeLogRecord(0, 0, (0, 0)), "2 position fields"),
        (TimeLogRecord(0, 0, (0, 0, 0, 0, 0), ((256, 1),)), "DLV index"),
        (TimeLogRecord(0, 0, (0, 0, 0, 0, 0), ((1, 2**31),)), "value of DLV 1"),
        (TimeLogRecord(0, 0, (0, 0, 0, 0, 0), tuple((i % 256, 0) for i in range(256))),
         "at most 255"),
    ],
)
def test_out_of_range_fields_are_refused_by_name(record: TimeLogRecord, message: str) -> None:
    with pytest.raises(TimeLogError, match=message):
        encode_record(TimeLogLayout(), record)


def test_a_layout_must_name_ptn_fields_in_record_order() -> None:
    with pytest.raises(TimeLogError, match="record order"):
        TimeLogLayout(("B", "A"))
    with pytest.raises(TimeLogError, match="no attribute"):
        TimeLogLayout(("Z",))
    assert issubclass(TimeLogError, ProtocolError)


@given(layouts(), st.lists(st.tuples(st.integers(0, 0xFFFF), st.from_regex(r"DET-?[0-9]{1,5}",
                                                                           fullmatch=True)),
                           min_size=1, max_size=256))
def test_a_header_reads_back_as_its_layout_and_values(
    layout: TimeLogLayout, pairs: list[tuple[int, str]]
) -> None:
    values = [DataLogValue(ddi, det) for ddi, det in pairs]
    assert parse_header_xml(header_xml(layout, values)) == (layout, values)


def test_the_header_lists_present_fields_as_empty_attributes() -> None:
    text = header_xml(TimeLogLayout(("A", "B", "H", "I")), [DataLogValue(0x8D, "DET-1")])
    assert b'<TIM A="" D="4">' in text
    assert b'<PTN A="" B="" H="" I="" />' in text
    assert b'<DLV A="008D" B="" C="DET-1" />' in text


def test_a_header_with_too_many_or_no_values_is_refused() -> None:
    with pytest.raises(TimeLogError, match="at most 256"):
        header_xml(TimeLogLayout(), [DataLogValue(1, "DET-1")] * 257)
    with pytest.raises(TimeLogError, match="at least one"):
        header_xml(TimeLogLayout(), [])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (b"<TIM", "not XML"),
        (b'<TLG A=""/>', "expected <TIM>"),
        (b'<TIM A="2026-01-01T00:00:00"/>', 'TIM A=""'),
        (b'<TIM A=""><DLV A="zz" B="" C="DET-1"/></TIM>', "not a hex DDI"),
        (b'<TIM A=""><DLV A="0001" B="5" C="DET-1"/></TIM>', 'B=""'),
    ],
)
def test_headers_this_reader_cannot_use_say_why(text: bytes, message: str) -> None:
    with pytest.raises(TimeLogError, match=message):
        parse_header_xml(text)
