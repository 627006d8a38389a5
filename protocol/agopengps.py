"""AgOpenGPS's UDP frames (the "PGN" protocol AgIO relays), both directions, without I/O.

Frame: ``0x80 0x81 src pgn len data[len] crc``; ``crc`` is the low byte of the sum of the bytes
from ``src`` to the last data byte; multi-byte values are little-endian. AgIO sends with
``src = 0x7F``. What sowgate reads (byte offsets from the frame start, as AgOpenGPS's own
``CPGN_*`` classes number them; checked in AgOpenGPS ``SourceCode/GPS/Classes/CPGN.cs`` /
``Forms/Sections.Designer.cs`` and ``docs/pgn-protocol.md``):

* 254 (0xFE) steer data: 5-6 speed km/h x 10 (u16, no sign), 11 sections 1-8, 12 sections 9-16;
* 239 (0xEF) machine data: 5 u-turn, 6 speed km/h x 10 in ONE byte (AgOpenGPS writes
  ``(byte)(avgSpeed * 10)``, so it wraps above 25.5 km/h: never used as a speed here), 7
  hydraulic lift (0 none, 1 lower, 2 raise), 8 tram, 9 geo-stop, 11-12 sections 1-16;
* 229 (0xE5) 64 sections: 5-12 sections 1-64, 13 / 14 far-left / far-right tool speed m/s x 10
  (one byte each, AgOpenGPS clamps them to >= 0.1 m/s);
* 200 (0xC8) hello from AgIO, answered by 123 (0x7B) so AgIO lists the machine module.

Out: 123 (hello reply: relay bytes = sections 1-8 / 9-16) and 221 (0xDD: a text AgOpenGPS shows
for ``seconds``; byte 5 seconds, 6 colour, 7.. UTF-8 text).

Two places where the sources disagree, and what this codec does:

* PGN 229's length: AgOpenGPS builds it with ``len = 10`` (16 bytes in all) while some tables
  list 8 section bytes only. The decoder takes the frame's own ``len`` byte as the truth for
  framing and needs at least the bytes it reads (a 229 shorter than 10 data bytes has no tool
  speeds: they are None); longer frames of every PGN are accepted, the extra bytes ignored, so a
  later AgOpenGPS that appends fields still works.
* AgIO's hello is the fixed array ``80 81 7F C8 03 38 00 00 47``: its last byte 0x47 is not the
  sum rule's 0x82. A hello is accepted with either checksum (answering it moves nothing);
  every other PGN must have the right sum.
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol.errors import ChecksumError, FieldError, FrameError

HEADER = b"\x80\x81"
AGIO_SOURCE = 0x7F
PGN_STEER_DATA = 254
PGN_MACHINE_DATA = 239
PGN_SECTIONS_64 = 229
PGN_HELLO = 200
PGN_HELLO_REPLY_MACHINE = 123
PGN_DISPLAY_TEXT = 221
HELLO_FIXED_CRC = 0x47  # AgIO's hello carries this constant, not the sum (see module doc)
MIN_FRAME = 6  # header 2 + src + pgn + len + crc
# data bytes a frame must carry for the fields read (offset of the last one - 4)
MIN_DATA = {PGN_STEER_DATA: 8, PGN_MACHINE_DATA: 8, PGN_SECTIONS_64: 8, PGN_HELLO: 0}
SECTIONS_64_SPEED_DATA = 10
MAX_TEXT_BYTES = 240  # 221's text, well inside a frame's 255-byte payload

# AgOpenGPS's speed in PGN 254 is km/h x 10 in a u16: up to 6553.5 km/h on the wire. The codec
# refuses what no tractor does, so a corrupted frame that still sums right cannot meter seed
# at a phantom speed; the gateway's own speed.max_plausible_kmh (lower) applies after this.
MAX_WIRE_SPEED_KMH = 100.0
HYD_LIFT_NONE, HYD_LIFT_LOWER, HYD_LIFT_RAISE = 0, 1, 2


def checksum(body: bytes) -> int:
    """Low byte of the sum of ``body`` (the bytes from ``src`` to the last data byte)."""
    return sum(body) & 0xFF


def encode(src: int, pgn: int, data: bytes) -> bytes:
    """One frame with a correct checksum."""
    if not (0 <= src <= 0xFF and 0 <= pgn <= 0xFF):
        raise FieldError(f"src and pgn are one byte each (got {src}, {pgn})")
    if len(data) > 0xFF:
        raise FieldError(f"at most 255 data bytes (got {len(data)})")
    body = bytes((src, pgn, len(data))) + data
    return HEADER + body + bytes((checksum(body),))


@dataclass(frozen=True, slots=True)
class Frame:
    """A frame whose header, length and checksum are right (``decode_frame``)."""

    src: int
    pgn: int
    data: bytes


@dataclass(frozen=True, slots=True)
class SteerData:
    """PGN 254: the speed AgOpenGPS navigates at and sections 1-16."""

    speed_kmh: float
    sections: tuple[bool, ...]  # 16, section 1 first


@dataclass(frozen=True, slots=True)
class MachineData:
    """PGN 239: lift, tram, geo-stop and sections 1-16 (its one-byte speed is not trusted)."""

    uturn: int
    speed_byte_kmh: float  # km/h modulo 25.6: shown for diagnostics only
    hyd_lift: int  # HYD_LIFT_NONE / _LOWER / _RAISE
    tram: int
    geo_stop: bool
    sections: tuple[bool, ...]  # 16


@dataclass(frozen=True, slots=True)
class Sections64:
    """PGN 229: 64 sections and the far-left / far-right tool speeds (None if not sent)."""

    sections: tuple[bool, ...]  # 64
    left_speed_mps: float | None
    right_speed_mps: float | None


@dataclass(frozen=True, slots=True)
class Hello:
    """PGN 200: AgIO asks every module to answer."""


@dataclass(frozen=True, slots=True)
class Unhandled:
    """A well-formed frame of a PGN sowgate does not use (AgIO relays every PGN to 8888)."""

    pgn: int


Message = SteerData | MachineData | Sections64 | Hello | Unhandled


def decode_frame(datagram: bytes) -> Frame:
    """Check header, length and checksum of one datagram (one frame per datagram)."""
    if len(datagram) < MIN_FRAME:
        raise FrameError(f"{len(datagram)} bytes is shorter than a frame ({MIN_FRAME})")
    if datagram[:2] != HEADER:
        raise FrameError(f"header {datagram[:2].hex(' ')} is not 80 81")
    src, pgn, n = datagram[2], datagram[3], datagram[4]
    if len(datagram) != n + MIN_FRAME:
        raise FrameError(
            f"PGN {pgn}: length byte says {n} data bytes, the datagram has {len(datagram) - 6}"
        )
    body = datagram[2:-1]
    crc = datagram[-1]
    expected = checksum(body)
    if crc != expected and not (pgn == PGN_HELLO and crc == HELLO_FIXED_CRC):
        raise ChecksumError(f"PGN {pgn}: checksum 0x{crc:02X}, the bytes sum to 0x{expected:02X}")
    return Frame(src, pgn, bytes(datagram[5:-1]))


def _bits(data: bytes) -> tuple[bool, ...]:
    return tuple(bool(b >> i & 1) for b in data for i in range(8))


def decode(datagram: bytes) -> Message:
    """One datagram as a message; ``ProtocolError`` (a subclass) saying why not."""
    frame = decode_frame(datagram)
    need = MIN_DATA.get(frame.pgn)
    if need is None:
        return Unhandled(frame.pgn)
    d = frame.data
    if len(d) < need:
        raise FrameError(f"PGN {frame.pgn} needs at least {need} data bytes, has {len(d)}")
    if frame.pgn == PGN_HELLO:
        return Hello()
    if frame.pgn == PGN_STEER_DATA:
        speed = int.from_bytes(d[0:2], "little") / 10.0
        if speed > MAX_WIRE_SPEED_KMH:
            raise FieldError(f"PGN 254 speed {speed:g} km/h is above {MAX_WIRE_SPEED_KMH:g}")
        return SteerData(speed, _bits(d[6:8]))
    if frame.pgn == PGN_MACHINE_DATA:
        if d[2] > HYD_LIFT_RAISE:
            raise FieldError(f"PGN 239 hydraulic lift {d[2]} is not 0, 1 or 2")
        return MachineData(d[0], d[1] / 10.0, d[2], d[3], d[4] != 0, _bits(d[6:8]))
    left = right = None
    if len(d) >= SECTIONS_64_SPEED_DATA:
        left, right = d[8] / 10.0, d[9] / 10.0
    return Sections64(_bits(d[0:8]), left, right)


def _section_bytes(sections: tuple[bool, ...] | list[bool], n_bytes: int) -> bytes:
    out = bytearray(n_bytes)
    for i, on in enumerate(sections[: n_bytes * 8]):
        if on:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def encode_steer_data(speed_kmh: float, sections: tuple[bool, ...] | list[bool]) -> bytes:
    """PGN 254 as AgOpenGPS sends it (steer angle, xte and status zero)."""
    speed = round(abs(speed_kmh) * 10)
    if speed > 0xFFFF:
        raise FieldError(f"speed {speed_kmh} km/h does not fit PGN 254")
    data = speed.to_bytes(2, "little") + bytes(4) + _section_bytes(sections, 2)
    return encode(AGIO_SOURCE, PGN_STEER_DATA, data)


def encode_machine_data(
    speed_kmh: float,
    sections: tuple[bool, ...] | list[bool],
    *,
    hyd_lift: int = HYD_LIFT_NONE,
    tram: int = 0,
    geo_stop: bool = False,
    uturn: int = 0,
) -> bytes:
    """PGN 239 as AgOpenGPS sends it, its speed byte wrapping as AgOpenGPS's does."""
    speed_byte = int(speed_kmh * 10) & 0xFF
    data = bytes((uturn, speed_byte, hyd_lift, tram, int(geo_stop), 0))
    return encode(AGIO_SOURCE, PGN_MACHINE_DATA, data + _section_bytes(sections, 2))


def encode_sections_64(
    sections: tuple[bool, ...] | list[bool], left_mps: float, right_mps: float
) -> bytes:
    """PGN 229 as AgOpenGPS sends it (len 10)."""
    speeds = bytes((int(left_mps * 10) & 0xFF, int(right_mps * 10) & 0xFF))
    return encode(AGIO_SOURCE, PGN_SECTIONS_64, _section_bytes(sections, 8) + speeds)


def hello_from_agio() -> bytes:
    """AgIO's hello, byte for byte (``UDP.designer.cs`` ``helloFromAgIO``, fixed crc 0x47)."""
    return bytes((0x80, 0x81, AGIO_SOURCE, PGN_HELLO, 3, 56, 0, 0, HELLO_FIXED_CRC))


def hello_reply(sections: tuple[bool, ...] | list[bool] = ()) -> bytes:
    """PGN 123: the machine module's answer (11 bytes: AgIO checks ``pgn == 123`` and the
    length); data = sections 1-8, 9-16 (AgIO shows them as the relay bits), 3 spare."""
    return encode(
        PGN_HELLO_REPLY_MACHINE, PGN_HELLO_REPLY_MACHINE, _section_bytes(sections, 2) + bytes(3)
    )


def display_text(text: str, seconds: int = 5, colour: int = 0) -> bytes:
    """PGN 221: ``text`` on the AgOpenGPS screen for ``seconds`` (AgOpenGPS shows it only with
    "hardware messages" enabled). Too long a text is cut at a character boundary."""
    if not (0 <= seconds <= 0xFF and 0 <= colour <= 0xFF):
        raise FieldError(f"seconds and colour are one byte each (got {seconds}, {colour})")
    raw = text.encode("utf-8")
    if len(raw) > MAX_TEXT_BYTES:
        raw = raw[:MAX_TEXT_BYTES].decode("utf-8", "ignore").encode("utf-8")
    return encode(PGN_HELLO_REPLY_MACHINE, PGN_DISPLAY_TEXT, bytes((seconds, colour)) + raw)
