"""Seed records on their way from a ``seeds`` message to PostgreSQL, without a model per record.

At ten seeders (21 000 records/s) ingest's own CPU went mostly to making a pydantic
``SeedRecord`` per record (≈ 7 µs, and ≈ 2 kB of heap while it waited for its flush) and to
psycopg adapting every value of every row at COPY time (≈ 4 µs). Here a batch is decoded with
orjson and each record checked, field by field, against the same contract
(``gateway.core.records.SeedRecord``: required fields, ranges, literal values, no unknown
field, the topic's machine id), then encoded at once into its row of PostgreSQL's binary COPY
format: one ``bytes`` of ≈ 280 B that waits in the queue and is written to the COPY as is.

The fast path takes only the shape the cab publishes (``seed_batch_json``: every field
present, floats as JSON floats, ``utc`` as ``YYYY-MM-DDTHH:MM:SS.ffffffZ``). Anything else,
valid or not, is not judged here: ``parse_seed_batch`` returns None and the caller validates
the payload with pydantic as before, so what is accepted, and with which values, is decided
by the models alone (tests/gateway/farm_server/test_rows.py checks the two agree on mutated
payloads, and that the rows are what psycopg's own binary COPY writes).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, date, datetime
from typing import Any, get_args

import orjson

from gateway.core.records import (
    AttitudeSource,
    FixQuality,
    HeadingSource,
    PositionMethod,
    SeedRecord,
    utc_to_us,
)

# PostgreSQL's binary COPY: signature, flags, header extension length; rows; trailer
COPY_SIGNATURE = b"PGCOPY\n\xff\r\n\x00" + b"\x00\x00\x00\x00" + b"\x00\x00\x00\x00"
COPY_TRAILER = b"\xff\xff"
_PG_EPOCH_US = 946_684_800 * 1_000_000  # timestamptz counts µs from 2000-01-01 UTC
_NULL = b"\xff\xff\xff\xff"
_FIELDS = 17  # SEED_COLUMNS (16) and the point
# the point as EWKB, big-endian ("XDR", byte order flag 0: geometry's binary input takes
# either order), so that it packs in the same big-endian struct as the rest of the row:
# point type 1 with the SRID flag, SRID 4326, x = lon, y = lat
_EWKB_POINT_SRID = 0x20000001

_FIX = frozenset(get_args(FixQuality))
_HEADING_SOURCE = frozenset(get_args(HeadingSource))
_METHOD = frozenset(get_args(PositionMethod))
_ATTITUDE = frozenset(get_args(AttitudeSource))
ID_MAX = 2**63 - 1  # seed_records.id is a bigint (pydantic's int has no bound)
_KEYS = 17  # a published record's fields (seed_batch_json writes every one)
_UTC = re.compile(r"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)\.(\d{6})Z", re.ASCII)


def _text(s: str) -> bytes:
    b = s.encode()
    return struct.pack(">i", len(b)) + b


def _float(x: float | None) -> bytes:
    return _NULL if x is None else struct.pack(">id", 8, x)


@dataclass
class SeedRows:
    """One machine's seed records waiting for the database: ids and binary COPY rows, in
    step, and the UTC days they fall on (a partition each)."""

    ids: list[int] = field(default_factory=list)
    rows: list[bytes] = field(default_factory=list)
    days: set[date] = field(default_factory=set)

    def __len__(self) -> int:
        return len(self.ids)

    def extend(self, other: SeedRows) -> None:
        self.ids.extend(other.ids)
        self.rows.extend(other.rows)
        self.days |= other.days

    def prepend(self, other: SeedRows) -> None:
        self.ids[:0] = other.ids
        self.rows[:0] = other.rows
        self.days |= other.days


class RowEncoder:
    """Binary COPY rows of ``seed_records`` (the columns of ``db.SEED_COLUMNS``, then the
    point) for one machine. The constant parts of a row (field count, machine id, the
    length words, the text values of the four enumerations) are packed once per combination
    of enumeration values; a row is then one ``struct.pack``."""

    def __init__(self, machine_id: str) -> None:
        self.machine_id = machine_id
        self._head = struct.pack(">h", _FIELDS) + _text(machine_id)
        self._structs: dict[tuple[str, str, str, str], tuple[struct.Struct, bytes, bytes,
                                                             bytes, bytes]] = {}

    def _struct(self, fix: str, hsrc: str, method: str,
                attitude: str) -> tuple[struct.Struct, bytes, bytes, bytes, bytes]:
        key = (fix, hsrc, method, attitude)
        got = self._structs.get(key)
        if got is None:
            # every float present (what a seeder with RTK and dual antenna sends): one pack;
            # each text value is packed with the length word of the field after it
            c_fix = _text(fix) + b"\x00\x00\x00\x08"  # then speed_kmh
            c_hm = _text(hsrc) + b"\x00\x00\x00\x01"  # then extrapolated (a bool's byte)
            c_mid = _text(method) + b"\x00\x00\x00\x08"  # then spacing_m
            c_att = _text(attitude) + b"\x00\x00\x00\x08"  # then roll_deg
            fmt = (f">{len(self._head)}s iq ih iq id id {len(c_fix)}s d id {len(c_hm)}s ? "
                   f"{len(c_mid)}s d {len(c_att)}s d id i BIIdd")
            got = (struct.Struct(fmt), c_fix, c_hm, c_mid, c_att)
            self._structs[key] = got
        return got

    def row(self, id_: int, row: int, utc_us: int, lat: float, lon: float, fix: str,
            speed: float, heading: float | None, hsrc: str, extrapolated: bool, method: str,
            spacing: float | None, attitude: str, roll: float | None,
            pitch: float | None) -> bytes:
        """One row; values already checked against ``SeedRecord``'s constraints."""
        if heading is None or spacing is None or roll is None or pitch is None:
            return self._row_any(id_, row, utc_us, lat, lon, fix, speed, heading, hsrc,
                                 extrapolated, method, spacing, attitude, roll, pitch)
        st, c_fix, c_hm, c_mid, c_att = self._struct(fix, hsrc, method, attitude)
        return st.pack(self._head, 8, id_, 2, row, 8, utc_us - _PG_EPOCH_US, 8, lat, 8, lon,
                       c_fix, speed, 8, heading, c_hm, extrapolated, c_mid, spacing, c_att,
                       roll, 8, pitch, 25, 0, _EWKB_POINT_SRID, 4326, lon, lat)

    def _row_any(self, id_: int, row: int, utc_us: int, lat: float, lon: float, fix: str,
                 speed: float, heading: float | None, hsrc: str, extrapolated: bool,
                 method: str, spacing: float | None, attitude: str, roll: float | None,
                 pitch: float | None) -> bytes:
        """The same row, field by field (some float is null)."""
        return b"".join((
            self._head, struct.pack(">iqihiqidid", 8, id_, 2, row, 8, utc_us - _PG_EPOCH_US,
                                    8, lat, 8, lon),
            _text(fix), struct.pack(">id", 8, speed), _float(heading), _text(hsrc),
            struct.pack(">i?", 1, extrapolated), _text(method), _float(spacing),
            _text(attitude), _float(roll), _float(pitch),
            struct.pack(">iBIIdd", 25, 0, _EWKB_POINT_SRID, 4326, lon, lat),
        ))

    def record(self, r: SeedRecord) -> bytes:
        """The row of a validated record (the slow path's, and ``write_seed_batches``')."""
        return self.row(r.id, r.row, utc_to_us(r.utc), r.lat, r.lon, r.fix, r.speed_kmh,
                        r.heading_deg, r.heading_source, r.extrapolated, r.method,
                        r.spacing_m, r.attitude, r.roll_deg, r.pitch_deg)


def rows_of_records(machine_id: str, records: Iterable[SeedRecord],
                    encoder: RowEncoder | None = None) -> SeedRows:
    """Validated records as queued rows. ``ValueError`` for an id beyond a bigint (valid to
    the model, not to the table: it must be refused, not retried for ever)."""
    enc = encoder or RowEncoder(machine_id)
    out = SeedRows()
    for r in records:
        if r.id > ID_MAX:
            raise ValueError(f"id {r.id} is beyond a bigint")
        out.ids.append(r.id)
        out.rows.append(enc.record(r))
        out.days.add(r.utc.astimezone(UTC).date())
    return out


# the epoch second of a "YYYY-MM-DDTHH:MM:SS" (UTC), and its day; seeds of one second share it
_SECONDS: dict[str, tuple[int, date]] = {}
_SECONDS_MAX = 4096


def _second(prefix: str) -> tuple[int, date] | None:
    got = _SECONDS.get(prefix)
    if got is None:
        try:
            t = datetime.fromisoformat(prefix).replace(tzinfo=UTC)
        except ValueError:
            return None
        got = (utc_to_us(t) // 1_000_000, t.date())
        if len(_SECONDS) >= _SECONDS_MAX:
            _SECONDS.clear()
        _SECONDS[prefix] = got
    return got


@dataclass
class ParsedBatch:
    rows: SeedRows
    min_id: int
    pending_from: int | None


def parse_seed_batch(payload: bytes, machine_id: str,
                     encoder: RowEncoder) -> ParsedBatch | None:
    """A ``seeds`` payload of the shape the cab publishes, for this topic's machine, as queued
    rows; None for anything else (the caller then validates it with pydantic, which accepts
    or rejects it and says why). Accepts nothing ``SeedBatch`` would refuse."""
    try:
        doc = orjson.loads(payload)
    except orjson.JSONDecodeError:
        return None
    try:
        return _parse(doc, machine_id, encoder)
    except (KeyError, TypeError):  # a field missing, or of a type a set cannot hash
        return None


def _parse(doc: Any, machine_id: str, encoder: RowEncoder) -> ParsedBatch | None:
    if type(doc) is not dict or doc.get("machine_id") != machine_id:
        return None
    records = doc.get("records")
    pending = doc.get("pending_from")
    if type(records) is not list or len(doc) != 2 + ("pending_from" in doc):
        return None
    if pending is not None and (type(pending) is not int or pending < 1):
        return None
    out = SeedRows()
    ids, rows, days = out.ids, out.rows, out.days
    encode = encoder.row
    last_prefix = ""
    second_us = 0
    fixes, sources, methods, attitudes = _FIX, _HEADING_SOURCE, _METHOD, _ATTITUDE
    match = _UTC.fullmatch
    for r in records:
        if type(r) is not dict or len(r) != _KEYS:
            return None
        i = r["id"]
        row = r["row"]
        lat = r["lat"]
        lon = r["lon"]
        speed = r["speed_kmh"]
        heading = r["heading_deg"]
        spacing = r["spacing_m"]
        roll = r["roll_deg"]
        pitch = r["pitch_deg"]
        accuracy = r["accuracy_m"]
        extrapolated = r["extrapolated"]
        fix = r["fix"]
        hsrc = r["heading_source"]
        method = r["method"]
        attitude = r["attitude"]
        if not (
            type(i) is int and 1 <= i <= ID_MAX and type(row) is int and 1 <= row <= 128
            and type(lat) is float and -90.0 <= lat <= 90.0
            and type(lon) is float and -180.0 <= lon <= 180.0
            and type(speed) is float and speed >= 0.0
            and (heading is None or (type(heading) is float and 0.0 <= heading < 360.0))
            and (spacing is None or (type(spacing) is float and spacing >= 0.0))
            and (roll is None or (type(roll) is float and -90.0 <= roll <= 90.0))
            and (pitch is None or (type(pitch) is float and -90.0 <= pitch <= 90.0))
            and (accuracy is None or (type(accuracy) is float and accuracy >= 0.0))
            and (extrapolated is True or extrapolated is False)
            and type(fix) is str and fix in fixes and type(hsrc) is str and hsrc in sources
            and type(method) is str and method in methods
            and type(attitude) is str and attitude in attitudes
            and r["machine_id"] == machine_id
        ):
            return None
        utc = r["utc"]
        if type(utc) is not str:
            return None
        m = match(utc)
        if m is None:
            return None
        prefix = m.group(1)
        if prefix != last_prefix:
            second = _second(prefix)
            if second is None:
                return None
            last_prefix = prefix
            second_us = second[0] * 1_000_000
            days.add(second[1])
        ids.append(i)
        rows.append(encode(i, row, second_us + int(m.group(2)), lat, lon, fix, speed, heading,
                           hsrc, extrapolated, method, spacing, attitude, roll, pitch))
    return ParsedBatch(out, min(ids) if ids else 0, pending)
