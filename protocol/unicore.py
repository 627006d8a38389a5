"""Unicore ASCII heading logs (#HEADINGA, #UNIHEADINGA) from the UM982's dual-antenna solution.

NMEA has no standard sentence carrying heading *quality*; the Unicore log does (solution status,
ambiguity type, standard deviations), and that is what decides whether a seed record may use
the heading or must fall back to the course over ground.

Two header layouts exist on the same receiver family:

* legacy (NovAtel-style) ``#HEADINGA,COM1,<seq>,<idle%>,<time status>,<week>,<tow s>,
  <rx status>,<reserved>,<build>;`` — time of week in seconds with decimals;
* N4 ``#UNIHEADINGA,<cpu idle%>,<time ref>,<time status>,<week>,<tow ms>,<reserved>,
  <version>,<leap s>,<output delay ms>;`` — time of week in integer milliseconds, and the
  receiver's own leap second count. The time reference is ``GPS`` (the default) or ``BDS``
  when the receiver is set to BeiDou time: BDT runs 14 s behind GPS time and its week 0
  began 1356 GPS weeks later, so such a log is converted to GPS time on parsing (otherwise
  every heading would be stamped 14 s early and never meet its RMC/GGA epoch).

The 8-hex-digit CRC is CRC-32 with the reflected polynomial 0xEDB88320, initial value 0 and no
final XOR over the bytes between ``#`` and ``*``. That is *not* ``zlib.crc32`` (which starts at
0xFFFFFFFF and inverts at the end), hence the table below.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import ClassVar, Final

from protocol.errors import ChecksumError, FieldError, FrameError
from protocol.nmea import MissingFieldError, TruncatedError, UnknownSentenceError

CRC32_POLY_REFLECTED: Final = 0xEDB88320
MAX_UNICORE_LINE_CHARS: Final = 600  # the longest ASCII log we accept (BESTNAVA is ~330)
GPS_UTC_LEAP_S: Final = 18  # GPS time minus UTC since 2017-01-01; the N4 header carries its own
GPS_EPOCH: Final = datetime(1980, 1, 6, tzinfo=UTC)
# BeiDou time (BDT): epoch 2006-01-01 00:00:00 UTC = GPS week 1356 + 14 s; BDT = GPST - 14 s.
BDS_WEEK_OFFSET: Final = 1356
BDS_GPS_OFFSET_S: Final = 14
TIME_REFS: Final = frozenset({"GPS", "BDS"})
SECONDS_PER_WEEK: Final = 7 * 86400

HEADING_LOGS: Final = frozenset({"HEADINGA", "UNIHEADINGA"})

# Ambiguity-fixed baseline types: heading to a few hundredths of a degree, safe to use.
FIXED_POS_TYPES: Final = frozenset({"NARROW_INT", "WIDE_INT", "L1_INT", "INS_RTKFIXED"})
# Float-ambiguity types: a heading exists but may be off by degrees; recorded, not trusted.
FLOAT_POS_TYPES: Final = frozenset(
    {"NARROW_FLOAT", "L1_FLOAT", "IONOFREE_FLOAT", "WIDE_FLOAT", "INS_RTKFLOAT"}
)

_TRAILER = re.compile(r"\*(?P<crc>[0-9A-Fa-f]{8})$")
_MIN_BODY_FIELDS: Final = 8  # sol, pos type, length, heading, pitch, reserved, hdg std, ptch std


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ CRC32_POLY_REFLECTED if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE: Final = _make_table()


def unicore_crc32(data: bytes) -> int:
    """Unicore/NovAtel ASCII-log CRC: reflected CRC-32, init 0, no final XOR."""
    crc = 0
    for byte in data:
        crc = _CRC_TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc


@dataclass(frozen=True)
class Heading:
    """One dual-antenna heading solution, stamped in GPS time by the receiver."""

    log: str  # HEADINGA or UNIHEADINGA
    gps_week: int
    gps_tow_s: float
    leap_s: int | None  # from the N4 header; None for the legacy header
    time_status: str
    sol_status: str
    pos_type: str
    baseline_m: float
    heading_deg: float
    pitch_deg: float
    hdg_std: float
    ptch_std: float
    station_id: str | None = None
    num_sv_tracked: int | None = None
    num_sv_used: int | None = None
    time_ref: str = "GPS"  # the header's time system; week and tow above are GPS time

    kind: ClassVar[str] = "HEADING"

    @property
    def valid(self) -> bool:
        """Usable for seed positions: a computed, ambiguity-fixed baseline."""
        return self.sol_status == "SOL_COMPUTED" and self.pos_type in FIXED_POS_TYPES

    @property
    def quality(self) -> str:
        """``fixed``, ``float`` or ``none`` — what the record's quality flag reports."""
        if self.sol_status != "SOL_COMPUTED":
            return "none"
        if self.pos_type in FIXED_POS_TYPES:
            return "fixed"
        if self.pos_type in FLOAT_POS_TYPES:
            return "float"
        return "none"

    def utc(self, leap_s: int | None = None) -> datetime:
        """UTC of this solution, using the header's leap seconds when it has them."""
        leap = leap_s if leap_s is not None else self.leap_s
        return gps_to_utc(self.gps_week, self.gps_tow_s, GPS_UTC_LEAP_S if leap is None else leap)


def gps_to_utc(week: int, tow_s: float, leap_s: int = GPS_UTC_LEAP_S) -> datetime:
    """GPS week + time of week to an aware UTC datetime (rounded to the millisecond)."""
    ms = round(tow_s * 1000.0)
    return GPS_EPOCH + timedelta(weeks=week, milliseconds=ms) - timedelta(seconds=leap_s)


def place_in_leap_second(utc: datetime, leap_midnight: datetime | None) -> tuple[datetime, bool]:
    """A log's UTC on the NMEA time line while a leap second is being inserted.

    GPS time has no leap seconds and runs on through one: converted with the GPS−UTC count
    from before it, a log of the leap second reads 00:00:00.x while the NMEA sentences of the
    same instant say 23:59:60.x (the count in the header changes only after it). Given the
    midnight that ends the leap second in progress (known from the NMEA ``235960``), a UTC in
    ``[midnight, midnight + 1 s)`` is that second: returned as 23:59:59.x with True, the
    representation ``protocol.nmea`` uses for second 60. Any other UTC is returned as is.
    """
    if leap_midnight is not None and leap_midnight <= utc < leap_midnight + timedelta(seconds=1):
        return utc - timedelta(seconds=1), True
    return utc, False


def utc_to_gps(utc: datetime, leap_s: int = GPS_UTC_LEAP_S) -> tuple[int, float]:
    """Aware UTC datetime to (GPS week, time of week in seconds)."""
    delta = utc + timedelta(seconds=leap_s) - GPS_EPOCH
    total_ms = delta // timedelta(milliseconds=1)
    week, ms = divmod(total_ms, SECONDS_PER_WEEK * 1000)
    return week, ms / 1000.0


def split_unicore(line: str) -> tuple[str, list[str], list[str]]:
    """Check framing and CRC; return (log name, header fields after the name, body fields)."""
    line = line.strip("\r\n ")
    if not line.startswith("#"):
        raise FrameError(f"not a Unicore log: does not start with '#' ({line[:16]!r})")
    if len(line) > MAX_UNICORE_LINE_CHARS:
        # the limit guards the heading logs we decode; a long log we do not use is not ours
        log = line[1:].split(",", 1)[0].split(";", 1)[0]
        if log.isalnum() and log.isascii() and log not in HEADING_LOGS:
            raise UnknownSentenceError(f"unknown Unicore log {log} ({len(line)} characters)", log)
        raise FrameError(f"line too long: {len(line)} > {MAX_UNICORE_LINE_CHARS} characters")
    trailer = _TRAILER.search(line)
    if trailer is None:
        raise TruncatedError("truncated: no '*xxxxxxxx' CRC at the end of the line")
    content = line[1 : trailer.start()]
    if "*" in content or "#" in content:
        raise FrameError("malformed: '#' or '*' inside the log body")
    got = trailer.group("crc").lower()
    try:
        expected = f"{unicore_crc32(content.encode('ascii')):08x}"
    except UnicodeEncodeError as exc:
        raise FrameError("malformed: non-ASCII characters in the log") from exc
    if got != expected:
        raise ChecksumError(f"CRC mismatch: expected {expected}, got {got}")
    header, sep, body = content.partition(";")
    if not sep:
        raise FrameError("malformed: no ';' between header and body")
    head = header.split(",")
    return head[0], head[1:], body.split(",")


def parse_unicore(line: str) -> Heading:
    """Decode a #HEADINGA or #UNIHEADINGA line; raise a ProtocolError subclass if not."""
    log, head, body = split_unicore(line)
    if log not in HEADING_LOGS:
        raise UnknownSentenceError(f"unknown Unicore log {log}", log)
    time_ref = "GPS"
    if log == "HEADINGA":
        week, tow_s, leap, time_status = _legacy_header(log, head)
    else:
        week, tow_s, leap, time_status, time_ref = _n4_header(log, head)
    if len(body) < _MIN_BODY_FIELDS:
        raise MissingFieldError(
            f"{log}: missing fields: body has {len(body)}, needs at least {_MIN_BODY_FIELDS}"
        )
    return Heading(
        log=log,
        gps_week=week,
        gps_tow_s=tow_s,
        leap_s=leap,
        time_status=time_status,
        sol_status=_word(log, "sol_status", body[0]),
        pos_type=_word(log, "pos_type", body[1]),
        baseline_m=_float(log, "baseline", body[2]),
        heading_deg=_float(log, "heading", body[3], 0.0, 360.0),
        pitch_deg=_float(log, "pitch", body[4], -90.0, 90.0),
        hdg_std=_float(log, "hdg_std", body[6]),
        ptch_std=_float(log, "ptch_std", body[7]),
        station_id=body[8].strip('"') if len(body) > 8 else None,
        num_sv_tracked=_int(log, "num_sv_tracked", body[9]) if len(body) > 9 else None,
        num_sv_used=_int(log, "num_sv_used", body[10]) if len(body) > 10 else None,
        time_ref=time_ref,
    )


def _legacy_header(log: str, head: list[str]) -> tuple[int, float, int | None, str]:
    if len(head) < 6:
        raise MissingFieldError(f"{log}: header has {len(head)} fields, needs at least 6")
    return _int(log, "week", head[4]), _float(log, "seconds", head[5]), None, head[3]


def _n4_header(log: str, head: list[str]) -> tuple[int, float, int | None, str, str]:
    """(GPS week, GPS time of week s, GPS-UTC leap s, time status, time reference)."""
    if len(head) < 8:
        raise MissingFieldError(f"{log}: header has {len(head)} fields, needs at least 8")
    time_ref = head[1]
    if time_ref not in TIME_REFS:
        raise FieldError(
            f"{log}: field time reference: {time_ref!r} not supported (expected GPS or BDS)"
        )
    week = _int(log, "week", head[3])
    tow_s = _int(log, "ms of week", head[4]) / 1000.0
    leap = _int(log, "leap", head[7])
    if time_ref == "BDS":
        week, tow_s = bds_to_gps(week, tow_s)
        # GPS-UTC has been >= 14 s since BDT began (2006) and BDT-UTC = GPS-UTC - 14 s, so a
        # smaller count can only be BDT-UTC: either way it becomes GPS-UTC here.
        if leap < BDS_GPS_OFFSET_S:
            leap += BDS_GPS_OFFSET_S
    return week, tow_s, leap, head[2], time_ref


def bds_to_gps(bds_week: int, bds_tow_s: float) -> tuple[int, float]:
    """BeiDou week and time of week to GPS week and time of week."""
    week = bds_week + BDS_WEEK_OFFSET
    tow_s = bds_tow_s + BDS_GPS_OFFSET_S
    if tow_s >= SECONDS_PER_WEEK:
        week, tow_s = week + 1, tow_s - SECONDS_PER_WEEK
    return week, tow_s


def gps_to_bds(gps_week: int, gps_tow_s: float) -> tuple[int, float]:
    """GPS week and time of week to BeiDou week and time of week."""
    week = gps_week - BDS_WEEK_OFFSET
    tow_s = gps_tow_s - BDS_GPS_OFFSET_S
    if tow_s < 0:
        week, tow_s = week - 1, tow_s + SECONDS_PER_WEEK
    return week, tow_s


def _word(log: str, name: str, raw: str) -> str:
    if not raw:
        raise MissingFieldError(f"{log}: missing field {name} (empty)")
    if not raw.replace("_", "").isalnum():
        raise FieldError(f"{log}: field {name}: bad value {raw!r}")
    return raw


def _float(
    log: str, name: str, raw: str, lo: float | None = None, hi: float | None = None
) -> float:
    if raw == "":
        raise MissingFieldError(f"{log}: missing field {name} (empty)")
    try:
        value = float(raw)
    except ValueError as exc:
        raise FieldError(f"{log}: field {name}: bad value {raw!r}") from exc
    if value != value or (lo is not None and value < lo) or (hi is not None and value > hi):
        raise FieldError(f"{log}: field {name}: {raw} out of range [{lo}, {hi}]")
    return value


def _int(log: str, name: str, raw: str) -> int:
    if raw == "":
        raise MissingFieldError(f"{log}: missing field {name} (empty)")
    try:
        value = int(raw)
    except ValueError as exc:
        raise FieldError(f"{log}: field {name}: bad value {raw!r}") from exc
    if value < 0:
        raise FieldError(f"{log}: field {name}: negative value {raw}")
    return value


def _frame(content: str) -> str:
    return f"#{content}*{unicore_crc32(content.encode('ascii')):08x}"


def _body(
    heading_deg: float,
    pitch_deg: float,
    baseline_m: float,
    sol_status: str,
    pos_type: str,
    hdg_std: float,
    ptch_std: float,
    num_sv_tracked: int,
    num_sv_used: int,
) -> str:
    return (
        f"{sol_status},{pos_type},{baseline_m:.4f},{heading_deg % 360.0:.4f},{pitch_deg:.4f},"
        f'0.0000,{hdg_std:.4f},{ptch_std:.4f},"0",{num_sv_tracked},{num_sv_used},'
        f"{num_sv_used},{max(0, num_sv_used - 4)},0,01,3,f3"
    )


def encode_headinga(
    gps_week: int,
    gps_tow_s: float,
    heading_deg: float,
    pitch_deg: float = 0.0,
    baseline_m: float = 1.0,
    *,
    sol_status: str = "SOL_COMPUTED",
    pos_type: str = "NARROW_INT",
    hdg_std: float = 0.1,
    ptch_std: float = 0.2,
    num_sv_tracked: int = 24,
    num_sv_used: int = 20,
    port: str = "COM1",
    sequence: int = 0,
    idle_pct: float = 50.0,
) -> str:
    """A legacy-header #HEADINGA line (no terminator), the layout UM982 firmware sends."""
    header = (
        f"HEADINGA,{port},{sequence},{idle_pct:.1f},FINE,{gps_week},{gps_tow_s:.3f},"
        f"00000000,0,1"
    )
    body = _body(
        heading_deg, pitch_deg, baseline_m, sol_status, pos_type, hdg_std, ptch_std,
        num_sv_tracked, num_sv_used,
    )
    return _frame(f"{header};{body}")


def encode_uniheadinga(
    gps_week: int,
    gps_tow_s: float,
    heading_deg: float,
    pitch_deg: float = 0.0,
    baseline_m: float = 1.0,
    *,
    sol_status: str = "SOL_COMPUTED",
    pos_type: str = "NARROW_INT",
    hdg_std: float = 0.1,
    ptch_std: float = 0.2,
    num_sv_tracked: int = 24,
    num_sv_used: int = 20,
    leap_s: int = GPS_UTC_LEAP_S,
    idle_pct: int = 80,
    output_delay_ms: int = 10,
    time_ref: str = "GPS",
) -> str:
    """An N4-header #UNIHEADINGA line (no terminator).

    With ``time_ref="BDS"`` the header carries BeiDou week and time of week (converted from
    the GPS values given) and ``leap_s`` as given.
    """
    week, tow_s = (gps_week, gps_tow_s) if time_ref != "BDS" else gps_to_bds(gps_week, gps_tow_s)
    tow_ms = round(tow_s * 1000.0)
    header = (
        f"UNIHEADINGA,{idle_pct},{time_ref},FINE,{week},{tow_ms},0,0,{leap_s},{output_delay_ms}"
    )
    body = _body(
        heading_deg, pitch_deg, baseline_m, sol_status, pos_type, hdg_std, ptch_std,
        num_sv_tracked, num_sv_used,
    )
    return _frame(f"{header};{body}")
