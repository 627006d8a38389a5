"""parse_command: any bytes on cmd/<name> become a Command or one clear CommandPayloadError.

Whoever may publish on cmd/ can send anything; what comes back must name the problem, and
nothing else may ever be raised (an exception escaping here used to restart the MQTT session).
"""

from __future__ import annotations

import json
import math
import re

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from gateway.core.commands import (
    AckAlarm,
    CalibrateSpeed,
    SelectSeedLot,
    SetChannelRate,
    SetRate,
    Start,
    Stop,
)
from gateway.core.errors import CommandError
from gateway.link.command_payloads import (
    KNOWN_COMMANDS,
    MAX_NESTING,
    CommandPayloadError,
    ParsedCommand,
    parse_command,
)

CAP = 4096  # the default [commands] max_payload_bytes
BIG_CAP = 65536  # the largest allowed


def parse(name: str, payload: bytes, cap: int = CAP) -> ParsedCommand:
    return parse_command(name, payload, max_payload_bytes=cap)


def refusal(name: str, payload: bytes, cap: int = CAP) -> CommandPayloadError:
    with pytest.raises(CommandPayloadError) as info:
        parse(name, payload, cap)
    return info.value


def assert_clear(error: CommandPayloadError) -> None:
    """A message an operator can act on: one short line, in our words, not pydantic's."""
    text = str(error)
    assert text.strip(), "empty error message"
    assert "\n" not in text and len(text) <= 1000, text
    assert "should" not in text, f"untranslated pydantic wording: {text}"


# -- what is accepted ---------------------------------------------------------------------------


def test_the_documented_commands_parse() -> None:
    assert parse("rate", b'{"crop": "wheat", "rate_kg_ha": 225.0, "request_id": "r1"}') == (
        ParsedCommand(SetRate("wheat", 225.0), "r1")
    )
    assert parse("channel_rate", b'{"channel": "deep", "rate_kg_ha": 280}').command == (
        SetChannelRate("deep", 280.0)
    )
    assert parse("speed_cal", b'{"action": "finish", "distance_m": 50}').command == (
        CalibrateSpeed("finish", 50.0)
    )
    assert parse("seed_lot", b'{"crop": "wheat", "lot": "2026-B"}').command == (
        SelectSeedLot("wheat", "2026-B")
    )
    assert parse("start", b"{}").command == Start()
    assert parse("stop", b"  \n").command == Stop()  # an empty payload is fine for these
    assert parse("ack_alarm", b'{"code": "pwm.unavailable"}').command == (
        AckAlarm("pwm.unavailable")
    )
    assert parse("ack_alarm", b"{}").command == AckAlarm(None)  # every one waiting


@pytest.mark.parametrize(("payload", "said"), [
    (b'{"crop": "wheat"}', "lot"),
    (b'{"crop": "wheat", "lot": 2}', "lot: must be a string"),
    (b'{"crop": "wheat", "lot": "a b"}', "lot"),
    (b'{"crop": "wheat", "lot": "x", "rate": 1}', "rate"),
])
def test_a_seed_lot_command_is_strict(payload: bytes, said: str) -> None:
    with pytest.raises(CommandPayloadError) as info:
        parse("seed_lot", payload)
    assert said in str(info.value)
    assert_clear(info.value)


def test_a_json_integer_is_a_number_and_arrives_as_a_float() -> None:
    command = parse("rate", b'{"crop": "wheat", "rate_kg_ha": 200}').command
    assert isinstance(command, SetRate) and type(command.rate_kg_ha) is float


def test_brackets_inside_strings_are_not_nesting() -> None:
    crop = "[" * 50
    payload = json.dumps({"crop": crop, "rate_kg_ha": 1}).encode()
    assert parse("rate", payload).command == SetRate(crop, 1.0)


# -- what is refused, and how it is said -------------------------------------------------------


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        # strict: nothing is guessed
        (b'{"crop": "wheat", "rate_kg_ha": "200"}',
         "rate_kg_ha: must be a number (got string '200')"),
        (b'{"crop": "wheat", "rate_kg_ha": true}', "rate_kg_ha: must be a number (got true)"),
        (b'{"crop": "wheat", "rate_kg_ha": null}', "rate_kg_ha: must be a number (got null)"),
        (b'{"crop": "wheat", "rate_kg_ha": [200]}', "rate_kg_ha: must be a number (got array)"),
        (b'{"crop": 7, "rate_kg_ha": 200}', "crop: must be a string (got number 7)"),
        (b'{"crop": "wheat", "rate_kg_ha": NaN}',
         "rate_kg_ha: must be a finite number (got NaN)"),
        (b'{"crop": "wheat", "rate_kg_ha": Infinity}',
         "rate_kg_ha: must be a finite number (got Infinity)"),
        (b'{"crop": "wheat", "rate_kg_ha": 1e999}',
         "rate_kg_ha: must be a finite number (got Infinity)"),
        (b'{"crop": "wheat", "rate_kg_ha": -5}',
         "rate_kg_ha: must be greater than 0 (got number -5)"),
        (b'{"crop": "", "rate_kg_ha": 5}', "crop: must have at least 1 character (got string '')"),
        (b'{"crop": "wheat"}', "rate_kg_ha: required field is missing"),
        (b'{"crop": "wheat", "rate_kg_ha": 5, "rate": 6}',
         "rate: unknown field (allowed: request_id, crop, rate_kg_ha)"),
        (b'{"crop": "wheat", "rate_kg_ha": 5, "request_id": 12}',
         "request_id: must be a string (got number 12)"),
        # not a command-shaped document at all
        (b"[1, 2]", "payload must be a JSON object, got array"),
        (b'"wheat"', "payload must be a JSON object, got string"),
        (b"null", "payload must be a JSON object, got null"),
        (b"", "payload is empty; this command needs a JSON object"),
        (b"not json", "payload is not valid JSON"),
        (b'{"crop": "wheat"} trailing', "payload is not valid JSON: trailing characters"),
        (b'{"crop": "\xff"}', "payload is not UTF-8 text (invalid byte at offset 10)"),
        (b"[" * 2000, f"payload is nested more than {MAX_NESTING} levels deep"),
        (b'{"a": ' * 100, f"payload is nested more than {MAX_NESTING} levels deep"),
        (b"x" * (CAP + 1), f"payload too large: {CAP + 1} bytes (max {CAP})"),
    ],
)
def test_a_bad_rate_command_is_refused_naming_the_problem(payload: bytes, message: str) -> None:
    error = refusal("rate", payload)
    assert str(error).startswith(message), str(error)
    assert_clear(error)


def test_the_speed_cal_action_lists_what_is_allowed() -> None:
    error = refusal("speed_cal", b'{"action": "jump"}')
    assert str(error) == "action: must be 'start', 'finish' or 'cancel' (got string 'jump')"


def test_a_refusal_keeps_the_senders_request_id() -> None:
    error = refusal("rate", b'{"crop": "wheat", "rate_kg_ha": "200", "request_id": "r7"}')
    assert error.request_id == "r7"
    assert refusal("rate", b'{"rate_kg_ha": "200", "request_id": 7}').request_id is None


def test_unknown_commands_are_named_and_the_known_ones_listed() -> None:
    error = refusal("fly", b"{}")
    assert str(error) == f"unknown command 'fly' (known: {', '.join(KNOWN_COMMANDS)})"
    long_name = refusal("x" * 60_000, b"{}")
    assert "'" + "x" * 40 + "…'" in str(long_name) and len(str(long_name)) < 300


def test_a_huge_integer_is_refused_without_pythons_digit_limit_error() -> None:
    # json.loads raises a bare ValueError above 4300 digits; the float field refuses a big one
    digits = refusal("rate", b'{"crop": "w", "rate_kg_ha": ' + b"9" * 5000 + b"}", BIG_CAP)
    assert str(digits).startswith("payload is not valid JSON: number out of range")
    big = refusal("rate", b'{"crop": "w", "rate_kg_ha": ' + b"9" * 400 + b"}")
    assert str(big) == "rate_kg_ha: must be a number (got an integer too large for any field)"


def test_odd_keys_are_quoted_and_many_problems_summarised() -> None:
    error = refusal("start", json.dumps({"line\nbreak": 1}).encode())
    assert str(error).startswith("'line\\nbreak': unknown field")
    many = refusal("start", json.dumps({f"k{i}": i for i in range(50)}).encode())
    assert str(many) == "unknown fields k0, k1, k2, k3, k4 and 45 more (allowed: request_id)"
    assert_clear(many)


def test_the_error_is_a_command_error_like_any_refused_command() -> None:
    assert issubclass(CommandPayloadError, CommandError)


# -- fuzz: nothing but CommandPayloadError, ever -----------------------------------------------

NAMES = st.sampled_from([*KNOWN_COMMANDS, "", "fly", "rate/ack"]) | st.text(max_size=50)


def parse_or_refuse(name: str, payload: bytes, cap: int = CAP) -> ParsedCommand | None:
    """Parse; a refusal must be a clear CommandPayloadError (anything else fails the test)."""
    try:
        parsed = parse(name, payload, cap)
    except CommandPayloadError as error:
        assert_clear(error)
        return None
    for value in vars(parsed.command).values():  # what reaches the controller is well typed
        assert value is None or isinstance(value, str) or (
            type(value) is float and math.isfinite(value)
        ), parsed
    return parsed


@settings(max_examples=500, deadline=None)
@given(name=NAMES, payload=st.binary(max_size=5000))
@example(name="rate", payload=b"[" * 2000)  # json.loads: RecursionError
@example(name="rate", payload=b'{"rate_kg_ha": ' + b"9" * 4400 + b"}")  # json.loads: ValueError
@example(name="start", payload=b"\xff\xfe{}")
def test_fuzz_arbitrary_bytes(name: str, payload: bytes) -> None:
    parse_or_refuse(name, payload, BIG_CAP)


JSON_LEAVES = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=-(10**400), max_value=10**400)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=80)
    | st.sampled_from(["200", "wheat", "start", "finish", "cancel", "deep", ""])
)
JSON_VALUES = st.recursive(
    JSON_LEAVES,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=4),
    max_leaves=20,
)
FIELDS = st.sampled_from(
    ["crop", "rate_kg_ha", "channel", "action", "distance_m", "request_id", "force"]
) | st.text(max_size=12)


@settings(max_examples=1000, deadline=None)
@given(
    name=st.sampled_from(list(KNOWN_COMMANDS)),
    document=st.dictionaries(FIELDS, JSON_VALUES, max_size=6) | JSON_VALUES,
)
def test_fuzz_json_of_every_type_in_every_field(name: str, document: object) -> None:
    # json.dumps writes NaN/Infinity as the bare tokens dashboards (and JavaScript) produce
    parse_or_refuse(name, json.dumps(document).encode(), BIG_CAP)


@settings(max_examples=200, deadline=None)
@given(
    name=st.sampled_from(list(KNOWN_COMMANDS)),
    opening=st.lists(st.sampled_from(['[', '{"a": ', '[1, ', '{"b": [']), min_size=1,
                     max_size=3000),
    closed=st.booleans(),
)
@example(name="rate", opening=["["] * 2000, closed=False)
@example(name="speed_cal", opening=['{"a": '] * 1500, closed=True)
def test_fuzz_deep_nesting(name: str, opening: list[str], closed: bool) -> None:
    text = "".join(opening)
    if closed:  # a well-formed document, as deep as the brackets go
        text += "0" + "".join("]" if o.startswith("[") else "}" for o in reversed(opening))
    depth = sum(o.count("[") + o.count("{") for o in opening)
    payload = text.encode()
    result = parse_or_refuse(name, payload, BIG_CAP)
    assert result is None  # no command is an array, or nests
    if depth > MAX_NESTING and len(payload) <= BIG_CAP:
        assert "nested more than" in str(refusal(name, payload, BIG_CAP))


@settings(max_examples=300, deadline=None)
@given(
    crop=st.text(min_size=1, max_size=64),
    rate=st.floats(min_value=0, exclude_min=True, allow_infinity=False) | st.integers(1, 10**6),
    request_id=st.none() | st.text(max_size=128),
)
def test_fuzz_every_valid_rate_command_arrives_unchanged(
    crop: str, rate: float, request_id: str | None
) -> None:
    document: dict[str, object] = {"crop": crop, "rate_kg_ha": rate}
    if request_id is not None:
        document["request_id"] = request_id
    parsed = parse("rate", json.dumps(document).encode())
    assert parsed == ParsedCommand(SetRate(crop, float(rate)), request_id)


def test_fuzz_messages_quote_values_briefly() -> None:
    error = refusal("rate", json.dumps({"crop": "w", "rate_kg_ha": "9" * 3000}).encode())
    assert re.fullmatch(r"rate_kg_ha: must be a number \(got string '9{40}…'\)", str(error))
