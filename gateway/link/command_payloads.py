"""Parse one MQTT command payload into a ``Command``: a pure function, no I/O.

Everything on ``cmd/<name>`` comes from the network, so whoever may publish there can send any
bytes at all. ``parse_command`` turns them into a ``Command`` or raises ``CommandPayloadError``
with a message that names the problem (``rate_kg_ha: must be a number (got string '200')``),
and never raises anything else: the MQTT link turns the error into the command's ack, and a
parse can never take the MQTT session down. Being pure, it is fuzzed directly
(tests/gateway/test_mqtt_commands.py).

Commands are strict: a JSON object of exactly the documented keys and JSON types. No string is
read as a number (``"200"``), no boolean as a number, no NaN or Infinity, no unknown key. A
command moves a machine; guessing what a malformed one meant is not the box's job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ValidationError
from pydantic_core import from_json

from gateway.core.commands import (
    AckAlarm,
    CalibrateSpeed,
    Command,
    CriticalTilt,
    SelectSeedLot,
    SetChannelRate,
    SetRate,
    Start,
    Stop,
    ZeroTilt,
)
from gateway.core.errors import CommandError
from gateway.link.payloads import (
    REQUEST_ID_MAX_CHARS,
    AckAlarmCommand,
    ChannelRateCommand,
    EmptyCommand,
    RateCommand,
    SeedLotCommand,
    SpeedCalCommand,
)

KNOWN_COMMANDS: dict[str, type[BaseModel]] = {
    "rate": RateCommand,
    "channel_rate": ChannelRateCommand,
    "start": EmptyCommand,
    "stop": EmptyCommand,
    "zero_tilt": EmptyCommand,
    "tilt_critical": EmptyCommand,
    "speed_cal": SpeedCalCommand,
    "ack_alarm": AckAlarmCommand,
    "seed_lot": SeedLotCommand,
}
# A command is one flat JSON object; this leaves room for any future small structure and
# refuses, before any parser recurses into it, a payload like ``[`` x 2000.
MAX_NESTING = 8
# How much of a bad value or a key an error message quotes: enough to recognise it, and a
# 64 KB string cannot make a 64 KB ack.
QUOTE_MAX_CHARS = 40
ERRORS_LISTED_MAX = 5  # problems of one kind listed; then "and N more"


class CommandPayloadError(CommandError):
    """The payload is not a valid command; ``str()`` says why, naming the field.

    ``request_id`` is the payload's own, when it had a usable one, so the refusal can still be
    matched to its request by the sender.
    """

    def __init__(self, message: str, request_id: str | None = None) -> None:
        super().__init__(message)
        self.request_id = request_id


@dataclass(frozen=True)
class ParsedCommand:
    command: Command
    request_id: str | None = None


def parse_command(name: str, payload: bytes, *, max_payload_bytes: int) -> ParsedCommand:
    """``payload`` published on ``cmd/<name>`` as a command, or ``CommandPayloadError``.

    Raises nothing else, whatever the bytes (the fuzz tests hold it to that).
    """
    model = KNOWN_COMMANDS.get(name)
    if model is None:
        raise CommandPayloadError(
            f"unknown command {_quote(name)} (known: {', '.join(KNOWN_COMMANDS)})"
        )
    if len(payload) > max_payload_bytes:
        raise CommandPayloadError(
            f"payload too large: {len(payload)} bytes (max {max_payload_bytes})"
        )
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CommandPayloadError(
            f"payload is not UTF-8 text (invalid byte at offset {exc.start})"
        ) from None
    data = _json_object(text, model)
    rid = data.get("request_id")
    request_id = rid if isinstance(rid, str) and len(rid) <= REQUEST_ID_MAX_CHARS else None
    try:
        parsed = model.model_validate(data)
    except ValidationError as exc:
        raise CommandPayloadError(_describe_validation(exc, model), request_id) from None
    return ParsedCommand(_to_command(name, parsed), request_id)


def _json_object(text: str, model: type[BaseModel]) -> dict[str, Any]:
    if text.strip() == "":
        if model is EmptyCommand:
            return {}  # start/stop/... may be sent as an empty message
        raise CommandPayloadError("payload is empty; this command needs a JSON object")
    if _nesting_exceeds(text, MAX_NESTING):
        raise CommandPayloadError(
            f"payload is nested more than {MAX_NESTING} levels deep; a command is one flat "
            "JSON object"
        )
    try:
        # pydantic's parser, not json.loads: it has its own depth limit, reads NaN/Infinity
        # (so the field refuses them by name) and reports a 5000-digit number as invalid
        # JSON where json.loads raises a bare ValueError (Python's int digit limit)
        data = from_json(text)
    except ValueError as exc:
        raise CommandPayloadError(f"payload is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise CommandPayloadError(f"payload must be a JSON object, got {_json_type(data)}")
    return data


def _nesting_exceeds(text: str, limit: int) -> bool:
    """Whether ``[``/``{`` nest deeper than ``limit`` outside strings (JSON or not)."""
    if text.count("[") + text.count("{") <= limit:
        return False  # the usual case: too few brackets to nest that deep
    depth = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > limit:
                return True
        elif ch in "]}":
            depth -= 1
    return False


def _to_command(name: str, payload: BaseModel) -> Command:
    if isinstance(payload, RateCommand):
        return SetRate(crop=payload.crop, rate_kg_ha=payload.rate_kg_ha)
    if isinstance(payload, ChannelRateCommand):
        return SetChannelRate(channel=payload.channel, rate_kg_ha=payload.rate_kg_ha)
    if isinstance(payload, AckAlarmCommand):
        return AckAlarm(code=payload.code)
    if isinstance(payload, SpeedCalCommand):
        return CalibrateSpeed(action=payload.action, distance_m=payload.distance_m)
    if isinstance(payload, SeedLotCommand):
        return SelectSeedLot(crop=payload.crop, lot=payload.lot)
    simple: dict[str, Command] = {
        "start": Start(),
        "stop": Stop(),
        "zero_tilt": ZeroTilt(),
        "tilt_critical": CriticalTilt(),
    }
    return simple[name]


# pydantic's wording for the errors a strict command can give, in the ack's words
_TYPE_WORDS = {
    "float_type": "must be a number",
    "int_type": "must be an integer",
    "string_type": "must be a string",
    "bool_type": "must be true or false",
    "finite_number": "must be a finite number",
    "string_pattern_mismatch": "must be letters, digits, '.', '_' or '-' only",
}


def _describe_validation(exc: ValidationError, model: type[BaseModel]) -> str:
    """``field: what is allowed (got what)`` per problem; unknown keys named in one part.

    At most ``ERRORS_LISTED_MAX`` of each are listed, so a payload of 3000 unknown keys still
    gets a short answer.
    """
    parts = []
    unknown = []
    errors = exc.errors(include_url=False)
    for err in errors:
        loc = ".".join(_field_name(p) for p in err["loc"]) or "payload"
        kind = err["type"]
        if kind == "extra_forbidden":
            unknown.append(loc)
        elif kind == "missing":
            parts.append(f"{loc}: required field is missing")
        else:
            words = _TYPE_WORDS.get(kind) or (
                err["msg"]
                .removeprefix("Value error, ")
                .replace("Input should be ", "must be ")
                .replace("String should have ", "must have ")
            )
            parts.append(f"{loc}: {words} (got {_describe_value(err.get('input'))})")
    if len(parts) > ERRORS_LISTED_MAX:
        parts[ERRORS_LISTED_MAX:] = [f"and {len(parts) - ERRORS_LISTED_MAX} more problems"]
    allowed = ", ".join(model.model_fields)
    if len(unknown) == 1:
        parts.append(f"{unknown[0]}: unknown field (allowed: {allowed})")
    elif unknown:
        names = ", ".join(unknown[:ERRORS_LISTED_MAX])
        more = len(unknown) - ERRORS_LISTED_MAX
        parts.append(
            f"unknown fields {names}{f' and {more} more' if more > 0 else ''} "
            f"(allowed: {allowed})"
        )
    return "; ".join(parts)


def _describe_value(value: object) -> str:
    """A JSON value as the sender wrote it, short: ``string '200'``, ``true``, ``array``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        if value.bit_length() > 64:  # repr() of a 5000-digit int raises ValueError
            return "an integer too large for any field"
        return f"number {value}"
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return f"number {value!r}"
    if isinstance(value, str):
        return f"string {_quote(value)}"
    return _json_type(value)


def _json_type(value: object) -> str:
    names = {dict: "object", list: "array", str: "string", bool: "boolean", type(None): "null"}
    return names.get(type(value), "number")


def _field_name(key: str | int) -> str:
    """A key as the message names it: bare when it looks like a field, else quoted."""
    text = str(key)
    return text if text.isidentifier() and len(text) <= QUOTE_MAX_CHARS else _quote(text)


def _quote(text: str) -> str:
    return repr(_clip(text))


def _clip(text: str) -> str:
    return text if len(text) <= QUOTE_MAX_CHARS else text[:QUOTE_MAX_CHARS] + "…"
