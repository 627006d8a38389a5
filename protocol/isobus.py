"""Tractor messages of ISO 11783-7 that a seeder needs: speeds and the rear hitch.

All multi-byte fields are little-endian; byte and bit numbers below are the standard's
(byte 1 = first data byte, bit 1 = least significant). A value the tractor marks as error or
"not available" decodes to ``None`` with a validity tag, never to a plausible-looking number,
because a seeder that believed a 0xFFFF speed (65.5 m/s) would dump its hopper.

Layouts (8 data bytes each):
- 65097 ground-based speed, 65096 wheel-based speed, 61474 machine selected speed:
  bytes 1-2 speed 0.001 m/s/bit (raw 0..64255 valid), bytes 3-6 distance 0.001 m/bit,
  byte 8 bits 1-2 direction (00 reverse, 01 forward, 10 error, 11 not available).
- 65093 rear hitch status: byte 1 position 0.4 %/bit (0..250 valid), byte 2 bits 7-8
  in-work (00 out of work, 01 in work, 10 error, 11 not available).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from protocol.errors import FieldError, FrameError

PGN_GROUND_SPEED = 65097
PGN_WHEEL_SPEED = 65096
PGN_MACHINE_SELECTED_SPEED = 61474
PGN_REAR_HITCH = 65093
SPEED_PGNS = (PGN_GROUND_SPEED, PGN_WHEEL_SPEED, PGN_MACHINE_SELECTED_SPEED)
KNOWN_PGNS = (*SPEED_PGNS, PGN_REAR_HITCH)

SPEED_SCALE_MPS = 0.001
SPEED_RAW_MAX = 64255  # 0xFAFF; above: reserved, error (0xFE..), not available (0xFF..)
DISTANCE_SCALE_M = 0.001
DISTANCE_RAW_MAX = 0xFAFFFFFF
HITCH_SCALE_PCT = 0.4
HITCH_RAW_MAX = 250  # 100 %
DATA_LENGTH = 8
CAN_EFF_MAX = 0x1FFFFFFF
PDU2_MIN_PF = 240
DEFAULT_PRIORITY = 3


class Validity(enum.Enum):
    VALID = "valid"
    RESERVED = "reserved"
    ERROR = "error"
    NOT_AVAILABLE = "not_available"


class Direction(enum.IntEnum):
    REVERSE = 0
    FORWARD = 1
    ERROR = 2
    NOT_AVAILABLE = 3


class InWork(enum.IntEnum):
    OUT_OF_WORK = 0
    IN_WORK = 1
    ERROR = 2
    NOT_AVAILABLE = 3


@dataclass(frozen=True, slots=True)
class CanId:
    """The parts of a 29-bit J1939/ISO 11783 identifier."""

    priority: int
    pgn: int
    source_address: int
    destination_address: int | None  # PDU1 only; None for broadcast PDU2


@dataclass(frozen=True, slots=True)
class SpeedMessage:
    pgn: int
    source_address: int
    speed_mps: float | None
    validity: Validity
    distance_m: float | None
    direction: Direction

    @property
    def speed_kmh(self) -> float | None:
        return None if self.speed_mps is None else self.speed_mps * 3.6


@dataclass(frozen=True, slots=True)
class HitchStatus:
    source_address: int
    position_pct: float | None
    in_work: InWork


def parse_can_id(can_id: int) -> CanId:
    """Split a 29-bit id. PDU1 (PF < 240): PS is a destination and not part of the PGN."""
    if not 0 <= can_id <= CAN_EFF_MAX:
        raise FrameError(f"CAN id 0x{can_id:X} is not a 29-bit identifier")
    priority = (can_id >> 26) & 0x7
    edp_dp = (can_id >> 24) & 0x3
    pf = (can_id >> 16) & 0xFF
    ps = (can_id >> 8) & 0xFF
    sa = can_id & 0xFF
    if pf < PDU2_MIN_PF:
        return CanId(priority, (edp_dp << 16) | (pf << 8), sa, ps)
    return CanId(priority, (edp_dp << 16) | (pf << 8) | ps, sa, None)


def build_can_id(pgn: int, source_address: int, priority: int = DEFAULT_PRIORITY,
                 destination: int = 0xFF) -> int:
    """Inverse of :func:`parse_can_id` (used by the tractor simulator and tests)."""
    if not 0 <= pgn <= 0x3FFFF or not 0 <= source_address <= 0xFF or not 0 <= priority <= 7:
        raise FieldError("pgn, source address or priority out of range")
    pf = (pgn >> 8) & 0xFF
    ps = pgn & 0xFF
    if pf < PDU2_MIN_PF:
        if ps != 0:
            raise FieldError(f"PDU1 PGN {pgn} must have a zero low byte")
        ps = destination & 0xFF
    return (priority << 26) | ((pgn >> 16) << 24) | (pf << 16) | (ps << 8) | source_address


def _speed_validity(raw: int) -> Validity:
    if raw <= SPEED_RAW_MAX:
        return Validity.VALID
    if raw >= 0xFF00:
        return Validity.NOT_AVAILABLE
    if raw >= 0xFE00:
        return Validity.ERROR
    return Validity.RESERVED


def _check_data(data: bytes) -> None:
    if len(data) != DATA_LENGTH:
        raise FrameError(f"ISOBUS message needs {DATA_LENGTH} data bytes, got {len(data)}")


def decode_speed(pgn: int, source_address: int, data: bytes) -> SpeedMessage:
    _check_data(data)
    if pgn not in SPEED_PGNS:
        raise FrameError(f"PGN {pgn} is not a speed message")
    raw_speed, raw_dist = struct.unpack_from("<HI", data, 0)
    validity = _speed_validity(raw_speed)
    speed = raw_speed * SPEED_SCALE_MPS if validity is Validity.VALID else None
    dist = raw_dist * DISTANCE_SCALE_M if raw_dist <= DISTANCE_RAW_MAX else None
    return SpeedMessage(pgn, source_address, speed, validity, dist, Direction(data[7] & 0x3))


def decode_hitch(source_address: int, data: bytes) -> HitchStatus:
    _check_data(data)
    raw_pos = data[0]
    pos = raw_pos * HITCH_SCALE_PCT if raw_pos <= HITCH_RAW_MAX else None
    return HitchStatus(source_address, pos, InWork((data[1] >> 6) & 0x3))


def decode(can_id: int, data: bytes) -> SpeedMessage | HitchStatus | None:
    """Decode one frame; None for PGNs this module does not handle (the bus carries many)."""
    parts = parse_can_id(can_id)
    if parts.pgn in SPEED_PGNS:
        return decode_speed(parts.pgn, parts.source_address, data)
    if parts.pgn == PGN_REAR_HITCH:
        return decode_hitch(parts.source_address, data)
    return None


def encode_speed(pgn: int, speed_mps: float | None, direction: Direction = Direction.FORWARD,
                 distance_m: float | None = 0.0, raw_speed: int | None = None) -> bytes:
    """8 data bytes of a speed message; ``raw_speed`` forces a raw code (e.g. 0xFE00 error)."""
    if pgn not in SPEED_PGNS:
        raise FieldError(f"PGN {pgn} is not a speed message")
    if raw_speed is None:
        if speed_mps is None:
            raw_speed = 0xFFFF
        else:
            raw_speed = round(speed_mps / SPEED_SCALE_MPS)
            if not 0 <= raw_speed <= SPEED_RAW_MAX:
                raise FieldError(f"speed {speed_mps} m/s outside 0..{SPEED_RAW_MAX / 1000} m/s")
    raw_dist = 0xFFFFFFFF if distance_m is None else (
        round(distance_m / DISTANCE_SCALE_M) % (DISTANCE_RAW_MAX + 1)
    )
    # byte 7 (unused here) and bits 3-8 of byte 8 are "not available" (all ones)
    return struct.pack("<HIBB", raw_speed & 0xFFFF, raw_dist, 0xFF, 0xFC | int(direction))


def encode_hitch(position_pct: float | None, in_work: InWork) -> bytes:
    if position_pct is None:
        raw = 0xFF
    else:
        raw = round(position_pct / HITCH_SCALE_PCT)
        if not 0 <= raw <= HITCH_RAW_MAX:
            raise FieldError(f"hitch position {position_pct} % outside 0..100")
    return bytes([raw, (int(in_work) << 6) | 0x3F, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])
