"""The simulated receiver's own sentence encoder: NMEA $--RMC/$--GGA and Unicore #HEADINGA.

Written for the simulator and sharing no code with ``protocol/`` (a test checks that importing
this module, ``simulator.um982`` or ``simulator.field_truth`` loads nothing from ``protocol``,
``drivers`` or ``gateway``): the field truth is rendered by this code and decoded by the
gateway's, so a decoder bug shows up as an error instead of cancelling out against an encoder
that shares it. Layout and integrity as the UM982 prints them (checked against published
captures of real receivers in ``tests/simulator/test_gnss_sentences.py``):

* NMEA: ``$<talker><id>,...*hh``, hh the XOR of every byte between ``$`` and ``*`` as two
  upper-case hex digits; latitude ``ddmm.mmmmmmmm`` and longitude ``dddmm.mmmmmmmm`` (8
  decimals of minutes), time ``hhmmss.ss``, GGA height and geoid separation to 4 decimals,
  RMC speed in knots to 3 decimals and course to 1;
* Unicore ASCII logs: ``#<name>,<header>;<body>*xxxxxxxx``, xxxxxxxx the CRC-32 of every byte
  between ``#`` and ``*`` (reflected polynomial 0xEDB88320, initial value 0, no final XOR, as
  the receiver computes it; *not* zlib's CRC-32) in lower-case hex; the legacy header
  ``port,sequence,idle %,time status,week,seconds of week,status,reserved,version``.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Final, Literal

Fix = Literal["rtk_fixed", "rtk_float", "dgps", "single", "none"]

KNOT_KMH: Final = 1.852  # one knot in km/h (the international nautical mile per hour)
GPS_MINUS_UTC_S: Final = 18  # leap seconds between GPS time and UTC since 2017-01-01
GPS_START: Final = datetime(1980, 1, 6, tzinfo=UTC)
WEEK_S: Final = 604_800
GEOID_SEP_M: Final = 40.0  # a plausible geoid separation; GGA altitude = ellipsoidal - this

# GGA quality and RMC mode indicator for each fix type (NMEA 0183 v4.1 / the UM982 manual)
GGA_QUALITY: Final[dict[str, int]] = {
    "rtk_fixed": 4, "rtk_float": 5, "dgps": 2, "single": 1, "none": 0,
}
RMC_MODE: Final[dict[str, str]] = {
    "rtk_fixed": "R", "rtk_float": "F", "dgps": "D", "single": "A", "none": "N",
}


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        c = byte
        for _ in range(8):
            c = (c >> 1) ^ 0xEDB88320 if c & 1 else c >> 1
        table.append(c)
    return tuple(table)


_CRC_TABLE: Final = _crc_table()


def unicore_crc(data: bytes) -> int:
    """CRC-32 as the Unicore receivers compute it: reflected 0xEDB88320, init 0, no final XOR."""
    crc = 0
    for b in data:
        crc = _CRC_TABLE[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc


def xor_checksum(content: str) -> str:
    """The NMEA checksum of ``content`` (the text between ``$`` and ``*``), two hex digits."""
    x = 0
    for b in content.encode("ascii"):
        x ^= b
    return f"{x:02X}"


def nmea_line(content: str) -> str:
    """``$content*hh`` (no line terminator)."""
    return f"${content}*{xor_checksum(content)}"


def unicore_line(content: str) -> str:
    """``#content*xxxxxxxx`` (no line terminator)."""
    return f"#{content}*{unicore_crc(content.encode('ascii')):08x}"


def gps_week_tow(utc: datetime, leap_s: int = GPS_MINUS_UTC_S) -> tuple[int, float]:
    """(GPS week, seconds of week to the millisecond) of an aware UTC instant."""
    ms = (utc + timedelta(seconds=leap_s) - GPS_START) // timedelta(milliseconds=1)
    week, tow_ms = divmod(ms, WEEK_S * 1000)
    return week, tow_ms / 1000.0


def dm(value: float, deg_digits: int) -> str:
    """Degrees to NMEA (d)ddmm.mmmmmmmm, 8 decimals of minutes, as the UM982 prints."""
    units = round(abs(value) * 60.0 * 1e8)
    deg, minutes = divmod(units, 60 * 10**8)
    return f"{deg:0{deg_digits}d}{minutes // 10**8:02d}.{minutes % 10**8:08d}"


def hms(utc: datetime, leap_second: bool = False) -> str:
    """hhmmss.ss; with ``leap_second`` (utc is 23:59:59.x) the receiver prints second 60."""
    centis = min(99, round(utc.microsecond / 10_000))  # 100 only for sub-centisecond times
    if leap_second:
        return f"{utc:%H%M}60.{centis:02d}"
    return f"{utc:%H%M%S}.{centis:02d}"


def rmc(utc: datetime, lat: float, lon: float, speed_kmh: float, course_deg: float,
        fix: Fix = "rtk_fixed", *, talker: str = "GN", leap_second: bool = False) -> str:
    """$--RMC: time, status, position, speed over ground (knots), course, date, magnetic
    variation (empty: the UM982 leaves it so without a configured model), mode, nav status."""
    has_fix = fix != "none"
    pos = _position(lat, lon) if has_fix else ",,,"
    knots = max(0.0, speed_kmh) / KNOT_KMH
    return nmea_line(
        f"{talker}RMC,{hms(utc, leap_second)},{'A' if has_fix else 'V'},{pos},"
        f"{knots:.3f},{course_deg % 360.0:.1f},{utc:%d%m%y},,,{RMC_MODE[fix]},V"
    )


def gga(utc: datetime, lat: float, lon: float, alt_msl_m: float, fix: Fix = "rtk_fixed", *,
        num_sv: int = 28, hdop: float = 0.6, geoid_sep_m: float = GEOID_SEP_M,
        talker: str = "GN", leap_second: bool = False) -> str:
    """$--GGA: time, position, quality, satellites (2 digits), HDOP, height above MSL and geoid
    separation (4 decimals, metres), age of corrections and base station id (with RTK/DGPS)."""
    has_fix = fix != "none"
    pos = _position(lat, lon) if has_fix else ",,,"
    quality = GGA_QUALITY[fix]
    diff = "1.0,0001" if quality in (2, 4, 5) else ","
    tail = f"{alt_msl_m:.4f},M,{geoid_sep_m:.4f},M,{diff}" if has_fix else ",M,,M,,"
    return nmea_line(
        f"{talker}GGA,{hms(utc, leap_second)},{pos},{quality},{num_sv if has_fix else 0:02d},"
        f"{hdop if has_fix else 99.9:.1f},{tail}"
    )


def headinga(week: int, tow_s: float, heading_deg: float, pitch_deg: float = 0.0,
             baseline_m: float = 1.0, *, sol_status: str = "SOL_COMPUTED",
             pos_type: str = "NARROW_INT", hdg_std: float = 0.08, ptch_std: float = 0.16,
             num_sv_tracked: int = 28, num_sv_used: int = 22, port: str = "COM1",
             sequence: int = 0, idle_pct: float = 50.0) -> str:
    """#HEADINGA with the legacy header, as UM982 firmware sends it: solution status,
    position type, baseline length (m), heading, pitch (°), reserved, heading and pitch σ (°),
    station id, satellites tracked / used / above the mask / with L2, reserved, extended
    solution status, Galileo / BDS signal masks."""
    header = (f"HEADINGA,{port},{sequence},{idle_pct:.1f},FINE,{week},{tow_s:.3f},"
              f"00000000,0,1")
    body = (
        f"{sol_status},{pos_type},{baseline_m:.4f},{heading_deg % 360.0:.4f},{pitch_deg:.4f},"
        f'0.0000,{hdg_std:.4f},{ptch_std:.4f},"0",{num_sv_tracked},{num_sv_used},'
        f"{num_sv_used},{max(0, num_sv_used - 4)},0,01,3,f3"
    )
    return unicore_line(f"{header};{body}")


def _position(lat: float, lon: float) -> str:
    return (f"{dm(lat, 2)},{'N' if lat >= 0 else 'S'},"
            f"{dm(lon, 3)},{'E' if lon >= 0 else 'W'}")


def epoch_sentences(
    utc: datetime, lat: float, lon: float, alt_m: float, speed_kmh: float, course_deg: float,
    heading_deg: float, fix: Fix = "rtk_fixed", heading_ok: bool = True, *,
    num_sv: int = 28, hdop: float = 0.6, pitch_deg: float = 0.0, baseline_m: float = 1.0,
    hdg_std: float = 0.08, geoid_sep_m: float = GEOID_SEP_M, talker: str = "GN",
    leap_second: bool = False, gps_utc_leap_s: int = GPS_MINUS_UTC_S,
) -> list[str]:
    """One epoch's RMC, GGA and #HEADINGA (no line terminators).

    ``alt_m`` is the height above mean sea level that GGA carries. With ``fix="none"`` the
    position fields are empty, as a receiver without a fix sends them. With ``leap_second``
    ``utc`` is 23:59:59.x and the sentences say 23:59:60.x; the heading log carries the GPS
    time of that instant (one second after ``utc``, ``gps_utc_leap_s`` still the old count).
    """
    if utc.tzinfo is None:
        raise ValueError("utc must be timezone-aware")
    utc = utc.astimezone(UTC)
    week, tow = gps_week_tow(utc + timedelta(seconds=1 if leap_second else 0), gps_utc_leap_s)
    if heading_ok:
        heading = headinga(week, tow, heading_deg, pitch_deg, baseline_m, hdg_std=hdg_std,
                           ptch_std=2 * hdg_std, num_sv_tracked=num_sv,
                           num_sv_used=max(0, num_sv - 6))
    else:
        heading = headinga(week, tow, 0.0, 0.0, 0.0, sol_status="INSUFFICIENT_OBS",
                           pos_type="NONE", hdg_std=0.0, ptch_std=0.0, num_sv_tracked=num_sv,
                           num_sv_used=0)
    return [
        rmc(utc, lat, lon, speed_kmh, course_deg, fix, talker=talker, leap_second=leap_second),
        gga(utc, lat, lon, alt_m, fix, num_sv=num_sv, hdop=hdop, geoid_sep_m=geoid_sep_m,
            talker=talker, leap_second=leap_second),
        heading,
    ]
