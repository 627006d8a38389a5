"""The TJC screen protocol: 55 55 F C R1 R2 0D 0A frames in, Nextion instructions out."""

from __future__ import annotations

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from protocol.errors import FieldError, ProtocolError
from protocol.hmi import (
    MAX_BUFFER,
    MAX_TEXT_BYTES,
    AckAlarm,
    EmptySeed,
    HmiCommand,
    HmiDecoder,
    HmiEvent,
    NextionReplyDecoder,
    Rejected,
    RotationTest,
    ScreenError,
    ScreenReply,
    SeedLevelMonitoring,
    SelectCrop,
    SelectSeedLot,
    StartWork,
    StopWork,
    ZeroTilt,
    encode_frame,
    parse_instruction,
    set_text,
    set_value,
)


def frame(f: int, c: int = 0, r1: int = 0, r2: int = 0, trailer: bytes = b"\r\n") -> bytes:
    return bytes((0x55, 0x55, f, c, r1, r2)) + trailer


def decode_all(data: bytes) -> list[HmiEvent]:
    decoder = HmiDecoder()
    return decoder.feed(data) + decoder.flush()


def decode_bytewise(data: bytes) -> list[HmiEvent]:
    decoder = HmiDecoder()
    events: list[HmiEvent] = []
    for i in range(len(data)):
        events += decoder.feed(data[i : i + 1])
    return events + decoder.flush()


def decode_split(data: bytes, cut: int) -> list[HmiEvent]:
    decoder = HmiDecoder()
    return decoder.feed(data[:cut]) + decoder.feed(data[cut:]) + decoder.flush()


# -- function codes ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("raw", "event"),
    [
        (frame(0x01), StartWork()),
        (frame(0x02), StopWork()),
        (frame(0x03, 0x02, 0x08, 0xCA), SelectCrop(2, 225.0)),
        (frame(0x03, 0x01, 0x00, 0x3C), SelectCrop(1, 6.0)),
        (frame(0x04), EmptySeed()),
        (frame(0x05, 0x01), SeedLevelMonitoring(True)),
        (frame(0x05, 0x00), SeedLevelMonitoring(False)),
        (frame(0x06), ZeroTilt()),
        (frame(0x07), AckAlarm()),
        (frame(0x08, 0x02, 0x00, 0x01), SelectSeedLot(2, 1)),
        (frame(0x08, 0x01, 0x01, 0x00), SelectSeedLot(1, 256)),
        (frame(0x09, 0x01, 0x01, 0xC2), RotationTest("run", 45.0)),
        (frame(0x09, 0x03, 0x10, 0x04), RotationTest("mass", 410.0)),
        (frame(0x09, 0x00), RotationTest("cancel", 0.0)),
        (frame(0x09, 0x05), RotationTest("save_confirmed", 0.0)),
    ],
)
def test_every_function_code_decodes_to_its_command(raw: bytes, event: HmiEvent) -> None:
    """Each documented F byte maps to one typed command."""
    assert HmiDecoder().feed(raw) == [event]


def test_seed_lot_frame_is_crop_code_and_a_big_endian_lot_number_both_ways() -> None:
    assert encode_frame(SelectSeedLot(2, 1)) == bytes.fromhex("5555080200010D0A")
    assert HmiDecoder().feed(encode_frame(SelectSeedLot(1, 300))) == [SelectSeedLot(1, 300)]


@pytest.mark.parametrize("c", [0x06, 0x80, 0xFF])
def test_a_rotation_test_action_beyond_05_is_rejected(c: int) -> None:
    [event] = HmiDecoder().feed(frame(0x09, c))
    assert isinstance(event, Rejected) and event.kind == "bad_field"
    assert "rotation test action" in event.reason


def test_wheat_225_kg_ha_is_08_ca_both_ways() -> None:
    """The paper's worked example: 225.0 kg/ha = 2250 = 0x08CA, big-endian."""
    assert encode_frame(SelectCrop(2, 225.0)) == bytes.fromhex("5555030208CA0D0A")
    assert HmiDecoder().feed(bytes.fromhex("5555030208CA0D0A")) == [SelectCrop(2, 225.0)]


def test_largest_rate_field_decodes_without_range_judgement() -> None:
    """0xFFFF is 6553.5 kg/ha; range checks belong to the gateway, which knows the crops."""
    assert HmiDecoder().feed(frame(0x03, 0x07, 0xFF, 0xFF)) == [SelectCrop(7, 6553.5)]


@pytest.mark.parametrize("f", [0x01, 0x02, 0x04, 0x06, 0x07])
def test_c_and_r_bytes_are_ignored_where_unused(f: int) -> None:
    """Screens built from other projects' page files fill unused bytes with anything."""
    plain = HmiDecoder().feed(frame(f))
    assert HmiDecoder().feed(frame(f, 0xAB, 0xCD, 0xEF)) == plain
    assert len(plain) == 1 and not isinstance(plain[0], Rejected)


@pytest.mark.parametrize("c", [0x02, 0x10, 0xFF])
def test_seed_level_flag_other_than_0_or_1_is_rejected(c: int) -> None:
    """F=05 carries a boolean; anything else is a misconfigured button, not 'on'."""
    [event] = HmiDecoder().feed(frame(0x05, c))
    assert isinstance(event, Rejected)
    assert "seed-level" in event.reason and event.raw == frame(0x05, c)


@pytest.mark.parametrize("f", [0x00, 0x0A, 0x55, 0xFF])
def test_unknown_function_code_is_rejected_with_the_code(f: int) -> None:
    [event] = HmiDecoder().feed(frame(f))
    assert event == Rejected(f"unknown function code 0x{f:02X}", frame(f))


def test_bad_trailer_is_rejected_and_the_next_frame_still_decodes() -> None:
    """A frame with a wrong trailer is dropped whole (one Rejected), then sync is regained."""
    bad = frame(0x01, trailer=b"\r\r")
    events = decode_all(bad + frame(0x02))
    assert len(events) == 2
    assert isinstance(events[0], Rejected) and "bad trailer 0D 0D" in events[0].reason
    assert events[0].raw == bad
    assert events[1] == StopWork()


def test_frame_hidden_inside_a_bad_frame_is_found() -> None:
    """Resync looks for 55 55 inside the rejected bytes rather than skipping 8 at a time."""
    data = b"\x55\x55\x01\x00" + frame(0x06)  # a truncated frame, then a good one
    events = decode_all(data)
    assert events[-1] == ZeroTilt()
    assert [type(e) for e in events] == [Rejected, ZeroTilt]
    assert isinstance(events[0], Rejected) and events[0].raw == b"\x55\x55\x01\x00"


def test_garbage_between_frames_is_one_rejected_per_run() -> None:
    """Noise is reported once per run, not once per byte, and never eats a frame."""
    data = frame(0x01) + b"hello noise" + frame(0x02) + b"\x00\x01" + b"\x02" + frame(0x04)
    for events in (decode_all(data), decode_bytewise(data)):
        assert events == [
            StartWork(),
            Rejected("11 byte(s) of garbage, not a 55 55 frame", b"hello noise"),
            StopWork(),
            Rejected("3 byte(s) of garbage, not a 55 55 frame", b"\x00\x01\x02"),
            EmptySeed(),
        ]


def test_trailing_garbage_waits_for_flush() -> None:
    """Without a following frame the decoder cannot know the run is over; flush() ends it."""
    decoder = HmiDecoder()
    assert decoder.feed(b"junk") == []
    assert decoder.pending
    assert decoder.flush() == [Rejected("4 byte(s) of garbage, not a 55 55 frame", b"junk")]
    assert not decoder.pending


def test_truncated_frame_is_reported_as_incomplete_on_flush() -> None:
    decoder = HmiDecoder()
    assert decoder.feed(b"\x55\x55\x03\x02") == []
    assert decoder.flush() == [Rejected("incomplete frame", b"\x55\x55\x03\x02")]
    assert decoder.feed(frame(0x01)) == [StartWork()]


def test_frame_split_at_every_offset_decodes() -> None:
    data = frame(0x03, 0x02, 0x08, 0xCA) + frame(0x01)
    for cut in range(len(data) + 1):
        assert decode_split(data, cut) == [SelectCrop(2, 225.0), StartWork()], cut
    assert decode_bytewise(data) == [SelectCrop(2, 225.0), StartWork()]


def test_endless_garbage_is_reported_in_capped_runs() -> None:
    """Memory stays bounded: every MAX_BUFFER bytes of noise become one Rejected."""
    decoder = HmiDecoder()
    events: list[HmiEvent] = []
    for _ in range(10):
        events += decoder.feed(b"\xaa" * (MAX_BUFFER // 2 + 3))
    assert len(events) == (10 * (MAX_BUFFER // 2 + 3)) // MAX_BUFFER
    assert all(isinstance(e, Rejected) and len(e.raw) == MAX_BUFFER for e in events)
    assert decoder.garbage_run_bytes < MAX_BUFFER and decoder.partial_frame_bytes < 8
    assert decoder.feed(frame(0x01))[-1] == StartWork()


def test_nextion_error_replies_are_not_called_garbage() -> None:
    """The screen's own `1A FF FF FF` on the same wire is a ScreenError, not a bad frame."""
    data = frame(0x01) + b"\x1a\xff\xff\xff" + frame(0x02) + b"\x01\xff\xff\xff"
    assert decode_all(data) == [StartWork(), ScreenError(0x1A), StopWork(), ScreenReply(1, b"")]
    assert ScreenError(0x1A).meaning == "invalid variable name or attribute"


def test_reply_decoder_reads_return_codes_split_anywhere() -> None:
    data = b"\x1a\xff\xff\xff\x02\xff\xff\xff\x88\xff\xff\xff"
    expected = [ScreenError(0x1A), ScreenError(0x02), ScreenReply(0x88, b"")]
    for cut in range(len(data) + 1):
        decoder = NextionReplyDecoder()
        assert decoder.feed(data[:cut]) + decoder.feed(data[cut:]) == expected


# -- encoding ---------------------------------------------------------------------------------


def test_encode_frame_round_trips_every_command() -> None:
    commands: list[HmiCommand] = [
        StartWork(),
        StopWork(),
        SelectCrop(1, 4.5),
        EmptySeed(),
        SeedLevelMonitoring(True),
        SeedLevelMonitoring(False),
        ZeroTilt(),
        AckAlarm(),
    ]
    for command in commands:
        assert HmiDecoder().feed(encode_frame(command)) == [command]


@pytest.mark.parametrize(
    "command", [SelectCrop(1, 6553.6), SelectCrop(1, -0.1), SelectCrop(256, 6)]
)
def test_encode_frame_refuses_fields_that_do_not_fit(command: SelectCrop) -> None:
    with pytest.raises(FieldError):
        encode_frame(command)


def test_set_text_is_a_terminated_txt_assignment() -> None:
    assert set_text("t_speed", "4.8 km/h", "ascii") == b't_speed.txt="4.8 km/h"\xff\xff\xff'


def test_set_text_escapes_quotes_and_backslashes() -> None:
    """A quote in the text must not end the string and run the rest as an instruction."""
    raw = set_text("t_msg", 'say "hi" \\ bye', "ascii")
    assert raw == b't_msg.txt="say \\"hi\\" \\\\ bye"\xff\xff\xff'
    assert parse_instruction(raw[:-3]) == ("t_msg", 'say "hi" \\ bye')


def test_set_text_uses_the_configured_encoding() -> None:
    """Chinese fonts on TJC screens are GB2312."""
    raw = set_text("t_state", "播种", "gb2312")
    assert raw == b't_state.txt="' + "播种".encode("gb2312") + b'"\xff\xff\xff'


@pytest.mark.parametrize(
    ("text", "encoding", "payload"),
    [
        ("播种 ok", "ascii", b"?? ok"),
        ("ÿes", "latin-1", b"?es"),  # 0xFF would terminate the instruction
        ("a\tb", "ascii", b"a?b"),
        ("line1\nline2", "ascii", b"line1\\rline2"),
    ],
)
def test_set_text_never_fails_on_the_text(text: str, encoding: str, payload: bytes) -> None:
    assert set_text("t0", text, encoding) == b't0.txt="' + payload + b'"\xff\xff\xff'


def test_set_text_caps_the_payload() -> None:
    raw = set_text("t0", "x" * 5000, "ascii")
    assert len(raw) == len(b't0.txt=""\xff\xff\xff') + MAX_TEXT_BYTES


@pytest.mark.parametrize("obj", ["", "t 0", 't0.txt="x"\xff', "0abc", "a.b.c"])
def test_bad_object_names_are_refused(obj: str) -> None:
    with pytest.raises(ProtocolError):
        set_text(obj, "x")


def test_set_value_writes_a_number() -> None:
    assert set_value("n_duty", -42) == b"n_duty.val=-42\xff\xff\xff"
    assert set_value("page0.n0", 7) == b"page0.n0.val=7\xff\xff\xff"
    with pytest.raises(FieldError):
        set_value("n0", 2**31)


# -- hypothesis -------------------------------------------------------------------------------

commands = st.one_of(
    st.just(StartWork()),
    st.just(StopWork()),
    st.builds(SelectCrop, st.integers(0, 255), st.integers(0, 0xFFFF).map(lambda r: r / 10)),
    st.just(EmptySeed()),
    st.builds(SeedLevelMonitoring, st.booleans()),
    st.just(ZeroTilt()),
    st.just(AckAlarm()),
    st.builds(SelectSeedLot, st.integers(0, 255), st.integers(0, 0xFFFF)),
    st.builds(RotationTest, st.sampled_from(["cancel", "run", "rpm", "mass", "save"]),
              st.integers(0, 0xFFFF).map(lambda r: r / 10)),
)
garbage = st.binary(min_size=1, max_size=40)
stream_items = st.lists(st.one_of(commands, garbage), max_size=12)


def build_stream(items: list[HmiCommand | bytes]) -> tuple[bytes, list[HmiCommand], int]:
    """Concatenate items; merged garbage runs must not contain a header or reply terminator."""
    data = b""
    expected: list[HmiCommand] = []
    runs = 0
    run = b""
    for item in [*items, None]:
        if isinstance(item, bytes):
            run += item
            continue
        if run:
            assume(b"\x55\x55" not in run and b"\xff\xff\xff" not in run)
            data += run
            runs += 1
            run = b""
        if item is not None:
            data += encode_frame(item)
            expected.append(item)
    return data, expected, runs


@given(stream_items)
def test_fuzz_valid_frames_survive_any_garbage(items: list[HmiCommand | bytes]) -> None:
    """Whole, byte-by-byte and split anywhere: the same frames, one Rejected per garbage run."""
    data, expected, runs = build_stream(items)
    whole = decode_all(data)
    assert [e for e in whole if not isinstance(e, Rejected)] == expected
    assert sum(isinstance(e, Rejected) for e in whole) == runs
    assert decode_bytewise(data) == whole
    for cut in range(len(data) + 1):
        assert decode_split(data, cut) == whole


@given(st.binary(max_size=300))
def test_fuzz_arbitrary_bytes_never_crash_and_stay_bounded(data: bytes) -> None:
    decoder = HmiDecoder()
    events = decoder.feed(data)
    assert decoder.partial_frame_bytes < 8 and decoder.garbage_run_bytes < MAX_BUFFER
    events += decoder.flush()
    assert all(not isinstance(e, Rejected) or 0 < len(e.raw) <= MAX_BUFFER for e in events)
    assert decode_bytewise(data) == events


@given(st.text(max_size=80), st.sampled_from(["ascii", "gb2312", "latin-1", "utf-8"]))
def test_fuzz_set_text_is_one_well_formed_instruction(text: str, encoding: str) -> None:
    """Whatever the text, exactly one FF FF FF at the end and the quotes stay balanced."""
    raw = set_text("t0", text, encoding)
    assert raw.endswith(b"\xff\xff\xff") and raw.count(b"\xff") == 3
    parsed = parse_instruction(raw[:-3], encoding)
    assert parsed is not None and parsed[0] == "t0"
    if text.isascii() and text.isprintable():
        assert parsed[1] == text


@pytest.mark.parametrize(
    ("data", "kind"),
    [
        (b"hello noise", "garbage"),
        (frame(0x0A), "unknown_function"),
        (frame(0x05, 7), "bad_field"),
        (frame(0x01, trailer=b"\x0d\x0b"), "bad_trailer"),
        (b"\x55\x55\x03\x02", "incomplete_frame"),
    ],
)
def test_every_rejection_has_a_stable_kind_for_the_counters(data: bytes, kind: str) -> None:
    rejected = [e for e in decode_all(data) if isinstance(e, Rejected)]
    assert [r.kind for r in rejected] == [kind]
