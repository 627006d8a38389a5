"""NMEA 0183 sentences a GNSS receiver sends us, as typed values.

pynmeagps does the checksum and the field split; this module adds what it does not: a precise
reason for every rejection (a field engineer must be able to tell a bad checksum from a cut
line from a receiver that simply has no fix yet), and a small typed result the rest of sowgate
can rely on (units in the name, ``None`` where the receiver legitimately leaves a field empty).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import date, time
from typing import Any, ClassVar, Final

from pynmeagps import NMEAReader
from pynmeagps.exceptions import NMEAMessageError, NMEAParseError, NMEATypeError
from pynmeagps.nmeahelpers import calc_checksum

from protocol.errors import ChecksumError, FieldError, FrameError

KMH_PER_KNOT: Final = 1.852
MAX_NMEA_LINE_CHARS: Final = 200  # spec says 82; high-precision receivers exceed it, not by 2x
# Courses and headings; 360.0 itself is accepted (a receiver rounding 359.96) and wraps to 0.
DEGREES: Final = (0.0, 360.0)

SUPPORTED_SENTENCES: Final = frozenset({"RMC", "GGA", "VTG", "HDT", "THS"})

# hhmm60(.ss): second 60, a leap second; UTC inserts one only as 23:59:60
_LEAP_SECOND = re.compile(r"^(?P<hhmm>\d{4})60(?P<frac>\.\d{1,6})?$")
MS_PER_DAY: Final = 86_400_000
_ADDRESS = re.compile(r"^(?P<talker>[A-Z]{2})(?P<msg>[A-Z][A-Z0-9]{2,})$")
_TRAILER = re.compile(r"\*(?P<cs>[0-9A-Fa-f]{2})$")


class TruncatedError(FrameError):
    """The line ends before its checksum trailer: it was cut by a buffer, a reconnect or noise."""


class UnknownSentenceError(FrameError):
    """A well-framed sentence we do not decode (e.g. $GNGSV): skipped, not an error of the link."""

    def __init__(self, message: str, sentence: str) -> None:
        super().__init__(message)
        self.sentence = sentence


class MissingFieldError(FieldError):
    """A field the sentence needs to mean anything is empty or absent."""


@dataclass(frozen=True)
class Rmc:
    """Recommended minimum: position, speed and course over ground, and the date."""

    talker: str
    utc: time | None
    date: date | None
    valid: bool  # status A; V means the receiver itself says "do not use"
    lat: float | None
    lon: float | None
    speed_kmh: float | None
    course_deg: float | None
    mode: str | None  # NMEA 2.3: A autonomous, D differential, R RTK fixed, F RTK float, N none
    # ``235960.xx``: a UTC leap second, second 60 of 23:59, which ``datetime.time`` cannot
    # hold; ``utc`` then carries 23:59:59 with the fraction (see utc_ms_of_day)
    leap_second: bool = False

    kind: ClassVar[str] = "RMC"


@dataclass(frozen=True)
class Gga:
    """Fix data: position, fix quality, satellites and height."""

    talker: str
    utc: time | None
    lat: float | None
    lon: float | None
    quality: int  # 0 none, 1 single, 2 DGPS, 4 RTK fixed, 5 RTK float, 6 dead reckoning, ...
    num_sv: int | None
    hdop: float | None
    alt_m: float | None  # above mean sea level (geoid)
    geoid_sep_m: float | None
    diff_age_s: float | None
    leap_second: bool = False  # as Rmc.leap_second

    kind: ClassVar[str] = "GGA"


@dataclass(frozen=True)
class Vtg:
    """Course and speed over ground, without a time of its own."""

    talker: str
    course_deg: float | None
    course_mag_deg: float | None
    speed_knots: float | None
    speed_kmh: float | None
    mode: str | None

    kind: ClassVar[str] = "VTG"


@dataclass(frozen=True)
class Hdt:
    """True heading. No quality indicator: its presence is the receiver's claim of validity."""

    talker: str
    heading_deg: float | None

    kind: ClassVar[str] = "HDT"


@dataclass(frozen=True)
class Ths:
    """True heading with a mode: A autonomous, E estimated, M manual, S simulator, V invalid."""

    talker: str
    heading_deg: float | None
    mode: str

    @property
    def valid(self) -> bool:
        return self.mode == "A" and self.heading_deg is not None

    kind: ClassVar[str] = "THS"


NmeaSentence = Rmc | Gga | Vtg | Hdt | Ths


def nmea_checksum(content: str) -> str:
    """XOR checksum of the characters between ``$`` and ``*``, two upper-case hex digits."""
    return str(calc_checksum(content))


def encode_nmea(content: str) -> str:
    """``$<content>*hh`` without line terminator; used by the emulator and the tests."""
    return f"${content}*{nmea_checksum(content)}"


def split_nmea(line: str) -> tuple[str, str, list[str]]:
    """Check framing and checksum; return (talker, sentence id, raw fields).

    Done before pynmeagps sees the line so that each failure gets its own exception class
    and a message naming the expected and received values.
    """
    line = line.strip("\r\n ")
    if not line.startswith("$"):
        raise FrameError(f"not an NMEA sentence: does not start with '$' ({line[:16]!r})")
    if len(line) > MAX_NMEA_LINE_CHARS:
        # The limit guards the sentences we decode; a long one we do not use (a proprietary
        # $PQTM..., a $GNGSV from a busy sky) is simply not ours, like its shorter siblings.
        name = line[1:].split(",", 1)[0]
        match = _ADDRESS.match(name)
        ours = match is not None and match.group("msg") in SUPPORTED_SENTENCES
        if name.isalnum() and name.isascii() and not ours:
            raise UnknownSentenceError(f"unknown sentence {name} ({len(line)} characters)", name)
        raise FrameError(f"line too long: {len(line)} > {MAX_NMEA_LINE_CHARS} characters")
    trailer = _TRAILER.search(line)
    if trailer is None:
        raise TruncatedError("truncated: no '*hh' checksum at the end of the line")
    content = line[1 : trailer.start()]
    if "*" in content or "$" in content:
        raise FrameError("malformed: '$' or '*' inside the sentence body")
    got = trailer.group("cs").upper()
    expected = nmea_checksum(content)
    if got != expected:
        raise ChecksumError(f"checksum mismatch: expected {expected}, got {got}")
    fields = content.split(",")
    address = _ADDRESS.match(fields[0])
    if address is None:
        if fields[0].isalnum():  # proprietary ($KSXT, $PUBX...): framed fine, just not ours
            raise UnknownSentenceError(f"unknown sentence {fields[0]}", fields[0])
        raise FrameError(f"malformed address field {fields[0]!r}")
    return address.group("talker"), address.group("msg"), fields[1:]


def parse_nmea(line: str) -> NmeaSentence:
    """Decode one RMC/GGA/VTG/HDT/THS line (any talker); raise a ProtocolError subclass if not."""
    talker, msg_id, raw = split_nmea(line)
    if msg_id not in SUPPORTED_SENTENCES:
        raise UnknownSentenceError(f"unknown sentence {talker}{msg_id}", f"{talker}{msg_id}")
    try:
        msg = NMEAReader.parse(line.strip("\r\n ").encode("ascii"))
    except (NMEAParseError, NMEAMessageError, NMEATypeError, UnicodeEncodeError) as exc:
        raise FieldError(f"{talker}{msg_id}: {exc}") from exc
    if msg is None:  # pragma: no cover - pynmeagps returns None only for non-NMEA input
        raise FrameError(f"{talker}{msg_id}: not decodable")
    fields = _Fields(f"{talker}{msg_id}", msg, raw)
    if msg_id == "RMC":
        return _rmc(talker, fields)
    if msg_id == "GGA":
        return _gga(talker, fields)
    if msg_id == "VTG":
        return _vtg(talker, fields)
    if msg_id == "HDT":
        return Hdt(talker, fields.opt_float("headingT", 0, *DEGREES))
    return _ths(talker, fields)


class _Fields:
    """Reads pynmeagps attributes, telling an empty field from one pynmeagps could not parse.

    pynmeagps turns a malformed value into ``""`` just like an empty one; the raw field list
    lets us report "field lat: bad value '53x27'" instead of pretending there was no fix.
    """

    def __init__(self, name: str, msg: Any, raw: list[str]) -> None:
        self.name = name
        self.msg = msg
        self.raw = raw

    def _get(self, attr: str, index: int) -> Any:
        if index >= len(self.raw):
            raise MissingFieldError(
                f"{self.name}: missing field {attr} (sentence has {len(self.raw)} fields)"
            )
        value = getattr(self.msg, attr, "")
        if value == "" and self.raw[index] != "":
            raise FieldError(f"{self.name}: field {attr}: bad value {self.raw[index]!r}")
        return value

    def opt(self, attr: str, index: int) -> Any:
        value = self._get(attr, index)
        return None if value == "" else value

    def req(self, attr: str, index: int) -> Any:
        value = self._get(attr, index)
        if value == "":
            raise MissingFieldError(f"{self.name}: missing field {attr} (empty)")
        return value

    def opt_float(
        self, attr: str, index: int, lo: float | None = None, hi: float | None = None
    ) -> float | None:
        """An optional number; outside ``[lo, hi]`` is a bad field, not a value to use."""
        value = self.opt(attr, index)
        if value is None:
            return None
        number = float(value)
        if (lo is not None and number < lo) or (hi is not None and number > hi):
            allowed = f"must be >= {lo}" if hi is None else f"out of range [{lo}, {hi}]"
            raise FieldError(f"{self.name}: field {attr}: {self.raw[index]} {allowed}")
        return number

    def opt_str(self, attr: str, index: int) -> str | None:
        if index >= len(self.raw):
            return None  # optional trailing fields (NMEA 2.3+ mode) may be absent
        return self.raw[index] or None

    def latlon(self, lat_i: int) -> tuple[float | None, float | None]:
        """Signed degrees; both or neither, because half a position is no position."""
        lat = self.opt("lat", lat_i)
        lon = self.opt("lon", lat_i + 2)
        hemis = (self.opt_str("NS", lat_i + 1), self.opt_str("EW", lat_i + 3))
        if lat is None and lon is None:
            return None, None
        if lat is None or lon is None:
            missing = "lat" if lat is None else "lon"
            raise MissingFieldError(f"{self.name}: missing field {missing} (the other is set)")
        if hemis[0] not in ("N", "S") or hemis[1] not in ("E", "W"):
            raise FieldError(f"{self.name}: bad hemisphere {hemis[0]!r}/{hemis[1]!r}")
        lat_f, lon_f = abs(float(lat)), abs(float(lon))
        if lat_f > 90.0 or lon_f > 180.0:
            raise FieldError(f"{self.name}: position out of range ({lat_f}, {lon_f})")
        return (-lat_f if hemis[0] == "S" else lat_f), (-lon_f if hemis[1] == "W" else lon_f)


def utc_ms_of_day(utc: time, leap_second: bool = False) -> int:
    """Milliseconds since 00:00 UTC; second 60 of a leap second counts on past 86 400 000,
    so 23:59:60.5 is after 23:59:59.9 and before the next day's 00:00:00.0."""
    ms = ((utc.hour * 60 + utc.minute) * 60 + utc.second) * 1000 + round(utc.microsecond / 1000)
    return ms + 1000 if leap_second else ms


def parse_leap_second(raw: str) -> time | None:
    """``235960.xx`` as 23:59:59.xx (the caller flags it as the leap second), None when
    ``raw`` is not second 60. Second 60 anywhere but 23:59 is no UTC time: a bad field."""
    match = _LEAP_SECOND.match(raw)
    if match is None:
        return None
    if match.group("hhmm") != "2359":
        raise FieldError(f"time {raw!r}: second 60 exists only as 23:59:60 (a leap second)")
    frac = match.group("frac") or ".0"
    return time(23, 59, 59, round(float(frac) * 1e6) if len(frac) > 1 else 0)


def _time(fields: _Fields, index: int = 0) -> tuple[time | None, bool]:
    """(time, leap second?) of the sentence's time field."""
    try:
        leap = parse_leap_second(fields.raw[index]) if index < len(fields.raw) else None
    except FieldError as exc:
        raise FieldError(f"{fields.name}: field {exc}") from exc
    if leap is not None:
        return leap, True
    value = fields.opt("time", index)
    if value is None:
        return None, False
    if not isinstance(value, time):
        raise FieldError(f"{fields.name}: field time: bad value {fields.raw[index]!r}")
    return value, False


def _rmc(talker: str, f: _Fields) -> Rmc:
    status = f.req("status", 1)
    if status not in ("A", "V"):
        raise FieldError(f"{f.name}: field status: bad value {status!r} (expected A or V)")
    lat, lon = f.latlon(2)
    if status == "A" and lat is None:
        raise MissingFieldError(f"{f.name}: missing field lat (status A needs a position)")
    knots = f.opt_float("spd", 6, 0.0)
    day = f.opt("date", 8)
    if day is not None and not isinstance(day, date):
        raise FieldError(f"{f.name}: field date: bad value {f.raw[8]!r}")
    utc, leap = _time(f)
    return Rmc(
        talker=talker,
        utc=utc,
        date=day,
        valid=status == "A",
        lat=lat,
        lon=lon,
        speed_kmh=None if knots is None else knots * KMH_PER_KNOT,
        course_deg=f.opt_float("cog", 7, *DEGREES),
        mode=f.opt_str("posMode", 11),
        leap_second=leap,
    )


def _gga(talker: str, f: _Fields) -> Gga:
    lat, lon = f.latlon(1)
    quality = int(f.req("quality", 5))
    if quality > 0 and lat is None:
        raise MissingFieldError(f"{f.name}: missing field lat (quality {quality} needs one)")
    num_sv = f.opt("numSV", 6)
    utc, leap = _time(f)
    return Gga(
        talker=talker,
        utc=utc,
        lat=lat,
        lon=lon,
        quality=quality,
        num_sv=None if num_sv is None else int(num_sv),
        hdop=f.opt_float("HDOP", 7),
        alt_m=f.opt_float("alt", 8),
        geoid_sep_m=f.opt_float("sep", 10),
        diff_age_s=f.opt_float("diffAge", 12) if len(f.raw) > 12 else None,
        leap_second=leap,
    )


def _vtg(talker: str, f: _Fields) -> Vtg:
    return Vtg(
        talker=talker,
        course_deg=f.opt_float("cogt", 0, *DEGREES),
        course_mag_deg=f.opt_float("cogm", 2, *DEGREES),
        speed_knots=f.opt_float("sogn", 4, 0.0),
        speed_kmh=f.opt_float("sogk", 6, 0.0),
        mode=f.opt_str("posMode", 8),
    )


def _ths(talker: str, f: _Fields) -> Ths:
    mode = f.req("mi", 1)
    if mode not in ("A", "E", "M", "S", "V"):
        raise FieldError(f"{f.name}: field mode: bad value {mode!r} (expected A/E/M/S/V)")
    return Ths(talker, f.opt_float("headt", 0, *DEGREES), mode)
