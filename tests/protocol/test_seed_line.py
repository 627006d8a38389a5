"""The edge-capture module's ``D,<row>`` lines: every seed decoded, every glitch named."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.errors import FieldError, FrameError
from protocol.seed_line import (
    MAX_LINE_BYTES,
    Rejected,
    SeedEdge,
    SeedLineDecoder,
    encode_seed_line,
    parse_seed_line,
)

ROWS = 6
rows_st = st.lists(st.integers(1, ROWS), max_size=40)


def stream(rows: list[int]) -> bytes:
    return b"".join(encode_seed_line(r) for r in rows)


def edges(events: list[SeedEdge | Rejected]) -> list[int]:
    return [e.row for e in events if isinstance(e, SeedEdge)]


def test_a_well_formed_line_decodes_to_its_row() -> None:
    assert SeedLineDecoder(ROWS).feed(b"D,3\r\n") == [SeedEdge(3)]


def test_a_bare_newline_terminator_is_accepted_because_adapters_drop_cr() -> None:
    assert SeedLineDecoder(ROWS).feed(b"D,1\nD,6\n") == [SeedEdge(1), SeedEdge(6)]


def test_zero_padded_rows_from_padding_firmware_decode() -> None:
    assert parse_seed_line(b"D,03\r\n", ROWS) == SeedEdge(3)


@pytest.mark.parametrize(
    ("line", "error", "reason"),
    [
        (b"D,0\r\n", FieldError, "row 0 outside 1..6"),
        (b"D,7\r\n", FieldError, "row 7 outside 1..6"),
        (b"D,-1\r\n", FieldError, "row must be a decimal number"),
        (b"D,\r\n", FieldError, "row must be a decimal number"),
        (b"D,x\r\n", FieldError, "row must be a decimal number"),
        (b"S,1\r\n", FrameError, "unknown record type 'S'"),
        (b"D1\r\n", FrameError, "no comma"),
        (b"\r\n", FrameError, "empty line"),
        (b"D,\xff\r\n", FrameError, "not ASCII"),
        (b"D,1\x00\r\n", FrameError, "control characters"),
    ],
)
def test_bad_lines_raise_a_specific_error(line: bytes, error: type[Exception], reason: str) -> None:
    with pytest.raises(error, match=reason):
        parse_seed_line(line, ROWS)


def test_a_bad_line_is_rejected_and_decoding_carries_on() -> None:
    dec = SeedLineDecoder(ROWS)
    events = dec.feed(b"D,2\r\nD,9\r\nD,4\r\n")
    assert edges(events) == [2, 4]
    rejected = [e for e in events if isinstance(e, Rejected)]
    assert rejected == [Rejected(b"D,9\r\n", "row 9 outside 1..6")]
    assert (dec.edges, dec.rejected) == (2, 1)


def test_an_overlong_run_without_newline_is_rejected_once_and_buffer_stays_capped() -> None:
    dec = SeedLineDecoder(ROWS)
    events = []
    for _ in range(100):
        events += dec.feed(b"ZZZZZZZZZZ")
        assert dec.buffered <= MAX_LINE_BYTES
    assert [e.reason for e in events if isinstance(e, Rejected)] == ["line too long"]
    # the rest of the garbage line is skipped; the next line decodes
    assert dec.feed(b"ZZ\r\nD,5\r\n") == [SeedEdge(5)]


def test_encoding_refuses_impossible_rows() -> None:
    with pytest.raises(FieldError):
        encode_seed_line(0)


def test_decoder_refuses_an_impossible_row_count() -> None:
    with pytest.raises(ValueError, match="rows must be"):
        SeedLineDecoder(0)


@given(rows_st)
def test_whole_stream_decodes_every_seed(rows: list[int]) -> None:
    assert edges(SeedLineDecoder(ROWS).feed(stream(rows))) == rows


@given(rows_st)
def test_byte_by_byte_feeding_decodes_every_seed(rows: list[int]) -> None:
    dec = SeedLineDecoder(ROWS)
    data = stream(rows)
    out: list[SeedEdge | Rejected] = []
    for i in range(len(data)):
        out += dec.feed(data[i : i + 1])
    assert edges(out) == rows


@given(rows_st.filter(bool), st.data())
def test_split_at_any_offset_decodes_every_seed(rows: list[int], data: st.DataObject) -> None:
    raw = stream(rows)
    cut = data.draw(st.integers(0, len(raw)))
    dec = SeedLineDecoder(ROWS)
    assert edges(dec.feed(raw[:cut]) + dec.feed(raw[cut:])) == rows


@given(st.binary(max_size=300))
def test_garbage_never_raises_and_never_overflows_the_buffer(junk: bytes) -> None:
    dec = SeedLineDecoder(ROWS)
    for ev in dec.feed(junk):
        assert isinstance(ev, SeedEdge | Rejected)
        if isinstance(ev, SeedEdge):
            assert 1 <= ev.row <= ROWS
    assert dec.buffered <= MAX_LINE_BYTES


@given(st.binary(max_size=100).filter(lambda b: b"\n" not in b), rows_st)
def test_after_garbage_and_a_newline_every_following_seed_decodes(
    junk: bytes, rows: list[int]
) -> None:
    dec = SeedLineDecoder(ROWS)
    dec.feed(junk + b"\n")
    assert edges(dec.feed(stream(rows))) == rows


@pytest.mark.parametrize(
    ("data", "kind"),
    [
        (b"D,9\r\n", "bad_row"),
        (b"D,x\r\n", "bad_row"),
        (b"S,1\r\n", "malformed"),
        (b"\xff\xfe\r\n", "malformed"),
        (b"D" * 40 + b"\r\n", "overlong"),
        (b"D" * 40, "overlong"),
    ],
)
def test_every_rejection_has_a_stable_kind_for_the_counters(data: bytes, kind: str) -> None:
    decoder = SeedLineDecoder(ROWS)
    rejected = [e for e in decoder.feed(data) if isinstance(e, Rejected)]
    assert [r.kind for r in rejected] == [kind]
