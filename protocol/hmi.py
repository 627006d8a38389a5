"""The TJC touchscreen's serial protocol, both directions, without I/O.

In (screen → controller): 8-byte frames ``55 55 F C R1 R2 0D 0A`` that the screen's buttons emit
with ``printh``. The same wire also carries the screen's own Nextion return data (``1A FF FF FF``
when we wrote to an object the current page does not have), so the decoder recognises those too
instead of calling them garbage -- otherwise every "invalid variable" reply would be shown on the
screen as a rejected frame, which would itself produce another reply.

Out (controller → screen): Nextion/TJC instructions such as ``t_speed.txt="4.8 km/h"`` terminated
by ``FF FF FF``.

Decoding is deterministic in the byte content alone: the same bytes produce the same events
however they are split across reads, which is what lets the fuzz tests compare a whole feed with
a byte-by-byte one. Agronomic checks (is 300 kg/ha sensible for wheat?) are the gateway's job:
the crop table lives in config, so the decoder only checks the frame shape.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from protocol.errors import FieldError

HEADER = b"\x55\x55"
TRAILER = b"\x0d\x0a"
FRAME_LEN = 8
INSTRUCTION_END = b"\xff\xff\xff"

# Most bytes of one garbage run held before it is reported; endless noise on the line (a wrong
# baud rate, a floating RX pin) therefore costs bounded memory and yields a Rejected every
# MAX_BUFFER bytes rather than never.
MAX_BUFFER = 256
# Longest encoded text we put in one instruction. TJC screens have a 1 KiB serial buffer and
# text objects rarely allow more than a few dozen characters; anything longer is a bug upstream.
MAX_TEXT_BYTES = 255
# Longest Nextion return record (``0x70`` string replies aside, which we never request).
MAX_REPLY_LEN = 16

F_START = 0x01
F_STOP = 0x02
F_SELECT_CROP = 0x03
F_EMPTY = 0x04
F_SEED_LEVEL = 0x05
F_ZERO_TILT = 0x06
F_ACK_ALARM = 0x07  # sowgate's addition to paper A's set: the alarm line's "ACK" button
F_SEED_LOT = 0x08
F_ROTATION_TEST = 0x09
# F=09's C byte: what the operator does in the rotation test; R1R2 carry its value in 0.1 units
ROTATION_ACTIONS = {0: "cancel", 1: "run", 2: "rpm", 3: "mass", 4: "save", 5: "save_confirmed"}
ROTATION_SCALE = 10  # R1 R2: duty in 0.1 %, shaft speed in 0.1 r/min, mass in 0.1 g

RATE_SCALE = 10  # R1 R2 carry the rate in 0.1 kg/ha
RATE_RAW_MAX = 0xFFFF


# -- events -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class StartWork:
    """F=0x01: the operator pressed "work"."""


@dataclass(frozen=True, slots=True)
class StopWork:
    """F=0x02: stop; motor and fan off."""


@dataclass(frozen=True, slots=True)
class SelectCrop:
    """F=0x03: crop code (C) and target rate; the gateway maps the code to a crop and checks
    the rate against that crop's range."""

    crop_code: int
    rate_kg_ha: float


@dataclass(frozen=True, slots=True)
class EmptySeed:
    """F=0x04: empty the residual seed from the hopper."""


@dataclass(frozen=True, slots=True)
class SeedLevelMonitoring:
    """F=0x05: seed-level monitoring on (C=1) or off (C=0)."""

    enabled: bool


@dataclass(frozen=True, slots=True)
class ZeroTilt:
    """F=0x06: take the current inclinometer angle as level."""


@dataclass(frozen=True, slots=True)
class AckAlarm:
    """F=0x07: the operator acknowledges the critical alarms waiting (the alarm line's button).
    Not in paper A's frame set: a screen without the button never sends it."""


@dataclass(frozen=True, slots=True)
class SelectSeedLot:
    """F=0x08: make seed lot number R1R2 (big-endian) the active lot of crop code C. Lot 0
    is ``default``; which name a number stands for is the gateway's (it shows the list)."""

    crop_code: int
    lot_number: int


@dataclass(frozen=True, slots=True)
class RotationTest:
    """F=0x09: a step of the rotation test run from the screen. C is the action
    (``ROTATION_ACTIONS``: 00 cancel, 01 run at duty R1R2, 02 the run's shaft r/min, 03 its
    weighed mass in g, 04 fit and save, 05 save a large change the operator confirmed); R1R2
    (big-endian) its value in 0.1 units, 0 where the action has none."""

    action: str
    value: float = 0.0


# Kinds of rejected input: stable keys for the per-reason counters (the ``reason`` text varies).
KIND_GARBAGE = "garbage"  # bytes that are not a 55 55 frame (noise, wrong baud rate)
KIND_BAD_TRAILER = "bad_trailer"  # a 55 55 header without 0D 0A six bytes later
KIND_INCOMPLETE = "incomplete_frame"  # a frame cut short by the line going quiet
KIND_UNKNOWN_FUNCTION = "unknown_function"  # a well-formed frame with a function we lack
KIND_BAD_FIELD = "bad_field"  # a known function with an impossible value in it


@dataclass(frozen=True, slots=True)
class Rejected:
    """Bytes that are not a valid command; ``reason`` is short enough to show on the screen,
    ``kind`` is its stable counter key (``KIND_*``)."""

    reason: str
    raw: bytes
    kind: str = field(default=KIND_GARBAGE, compare=False)


@dataclass(frozen=True, slots=True)
class ScreenError:
    """The screen reported that one of our instructions failed (Nextion return code)."""

    code: int

    @property
    def meaning(self) -> str:
        return NEXTION_ERRORS.get(self.code, f"error 0x{self.code:02X}")


@dataclass(frozen=True, slots=True)
class ScreenReply:
    """Any other well-formed Nextion return record (success, ready, touch event...)."""

    code: int
    data: bytes


HmiCommand = (
    StartWork | StopWork | SelectCrop | EmptySeed | SeedLevelMonitoring | ZeroTilt | AckAlarm
    | SelectSeedLot | RotationTest
)
HmiEvent = HmiCommand | Rejected | ScreenError | ScreenReply

# Nextion instruction-set return codes that mean "your instruction failed".
NEXTION_ERRORS: dict[int, str] = {
    0x00: "invalid instruction",
    0x02: "invalid component id",
    0x03: "invalid page id",
    0x04: "invalid picture id",
    0x05: "invalid font id",
    0x06: "invalid file operation",
    0x09: "invalid CRC",
    0x11: "invalid baud rate",
    0x12: "invalid waveform id or channel",
    0x1A: "invalid variable name or attribute",
    0x1B: "invalid variable operation",
    0x1C: "failed to assign",
    0x1D: "EEPROM operation failed",
    0x1E: "invalid quantity of parameters",
    0x1F: "IO operation failed",
    0x20: "escape character invalid",
    0x23: "variable name too long",
    0x24: "serial buffer overflow",
}


# -- decoding ---------------------------------------------------------------------------------


def _decode_framed(frame: bytes) -> HmiEvent:
    """A frame with correct header and trailer: decode its function, or say why not."""
    function, c, r1, r2 = frame[2], frame[3], frame[4], frame[5]
    if function == F_START:
        return StartWork()
    if function == F_STOP:
        return StopWork()
    if function == F_SELECT_CROP:
        return SelectCrop(crop_code=c, rate_kg_ha=((r1 << 8) | r2) / RATE_SCALE)
    if function == F_EMPTY:
        return EmptySeed()
    if function == F_SEED_LEVEL:
        if c not in (0, 1):
            return Rejected(
                f"seed-level flag must be 0 or 1, got 0x{c:02X}", frame, KIND_BAD_FIELD
            )
        return SeedLevelMonitoring(enabled=c == 1)
    if function == F_ZERO_TILT:
        return ZeroTilt()
    if function == F_ACK_ALARM:
        return AckAlarm()
    if function == F_SEED_LOT:
        return SelectSeedLot(crop_code=c, lot_number=(r1 << 8) | r2)
    if function == F_ROTATION_TEST:
        action = ROTATION_ACTIONS.get(c)
        if action is None:
            return Rejected(
                f"rotation test action must be 00..05, got 0x{c:02X}", frame, KIND_BAD_FIELD
            )
        return RotationTest(action, ((r1 << 8) | r2) / ROTATION_SCALE)
    return Rejected(f"unknown function code 0x{function:02X}", frame, KIND_UNKNOWN_FUNCTION)


def parse_screen_replies(data: bytes) -> list[ScreenError | ScreenReply] | None:
    """Split ``data`` into Nextion return records, or None if it is not made only of them."""
    if not data.endswith(INSTRUCTION_END):
        return None
    out: list[ScreenError | ScreenReply] = []
    for record in data[: -len(INSTRUCTION_END)].split(INSTRUCTION_END):
        if not record or len(record) > MAX_REPLY_LEN:
            return None
        if len(record) == 1 and record[0] in NEXTION_ERRORS:
            out.append(ScreenError(record[0]))
        else:
            out.append(ScreenReply(record[0], bytes(record[1:])))
    return out


_GENERIC = "garbage"


class HmiDecoder:
    """Incremental decoder for the screen → controller byte stream.

    Feed it whatever each read returned. Bytes that cannot belong to a frame are gathered into a
    *garbage run* and reported as one ``Rejected`` when the run ends: at the next good frame, at
    ``flush()`` (the link calls it when the line goes idle), or every ``MAX_BUFFER`` bytes.
    After a bad frame the decoder resynchronises on the next ``55 55``.
    """

    def __init__(self) -> None:
        self._buf = bytearray()  # unexamined bytes: at most a partial frame between feeds
        self._garbage = bytearray()  # the current garbage run, < MAX_BUFFER
        self._reason: str | None = None
        self._kind = KIND_GARBAGE

    @property
    def pending(self) -> bool:
        """True while bytes are held that a later ``feed`` or ``flush`` will report."""
        return bool(self._buf or self._garbage)

    @property
    def partial_frame_bytes(self) -> int:
        """Bytes held for a frame not complete yet (fewer than a frame's length)."""
        return len(self._buf)

    @property
    def garbage_run_bytes(self) -> int:
        """Bytes of the current garbage run not reported yet (fewer than ``MAX_BUFFER``)."""
        return len(self._garbage)

    def feed(self, data: bytes | bytearray | memoryview) -> list[HmiEvent]:
        out: list[HmiEvent] = []
        buf = self._buf
        buf += data
        n = len(buf)
        i = 0
        while i < n:
            if buf[i] != 0x55:
                j = buf.find(0x55, i)
                j = n if j < 0 else j
                self._add_garbage(buf[i:j], _GENERIC, out)
                i = j
                continue
            if i + 1 == n:
                break  # a lone 0x55 at the end may start a frame
            if buf[i + 1] != 0x55:
                self._add_garbage(buf[i : i + 1], _GENERIC, out)
                i += 1
                continue
            if n - i < FRAME_LEN:
                break  # a partial frame: wait for the rest
            frame = bytes(buf[i : i + FRAME_LEN])
            if frame[6:8] != TRAILER:
                # Not a frame after all; drop one byte so a `55 55` inside it can still be found.
                reason = f"bad trailer {frame[6]:02X} {frame[7]:02X}, expected 0D 0A"
                self._add_garbage(frame[:1], reason, out, KIND_BAD_TRAILER)
                i += 1
                continue
            self._end_run(out)
            out.append(_decode_framed(frame))
            i += FRAME_LEN
        del buf[:i]
        return out

    def flush(self) -> list[HmiEvent]:
        """The line went quiet: whatever is held (garbage, a truncated frame) is reported now."""
        out: list[HmiEvent] = []
        if self._buf:
            if self._buf.startswith(HEADER):
                self._add_garbage(self._buf, "incomplete frame", out, KIND_INCOMPLETE)
            else:
                self._add_garbage(self._buf, _GENERIC, out)
            self._buf.clear()
        self._end_run(out)
        return out

    def _add_garbage(
        self,
        chunk: bytes | bytearray,
        reason: str,
        out: list[HmiEvent],
        kind: str = KIND_GARBAGE,
    ) -> None:
        if self._reason is None or (self._reason == _GENERIC and reason != _GENERIC):
            self._reason, self._kind = reason, kind
        view = memoryview(chunk)
        while view:
            room = MAX_BUFFER - len(self._garbage)
            self._garbage += view[:room]
            view = view[room:]
            if len(self._garbage) >= MAX_BUFFER:
                self._end_run(out)
        view.release()

    def _end_run(self, out: list[HmiEvent]) -> None:
        if not self._garbage:
            self._reason = None
            self._kind = KIND_GARBAGE
            return
        raw = bytes(self._garbage)
        replies = parse_screen_replies(raw)
        if replies is not None:
            out.extend(replies)
        else:
            reason = self._reason or _GENERIC
            if reason == _GENERIC:
                reason = f"{len(raw)} byte(s) of garbage, not a 55 55 frame"
            out.append(Rejected(reason, raw, self._kind))
        self._garbage.clear()
        self._reason = None
        self._kind = KIND_GARBAGE


class NextionReplyDecoder:
    """Decoder for a stream carrying only Nextion return records (``code … FF FF FF``).

    ``HmiDecoder`` already separates these from HMI frames on the shared wire; this class is for
    tools that talk to a stock screen directly (e.g. checking which objects a page has).
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes | bytearray | memoryview) -> list[ScreenError | ScreenReply]:
        self._buf += data
        out: list[ScreenError | ScreenReply] = []
        while (end := self._buf.find(INSTRUCTION_END)) >= 0:
            record = bytes(self._buf[: end + len(INSTRUCTION_END)])
            del self._buf[: end + len(INSTRUCTION_END)]
            out.extend(parse_screen_replies(record) or [])
        if len(self._buf) > MAX_REPLY_LEN:
            # No terminator in sight: this is not reply traffic; keep only a possible tail.
            del self._buf[: -len(INSTRUCTION_END)]
        return out


# -- encoding ---------------------------------------------------------------------------------


def encode_frame(command: HmiCommand) -> bytes:
    """The 8 bytes the screen sends for ``command`` (what the simulator's buttons emit)."""
    c, rate_raw = 0, 0
    match command:
        case StartWork():
            function = F_START
        case StopWork():
            function = F_STOP
        case SelectCrop(crop_code=code, rate_kg_ha=rate):
            function = F_SELECT_CROP
            if not 0 <= code <= 0xFF:
                raise FieldError(f"crop code must fit one byte (0..255), got {code}")
            rate_raw = round(rate * RATE_SCALE)
            if not 0 <= rate_raw <= RATE_RAW_MAX:
                raise FieldError(f"rate must be 0..6553.5 kg/ha, got {rate}")
            c = code
        case EmptySeed():
            function = F_EMPTY
        case SeedLevelMonitoring(enabled=enabled):
            function = F_SEED_LEVEL
            c = 1 if enabled else 0
        case ZeroTilt():
            function = F_ZERO_TILT
        case AckAlarm():
            function = F_ACK_ALARM
        case SelectSeedLot(crop_code=code, lot_number=number):
            function = F_SEED_LOT
            if not 0 <= code <= 0xFF:
                raise FieldError(f"crop code must fit one byte (0..255), got {code}")
            if not 0 <= number <= RATE_RAW_MAX:
                raise FieldError(f"seed lot number must be 0..65535, got {number}")
            c, rate_raw = code, number
        case RotationTest(action=action, value=value):
            function = F_ROTATION_TEST
            codes = {name: code for code, name in ROTATION_ACTIONS.items()}
            if action not in codes:
                raise FieldError(f"unknown rotation test action {action!r}")
            rate_raw = round(value * ROTATION_SCALE)
            if not 0 <= rate_raw <= RATE_RAW_MAX:
                raise FieldError(f"rotation test value must be 0..6553.5, got {value}")
            c = codes[action]
        case _:
            raise TypeError(f"not an HMI command: {command!r}")
    return HEADER + bytes((function, c, rate_raw >> 8, rate_raw & 0xFF)) + TRAILER


_OBJECT_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)?$")
_NEWLINE = re.compile(r"\r\n|\r|\n")


def check_object_name(obj: str) -> str:
    """Object names go into the instruction unquoted, so only plain identifiers are allowed
    (optionally ``page.object``)."""
    if not _OBJECT_NAME.fullmatch(obj):
        raise FieldError(f"invalid screen object name {obj!r}")
    return obj


def _encode_char(ch: str, encoding: str) -> bytes:
    """One character in the screen's encoding; anything the font cannot show becomes ``?``.

    0xFF is refused even if the encoding produces it (latin-1 ``ÿ``): it would end the
    instruction early and the rest of the text would be executed as a command.
    """
    if ch in '"\\':
        return b"\\" + ch.encode("ascii")
    if ch < " " or ch == "\x7f":
        return b"?"
    try:
        data = ch.encode(encoding)
    except UnicodeEncodeError:
        return b"?"
    return b"?" if 0xFF in data else data


def encode_text(text: str, encoding: str) -> bytes:
    """The quoted payload of a ``.txt=`` assignment, escaped, encoded and capped."""
    out = bytearray()
    for part_no, part in enumerate(_NEWLINE.split(text)):
        pieces = [b"\\r"] if part_no else []  # Nextion's in-string newline escape
        pieces += [_encode_char(ch, encoding) for ch in part]
        for piece in pieces:
            if len(out) + len(piece) > MAX_TEXT_BYTES:
                return bytes(out)
            out += piece
    return bytes(out)


def set_text(obj: str, text: str, encoding: str = "ascii") -> bytes:
    """``obj.txt="text"`` + FF FF FF. Never fails on the text: unencodable characters become
    ``?`` and over-long text is cut at ``MAX_TEXT_BYTES``; a bad object name is a FieldError."""
    check_object_name(obj)
    return obj.encode("ascii") + b'.txt="' + encode_text(text, encoding) + b'"' + INSTRUCTION_END


def set_value(obj: str, value: int) -> bytes:
    """``obj.val=N`` + FF FF FF; Nextion numbers are signed 32-bit."""
    check_object_name(obj)
    if isinstance(value, bool) or not isinstance(value, int):
        raise FieldError(f"value for {obj} must be an int, got {value!r}")
    if not -(2**31) <= value < 2**31:
        raise FieldError(f"value for {obj} must fit a signed 32-bit number, got {value}")
    return f"{obj}.val={value}".encode("ascii") + INSTRUCTION_END


_TXT_INSTRUCTION = re.compile(rb'^([A-Za-z_][A-Za-z0-9_.]*)\.txt="(.*)"$', re.DOTALL)
_VAL_INSTRUCTION = re.compile(rb"^([A-Za-z_][A-Za-z0-9_.]*)\.val=(-?[0-9]+)$")
_UNESCAPE = re.compile(rb"\\(.)", re.DOTALL)


def parse_instruction(instruction: bytes, encoding: str = "ascii") -> tuple[str, str | int] | None:
    """Inverse of ``set_text``/``set_value`` for one instruction (without FF FF FF): the
    object name and its text or number, or None for any other instruction."""
    if m := _TXT_INSTRUCTION.match(instruction):
        raw = _UNESCAPE.sub(lambda e: b"\n" if e.group(1) == b"r" else e.group(1), m.group(2))
        return m.group(1).decode("ascii"), raw.decode(encoding, errors="replace")
    if m := _VAL_INSTRUCTION.match(instruction):
        return m.group(1).decode("ascii"), int(m.group(2))
    return None
