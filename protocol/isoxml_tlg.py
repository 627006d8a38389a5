"""ISO 11783-10 time log (TLG) binary records and their XML header, pure and sans-I/O.

An ISO-XML task logs its process data in ``TLGnnnnn.BIN``, described by ``TLGnnnnn.XML``.
The header is a ``TIM`` element whose *empty* attributes say which fields every binary record
carries: ``<PTN A="" B=""/>`` means each record holds a north and an east coordinate, an
attribute that is absent is not recorded. The ``DLV`` children number the logged values: the
n-th ``DLV`` (its DDI and the device element it belongs to) is index n in the records.

A binary record, little-endian, back to back with no framing (ISO 11783-10 annex; read the
same way by isoxml-js ``ExtendedTimeLog.parseBinaryFile`` and ADAPT's ``TimeLogMapper``):

==========================  =======  =============================================
time of day                 uint32   ms since midnight
date                        uint16   days since 1980-01-01
PositionNorth (PTN ``A``)   int32    degrees x 1e7, only if the header lists ``A``
PositionEast (``B``)        int32    degrees x 1e7
PositionUp (``C``)          int32    mm
PositionStatus (``D``)      uint8    0 none, 1 GNSS, 2 DGNSS, 3 precise, 4 RTK fixed, 5 RTK float
PDOP (``E``), HDOP (``F``)  uint16   x 0.1
NumberOfSatellites (``G``)  uint8
GpsUtcTime (``H``)          uint32   ms since midnight UTC
GpsUtcDate (``I``)          uint16   days since 1980-01-01 (UTC)
count                       uint8    logged values that follow
count x (index, value)      uint8, int32
==========================  =======  =============================================

The standard does not say which clock the record time is on: ADAPT reads it as local time,
isoxml-js as UTC. sowgate writes UTC in both the record time and GpsUtcTime/GpsUtcDate, so a
reader that honours the GPS fields gets the same instant either way (docs/isoxml.md).

One index is a uint8, so a time log can name at most 256 values and a record can carry at
most 255 (its count is a uint8 too); a writer with more splits them over several time logs.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from protocol.errors import FrameError, ProtocolError

# The PTN attributes in record order, with their struct codes (ISO 11783-10 TimeLog XSD).
POSITION_FIELDS: dict[str, str] = {
    "A": "i",  # PositionNorth, deg x 1e7
    "B": "i",  # PositionEast, deg x 1e7
    "C": "i",  # PositionUp, mm
    "D": "B",  # PositionStatus
    "E": "H",  # PDOP x 0.1
    "F": "H",  # HDOP x 0.1
    "G": "B",  # NumberOfSatellites
    "H": "I",  # GpsUtcTime, ms since midnight
    "I": "H",  # GpsUtcDate, days since 1980-01-01
}
MAX_VALUES_PER_LOG = 256  # the DLV index is a uint8
MAX_VALUES_PER_RECORD = 255  # the count is a uint8
MS_PER_DAY = 86_400_000
# 1980-01-01T00:00:00Z in µs since the Unix epoch (3652 days after 1970-01-01)
EPOCH_1980_US = 3652 * MS_PER_DAY * 1000
DEGREE_SCALE = 10_000_000

_INT32 = (-(2**31), 2**31 - 1)
_RANGES = {"i": _INT32, "B": (0, 255), "H": (0, 65535), "I": (0, 2**32 - 1)}
_PAIR = struct.Struct("<Bi")
_COUNT = struct.Struct("<B")


class TimeLogError(ProtocolError):
    """A time log that cannot be written or read: a value out of its field's range, a
    truncated binary, a header that names no DLVs or too many."""


@dataclass(frozen=True, slots=True)
class TimeLogLayout:
    """Which position fields every record carries (PTN attribute letters, in record order)."""

    position_fields: tuple[str, ...] = ("A", "B", "D", "H", "I")

    def __post_init__(self) -> None:
        order = list(POSITION_FIELDS)
        for name in self.position_fields:
            if name not in POSITION_FIELDS:
                raise TimeLogError(f"PTN has no attribute {name!r} (A..I)")
        positions = [order.index(n) for n in self.position_fields]
        if positions != sorted(set(positions)):
            raise TimeLogError(
                f"PTN attributes must be unique and in record order A..I, got "
                f"{self.position_fields}"
            )

    @property
    def head(self) -> struct.Struct:
        """The fixed part of a record: time, date and the position fields."""
        return struct.Struct("<IH" + "".join(POSITION_FIELDS[n] for n in self.position_fields))


@dataclass(frozen=True, slots=True)
class TimeLogRecord:
    """One binary record: raw integers as stored (``position`` in the layout's field order,
    ``values`` as (DLV index, value) pairs)."""

    ms_of_day: int
    days_since_1980: int
    position: tuple[int, ...] = ()
    values: tuple[tuple[int, int], ...] = ()


@dataclass(frozen=True, slots=True)
class DataLogValue:
    """A ``DLV`` of the header: the DDI logged and the device element (``DET`` id) it is of."""

    ddi: int
    det_id: str


def encode_record(layout: TimeLogLayout, record: TimeLogRecord) -> bytes:
    """The record's bytes; every field is range-checked (``TimeLogError`` names it)."""
    if len(record.position) != len(layout.position_fields):
        raise TimeLogError(
            f"record has {len(record.position)} position fields, the layout "
            f"{len(layout.position_fields)} ({''.join(layout.position_fields)})"
        )
    _check("time of day (ms)", record.ms_of_day, (0, MS_PER_DAY - 1))
    _check("date (days since 1980)", record.days_since_1980, _RANGES["H"])
    for name, value in zip(layout.position_fields, record.position, strict=True):
        _check(f"PTN {name}", value, _RANGES[POSITION_FIELDS[name]])
    if len(record.values) > MAX_VALUES_PER_RECORD:
        raise TimeLogError(
            f"{len(record.values)} values in one record, at most {MAX_VALUES_PER_RECORD}"
        )
    parts = [layout.head.pack(record.ms_of_day, record.days_since_1980, *record.position),
             _COUNT.pack(len(record.values))]
    for index, value in record.values:
        _check("DLV index", index, _RANGES["B"])
        _check(f"value of DLV {index}", value, _INT32)
        parts.append(_PAIR.pack(index, value))
    return b"".join(parts)


def decode_records(layout: TimeLogLayout, data: bytes) -> Iterator[TimeLogRecord]:
    """The records of a binary time log, in file order; a truncated tail is a ``FrameError``
    naming the record and the offset (the records before it have been yielded)."""
    head = layout.head
    n_position = len(layout.position_fields)
    offset, number, size = 0, 0, len(data)
    while offset < size:
        if offset + head.size + 1 > size:
            raise FrameError(f"time log record {number} at byte {offset}: truncated header")
        fields = head.unpack_from(data, offset)
        offset += head.size
        (count,) = _COUNT.unpack_from(data, offset)
        offset += 1
        end = offset + count * _PAIR.size
        if end > size:
            raise FrameError(
                f"time log record {number} at byte {offset}: {count} values announced, "
                f"{(size - offset) // _PAIR.size} present"
            )
        values = tuple(_PAIR.unpack_from(data, offset + i * _PAIR.size) for i in range(count))
        offset = end
        yield TimeLogRecord(fields[0], fields[1], tuple(fields[2:2 + n_position]), values)
        number += 1


def utc_us_to_tlg_time(utc_us: int) -> tuple[int, int]:
    """µs since the Unix epoch (UTC) as (ms since midnight, days since 1980-01-01); the
    microseconds below a millisecond are dropped (floor), as the record time has none."""
    if utc_us < EPOCH_1980_US:
        raise TimeLogError(f"time {utc_us} µs is before 1980-01-01, which a time log cannot hold")
    days, ms = divmod((utc_us - EPOCH_1980_US) // 1000, MS_PER_DAY)
    return ms, days


def tlg_time_to_utc_us(ms_of_day: int, days_since_1980: int) -> int:
    """The inverse of ``utc_us_to_tlg_time`` (to the millisecond)."""
    return EPOCH_1980_US + (days_since_1980 * MS_PER_DAY + ms_of_day) * 1000


def degrees_to_tlg(degrees: float) -> int:
    """A latitude or longitude as the record's int32 (1e-7 degree, rounded to nearest)."""
    if not -180.0 <= degrees <= 180.0:
        raise TimeLogError(f"{degrees} is not a latitude or longitude in degrees")
    return round(degrees * DEGREE_SCALE)


def tlg_to_degrees(value: int) -> float:
    return value / DEGREE_SCALE


def _check(what: str, value: int, bounds: tuple[int, int]) -> None:
    lo, hi = bounds
    if not isinstance(value, int) or not lo <= value <= hi:
        raise TimeLogError(f"{what} = {value!r} does not fit ({lo}..{hi})")


# ---------------------------------------------------------------- the XML header


def header_xml(layout: TimeLogLayout, values: Sequence[DataLogValue]) -> bytes:
    """``TLGnnnnn.XML``: ``<TIM A="" D="4">`` (start time in every record, type effective),
    the ``PTN`` with the layout's fields present-but-empty and one ``DLV`` per value."""
    if not values:
        raise TimeLogError("a time log needs at least one DLV")
    if len(values) > MAX_VALUES_PER_LOG:
        raise TimeLogError(f"{len(values)} DLVs in one time log, at most {MAX_VALUES_PER_LOG}")
    tim = ET.Element("TIM", {"A": "", "D": "4"})
    ET.SubElement(tim, "PTN", dict.fromkeys(layout.position_fields, ""))
    for v in values:
        if not 0 <= v.ddi <= 0xFFFF:
            raise TimeLogError(f"DDI {v.ddi} out of range (0..65535)")
        ET.SubElement(tim, "DLV", {"A": f"{v.ddi:04X}", "B": "", "C": v.det_id})
    ET.indent(tim)
    return b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(tim) + b"\n"


def parse_header_xml(text: bytes | str) -> tuple[TimeLogLayout, list[DataLogValue]]:
    """The layout and DLVs of a ``TLGnnnnn.XML`` (the fields a reader needs to decode the
    binary); a header this reader cannot use is a ``TimeLogError`` saying why."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise TimeLogError(f"time log header is not XML: {exc}") from None
    if root.tag != "TIM":
        raise TimeLogError(f"time log header root is <{root.tag}>, expected <TIM>")
    if root.get("A") != "":
        raise TimeLogError("time log header: only TIM A=\"\" (time in every record) is read")
    ptn = root.find("PTN")
    fields: tuple[str, ...] = ()
    if ptn is not None:
        fields = tuple(n for n in POSITION_FIELDS if ptn.get(n) == "")
    values = []
    for i, dlv in enumerate(root.findall("DLV")):
        try:
            ddi = int(dlv.get("A", ""), 16)
        except ValueError:
            raise TimeLogError(f"DLV {i}: A={dlv.get('A')!r} is not a hex DDI") from None
        if dlv.get("B") != "":
            raise TimeLogError(f"DLV {i}: only B=\"\" (value in the records) is read")
        values.append(DataLogValue(ddi, dlv.get("C", "")))
    return TimeLogLayout(fields), values


__all__ = [
    "EPOCH_1980_US",
    "MAX_VALUES_PER_LOG",
    "MAX_VALUES_PER_RECORD",
    "POSITION_FIELDS",
    "DataLogValue",
    "TimeLogError",
    "TimeLogLayout",
    "TimeLogRecord",
    "decode_records",
    "degrees_to_tlg",
    "encode_record",
    "header_xml",
    "parse_header_xml",
    "tlg_time_to_utc_us",
    "tlg_to_degrees",
    "utc_us_to_tlg_time",
]
