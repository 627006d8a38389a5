"""The byte-stream decoder: same events however the bytes are chunked, noise counted, bounded."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.gnss import (
    MAX_LINE_BYTES,
    REASON_CHECKSUM,
    REASON_GARBAGE,
    REASON_OVERLONG,
    REASON_TRUNCATED,
    REASON_UNKNOWN,
    GnssEvent,
    GnssLineDecoder,
    Rejected,
    decode_line,
)
from protocol.nmea import Gga, Rmc, encode_nmea
from protocol.unicore import Heading
from simulator.um982 import corrupt_checksum, um982_sentences

T0 = datetime(2024, 6, 1, 8, 0, 0, tzinfo=UTC)


def _stream(n_epochs: int = 3) -> bytes:
    lines: list[str] = []
    for k in range(n_epochs):
        lines += um982_sentences(
            T0 + timedelta(seconds=k / 10), 45.0 + k * 1e-6, 7.0, 250.0, 8.0, 90.0, 91.0
        )
    return "".join(f"{ln}\r\n" for ln in lines).encode()


def _feed_chunks(chunks: list[bytes]) -> list[GnssEvent | Rejected]:
    decoder = GnssLineDecoder()
    out: list[GnssEvent | Rejected] = []
    for chunk in chunks:
        out += decoder.feed(chunk)
    return out


def test_whole_stream_decodes_to_rmc_gga_heading_per_epoch() -> None:
    events = _feed_chunks([_stream(3)])
    assert [type(e) for e in events] == [Rmc, Gga, Heading] * 3


def test_byte_by_byte_feeding_gives_the_same_events() -> None:
    data = _stream(2)
    assert _feed_chunks([data[i : i + 1] for i in range(len(data))]) == _feed_chunks([data])


def test_split_at_every_offset_gives_the_same_events() -> None:
    data = _stream(1)
    whole = _feed_chunks([data])
    for cut in range(len(data) + 1):
        assert _feed_chunks([data[:cut], data[cut:]]) == whole


@given(st.lists(st.integers(1, 64), max_size=40))
def test_any_chunking_gives_the_same_events(sizes: list[int]) -> None:
    data = _stream(2)
    chunks, i = [], 0
    for size in sizes:
        chunks.append(data[i : i + size])
        i += size
    chunks.append(data[i:])
    assert _feed_chunks(chunks) == _feed_chunks([data])


def test_lf_only_line_endings_work() -> None:
    data = _stream(1).replace(b"\r\n", b"\n")
    assert [type(e) for e in _feed_chunks([data])] == [Rmc, Gga, Heading]


def test_noise_before_a_sentence_is_counted_and_the_sentence_still_decodes() -> None:
    decoder = GnssLineDecoder()
    out = decoder.feed(b"\x00\xff\x13abc" + _stream(1))
    assert isinstance(out[0], Rejected) and out[0].reason == REASON_GARBAGE
    assert [type(e) for e in out[1:]] == [Rmc, Gga, Heading]
    assert decoder.counts == {"ok": 3, REASON_GARBAGE: 1}


def test_sentence_cut_by_a_reconnect_is_rejected_and_the_next_one_survives() -> None:
    rmc, gga, _ = um982_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0)
    decoder = GnssLineDecoder()
    out = decoder.feed(f"{rmc[:30]}{gga}\r\n".encode())
    assert isinstance(out[0], Rejected) and out[0].reason == REASON_GARBAGE
    assert isinstance(out[1], Gga)


def test_counters_per_reason() -> None:
    rmc, gga, hdg = um982_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0)
    lines = [
        rmc, corrupt_checksum(gga), corrupt_checksum(hdg), rmc[:20], encode_nmea("GNGSV,1,1,00"),
        "noise without start", hdg,
    ]
    decoder = GnssLineDecoder()
    out = decoder.feed("".join(f"{ln}\r\n" for ln in lines).encode())
    assert decoder.counts == {
        "ok": 2, REASON_CHECKSUM: 2, REASON_TRUNCATED: 1, REASON_UNKNOWN: 1, REASON_GARBAGE: 1,
    }
    assert decoder.rejected_total == 5
    assert len(out) == 7


def test_blank_lines_are_ignored() -> None:
    decoder = GnssLineDecoder()
    assert decoder.feed(b"\r\n\n  \r\n") == []
    assert decoder.counts == {}


def test_overlong_line_is_dropped_once_and_the_buffer_stays_bounded() -> None:
    decoder = GnssLineDecoder()
    out: list[GnssEvent | Rejected] = []
    for _ in range(10):
        out += decoder.feed(b"A" * 500)  # a receiver at the wrong baud rate, no newline
        assert decoder.buffered_bytes <= MAX_LINE_BYTES
    out += decoder.feed(b"\r\n" + _stream(1))
    assert [r.reason for r in out if isinstance(r, Rejected)] == [REASON_OVERLONG]
    assert [type(e) for e in out if not isinstance(e, Rejected)] == [Rmc, Gga, Heading]


def test_flush_reports_an_unfinished_line() -> None:
    decoder = GnssLineDecoder()
    assert decoder.feed(b"$GNRMC,1200") == []
    (rej,) = decoder.flush()
    assert isinstance(rej, Rejected) and rej.reason == REASON_TRUNCATED
    assert decoder.buffered_bytes == 0


@settings(max_examples=200)
@given(st.binary(max_size=3000))
def test_random_bytes_never_raise_and_never_grow_the_buffer(noise: bytes) -> None:
    decoder = GnssLineDecoder()
    for item in decoder.feed(noise):
        assert isinstance(item, Rejected) or item is not None
    assert decoder.buffered_bytes <= MAX_LINE_BYTES
    # and the stream recovers after the next newline
    tail = decoder.feed(b"\n" + _stream(1))
    assert [type(e) for e in tail if not isinstance(e, Rejected)][-3:] == [Rmc, Gga, Heading]


def test_decode_line_dispatches_on_the_start_character() -> None:
    rmc, _, hdg = um982_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0)
    assert isinstance(decode_line(rmc + "\r\n"), Rmc)
    assert isinstance(decode_line(hdg), Heading)


def test_sentences_run_together_by_a_lost_line_terminator_all_decode() -> None:
    rmc, gga, hdg = um982_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0)
    decoder = GnssLineDecoder()
    out = decoder.feed(f"{rmc}{gga}{hdg}\r\n".encode())
    assert [type(e) for e in out] == [Rmc, Gga, Heading]
    assert decoder.counts == {"ok": 3}


def test_noise_and_a_cut_head_before_a_whole_sentence_are_one_garbage_report() -> None:
    rmc, gga, hdg = um982_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0)
    decoder = GnssLineDecoder()
    out = decoder.feed(f"\x13zz{rmc[:25]}{gga}{hdg}\r\n".encode())
    assert isinstance(out[0], Rejected) and out[0].reason == REASON_GARBAGE
    assert "28 bytes" in out[0].detail  # 3 noise + 25 of the cut RMC
    assert [type(e) for e in out[1:]] == [Gga, Heading]
    assert decoder.counts == {"ok": 2, REASON_GARBAGE: 1}


# ---- binary output on the same port (u-blox UBX, Unicore binary logs) ----------------------

_START_OR_LF = frozenset(b"$#\n")
# binary junk that cannot start a sentence or end a line: the worst case, one endless "line"
binary_junk = st.binary(max_size=5000).map(
    lambda b: bytes(x for x in b if x not in _START_OR_LF)
)


def _one_sentence(kind: int) -> str:
    return um982_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0)[kind]


def _chunked(data: bytes, sizes: list[int]) -> list[bytes]:
    chunks, i = [], 0
    for size in sizes:
        chunks.append(data[i : i + size])
        i += size
    chunks.append(data[i:])
    return chunks


def test_a_sentence_after_a_kilobyte_of_binary_without_newline_still_decodes() -> None:
    binary = bytes(range(0x80, 0x100)) * 8  # 1 024 bytes, no '$', '#' or LF among them
    line = _one_sentence(0)
    decoder = GnssLineDecoder()
    out = decoder.feed(binary + f"{line}\r\n".encode())
    assert out[-1] == decode_line(line)
    assert [r.reason for r in out if isinstance(r, Rejected)] == [REASON_OVERLONG]
    assert decoder.discarded_bytes == len(binary)
    assert decoder.counts == {"ok": 1, REASON_OVERLONG: 1}


@settings(max_examples=150)
@given(
    junk=binary_junk,
    kind=st.sampled_from([0, 1, 2]),
    sizes=st.lists(st.integers(1, 700), max_size=30),
)
def test_any_binary_junk_then_a_valid_sentence_decodes_and_discards_exactly(
    junk: bytes, kind: int, sizes: list[int]
) -> None:
    sentence = _one_sentence(kind)
    line = junk + f"{sentence}\r\n".encode()
    decoder = GnssLineDecoder()
    out: list[GnssEvent | Rejected] = []
    for chunk in _chunked(line, sizes):
        out += decoder.feed(chunk)
        assert decoder.buffered_bytes <= MAX_LINE_BYTES
    assert out[-1] == decode_line(sentence)
    overlong = len(junk) + len(sentence) + 1 > MAX_LINE_BYTES  # + the CR before the LF
    assert decoder.discarded_bytes == (len(junk) if overlong else 0)
    assert decoder.counts[REASON_OVERLONG] == (1 if overlong else 0)


@settings(max_examples=150)
@given(
    junk=st.binary(max_size=5000).map(lambda b: b.replace(b"\n", b"")),
    kind=st.sampled_from([0, 1, 2]),
    sizes=st.lists(st.integers(1, 700), max_size=30),
)
def test_junk_with_stray_start_characters_still_lets_the_sentence_through_however_split(
    junk: bytes, kind: int, sizes: list[int]
) -> None:
    sentence = _one_sentence(kind)
    line = junk + f"{sentence}\r\n".encode()
    whole = GnssLineDecoder()
    expected = whole.feed(line)
    assert expected[-1] == decode_line(sentence)
    assert whole.discarded_bytes <= len(junk)
    chunked = GnssLineDecoder()
    out: list[GnssEvent | Rejected] = []
    for chunk in _chunked(line, sizes):
        out += chunked.feed(chunk)
        assert chunked.buffered_bytes <= MAX_LINE_BYTES
    assert out == expected
    assert chunked.discarded_bytes == whole.discarded_bytes
    assert chunked.counts == whole.counts


def test_endless_binary_keeps_counting_the_discarded_bytes() -> None:
    decoder = GnssLineDecoder()
    for _ in range(100):
        decoder.feed(b"\xb5\x62" * 2000)
        assert decoder.buffered_bytes <= MAX_LINE_BYTES
    assert decoder.discarded_bytes == 100 * 4000
    assert decoder.counts == {REASON_OVERLONG: 1}  # one line, one report


def test_an_overlong_proprietary_sentence_is_unknown_not_malformed() -> None:
    decoder = GnssLineDecoder()
    decoder.feed(f"{encode_nmea('PQTMEPE,' + ','.join(['1.234'] * 60))}\r\n".encode())
    assert decoder.counts == {REASON_UNKNOWN: 1}
