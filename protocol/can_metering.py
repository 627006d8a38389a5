"""Frames of paper B's metering controllers, encoded and decoded through ``metering.dbc``.

The DBC is the contract with whoever builds (or configures) the controller: a Rexroth RC or
any PLC can be set up from it without reading Python. This module only adds typing and the
checks cantools leaves to the caller (node range, DLC, unknown ids), so a garbled frame on
the bus becomes a ``protocol.errors`` exception instead of a KeyError deep in cantools.

Ids are 11-bit: command ``0x200 + node`` (terminal -> controller), status ``0x280 + node``
(controller -> terminal), node 1..15. See docs/can.md.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import cantools

from protocol.errors import FieldError, FrameError

DBC_PATH = Path(__file__).with_name("metering.dbc")
COMMAND_BASE_ID = 0x200
STATUS_BASE_ID = 0x280
NODE_MIN = 1
NODE_MAX = 15
FRAME_DLC = 8
SPEED_RESOLUTION_RPM = 0.01
SPEED_MAX_RPM = 655.35  # 16 bits at 0.01 r/min
SEQUENCE_MODULO = 256


class FaultCode(enum.IntEnum):
    """Controller fault codes (DBC value table of ``FaultCode``)."""

    NONE = 0
    ENCODER = 1
    VALVE = 2
    OVERPRESSURE = 3
    STALL = 4
    SUPPLY_VOLTAGE = 5
    COMMAND_TIMEOUT = 6
    UNKNOWN = 255  # any code this terminal does not know yet; still a fault


@dataclass(frozen=True, slots=True)
class SpeedCommand:
    """Target shaft speed for one controller."""

    node_id: int
    target_rpm: float
    enable: bool
    sequence: int


@dataclass(frozen=True, slots=True)
class MeterStatus:
    """What one controller reports about its shaft."""

    node_id: int
    measured_rpm: float
    enabled: bool
    at_target: bool
    stalled: bool
    fault_active: bool
    fault: FaultCode
    raw_fault_code: int
    sequence_echo: int
    valve_pct: float

    @property
    def faulted(self) -> bool:
        return self.fault_active or self.fault is not FaultCode.NONE


@cache
def database() -> Any:
    """The parsed DBC, loaded once (cantools parsing is slow and the file never changes)."""
    return cantools.database.load_file(str(DBC_PATH))


def _check_node(node_id: int) -> None:
    if not NODE_MIN <= node_id <= NODE_MAX:
        raise FieldError(f"node_id {node_id} outside {NODE_MIN}..{NODE_MAX}")


def command_id(node_id: int) -> int:
    _check_node(node_id)
    return COMMAND_BASE_ID + node_id


def status_id(node_id: int) -> int:
    _check_node(node_id)
    return STATUS_BASE_ID + node_id


def frame_kind(arbitration_id: int) -> tuple[str, int] | None:
    """``("command"|"status", node)`` for one of our ids, else None (other traffic on the bus)."""
    for kind, base in (("command", COMMAND_BASE_ID), ("status", STATUS_BASE_ID)):
        node = arbitration_id - base
        if NODE_MIN <= node <= NODE_MAX:
            return kind, node
    return None


def _check_speed(rpm: float, what: str) -> None:
    if not (0.0 <= rpm <= SPEED_MAX_RPM):  # also rejects NaN
        raise FieldError(f"{what} {rpm!r} r/min outside 0..{SPEED_MAX_RPM}")


def encode_command(cmd: SpeedCommand) -> tuple[int, bytes]:
    """(arbitration id, 8 data bytes) for a target-speed command."""
    _check_node(cmd.node_id)
    _check_speed(cmd.target_rpm, "target speed")
    if not 0 <= cmd.sequence < SEQUENCE_MODULO:
        raise FieldError(f"sequence {cmd.sequence} outside 0..{SEQUENCE_MODULO - 1}")
    frame_id = command_id(cmd.node_id)
    data = database().encode_message(
        frame_id,
        {"TargetSpeed": round(cmd.target_rpm, 2), "Enable": int(cmd.enable),
         "Sequence": cmd.sequence},
    )
    return frame_id, bytes(data)


def encode_status(st: MeterStatus) -> tuple[int, bytes]:
    """(arbitration id, 8 data bytes) for a status frame; used by simulators and tests."""
    _check_node(st.node_id)
    _check_speed(st.measured_rpm, "measured speed")
    if not 0 <= st.raw_fault_code <= 255 or not 0 <= st.sequence_echo < SEQUENCE_MODULO:
        raise FieldError("fault code and sequence echo must fit one byte")
    if not 0.0 <= st.valve_pct <= 127.5:
        raise FieldError(f"valve command {st.valve_pct!r} % outside 0..127.5")
    frame_id = status_id(st.node_id)
    data = database().encode_message(
        frame_id,
        {
            "MeasuredSpeed": round(st.measured_rpm, 2),
            "Enabled": int(st.enabled),
            "AtTarget": int(st.at_target),
            "Stalled": int(st.stalled),
            "FaultActive": int(st.fault_active),
            "FaultCode": st.raw_fault_code,
            "SequenceEcho": st.sequence_echo,
            "ValveCommand": round(st.valve_pct * 2) / 2,
        },
    )
    return frame_id, bytes(data)


def _decode(frame_id: int, data: bytes, expected: str) -> tuple[int, dict[str, Any]]:
    kind = frame_kind(frame_id)
    if kind is None:
        raise FrameError(f"unknown metering frame id 0x{frame_id:03X}")
    if kind[0] != expected:
        raise FrameError(f"frame 0x{frame_id:03X} is a {kind[0]} frame, expected {expected}")
    if len(data) != FRAME_DLC:
        raise FrameError(f"frame 0x{frame_id:03X} has DLC {len(data)}, expected {FRAME_DLC}")
    signals = database().decode_message(frame_id, bytes(data), decode_choices=False)
    return kind[1], signals


def decode_command(frame_id: int, data: bytes) -> SpeedCommand:
    node, s = _decode(frame_id, data, "command")
    return SpeedCommand(
        node_id=node,
        target_rpm=round(float(s["TargetSpeed"]), 2),
        enable=bool(s["Enable"]),
        sequence=int(s["Sequence"]),
    )


def decode_status(frame_id: int, data: bytes) -> MeterStatus:
    node, s = _decode(frame_id, data, "status")
    raw = int(s["FaultCode"])
    try:
        fault = FaultCode(raw)
    except ValueError:
        fault = FaultCode.UNKNOWN
    return MeterStatus(
        node_id=node,
        measured_rpm=round(float(s["MeasuredSpeed"]), 2),
        enabled=bool(s["Enabled"]),
        at_target=bool(s["AtTarget"]),
        stalled=bool(s["Stalled"]),
        fault_active=bool(s["FaultActive"]),
        fault=fault,
        raw_fault_code=raw,
        sequence_echo=int(s["SequenceEcho"]),
        valve_pct=float(s["ValveCommand"]),
    )


def decode(frame_id: int, data: bytes) -> SpeedCommand | MeterStatus:
    """Decode either kind of metering frame by id."""
    kind = frame_kind(frame_id)
    if kind is None:
        raise FrameError(f"unknown metering frame id 0x{frame_id:03X}")
    if kind[0] == "command":
        return decode_command(frame_id, data)
    return decode_status(frame_id, data)
