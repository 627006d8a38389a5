"""Register maps of the three devices on the RS485 bus, as pure codecs (registers <-> values).

The same functions serve the daemon (decode what a device answers) and the simulator (encode
what a device would answer), so a round trip through both is a test of the register contract.

Radar (any Modbus radar speed sensor)
    One value in 1 or 2 holding registers, typed by ``data_type`` (uint16 | int16 | uint32 |
    int32 | float32) and, for 32-bit types, ``word_order`` (``big`` = high word first, the
    Modbus convention; ``little`` = low word first, common on cheap sensors). ``raw * scale``
    is the value in ``unit``; ``doppler_hz`` units are converted with paper A eq. 1:
    ``V = c * f_d / (2 * cos(theta) * f_i)``, c = 1.079e9 km/h, f_i = 24 GHz.
    Negative values are passed through (a radar that reports direction reports reverse as
    negative); the control layer decides what reversing means.

WitMotion inclinometer (SINAT-485 / WT901-485 family)
    ``witmotion16``: the standard WitMotion Modbus map, one int16 per angle,
    Roll 0x3D, Pitch 0x3E, Yaw 0x3F, ``deg = int16 / 32768 * 180``.
    ``witmotion32``: the WitMotion high-precision map (HWT9073-485 style), one int32 per angle
    stored LOW word first, as WitMotion documents it: LRoll 0x3D, HRoll 0x3E, LPitch 0x3F,
    HPitch 0x40, LYaw 0x41, HYaw 0x42, ``deg = int32 / 1000``.

PWM output module
    One holding register per channel, duty in 0.1 % units, 0..1000 (100.0 %).
    Register 0x0010 (``PWM_COMM_TIMEOUT_REGISTER``): communication-loss timeout in 0.1 s
    units, 0 = off (the power-up value). The module type sowgate supports stops both outputs
    (duty 0) by itself when it has received no request for that long, so the motor stops
    when the bus is gone and sowgate can no longer write. sowgate writes it at start and
    reads it back; a module that lacks it must not drive a metering motor (README, safe
    states).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from protocol.errors import FieldError

RadarDataType = Literal["uint16", "int16", "uint32", "int32", "float32"]
WordOrder = Literal["big", "little"]
SpeedUnit = Literal["km/h", "m/s", "mm/s", "doppler_hz"]
InclinometerLayout = Literal["witmotion16", "witmotion32"]
Axis = Literal["roll", "pitch", "yaw"]

REGISTER_MAX = 0xFFFF

SPEED_OF_LIGHT_KMH = 1.079e9  # paper A eq. 1 (c in km/h)
RADAR_CARRIER_HZ = 24e9  # f_i, 24 GHz mm-wave radar

# struct format and register count per radar data type
_FORMATS: dict[str, tuple[str, int]] = {
    "uint16": ("H", 1),
    "int16": ("h", 1),
    "uint32": ("I", 2),
    "int32": ("i", 2),
    "float32": ("f", 2),
}

WITMOTION_ANGLE_BASE = 0x3D
WITMOTION16_SCALE_DEG = 180.0 / 32768.0
WITMOTION32_SCALE_DEG = 1.0 / 1000.0
_AXIS_INDEX: dict[str, int] = {"roll": 0, "pitch": 1, "yaw": 2}

DUTY_REGISTER_MAX = 1000  # 100.0 % in 0.1 % steps
DUTY_UNITS_PER_PCT = 10
PWM_COMM_TIMEOUT_REGISTER = 0x0010
COMM_TIMEOUT_UNITS_PER_S = 10  # 0.1 s steps
COMM_TIMEOUT_REGISTER_MAX = 6000  # 600.0 s, the longest the module accepts


# ---------------------------------------------------------------------------------------------
# Generic numbers in registers


def registers_needed(data_type: RadarDataType) -> int:
    """How many 16-bit registers one value of ``data_type`` occupies."""
    try:
        return _FORMATS[data_type][1]
    except KeyError:
        raise FieldError(
            f"unknown data_type {data_type!r}, expected one of {sorted(_FORMATS)}"
        ) from None


def _check_registers(registers: Sequence[int], count: int, what: str) -> None:
    if len(registers) != count:
        raise FieldError(f"{what} needs {count} register(s), got {len(registers)}")
    for reg in registers:
        if not 0 <= reg <= REGISTER_MAX:
            raise FieldError(f"{what}: register value {reg} is not a 16-bit word")


def decode_number(
    registers: Sequence[int], data_type: RadarDataType, word_order: WordOrder = "big"
) -> float:
    """The number held in ``registers`` (raw, unscaled)."""
    fmt, count = _FORMATS.get(data_type, ("", 0))
    if not fmt:
        registers_needed(data_type)  # raises the specific error
    _check_registers(registers, count, data_type)
    words = list(registers)
    if word_order == "little":
        words.reverse()
    elif word_order != "big":
        raise FieldError(f"unknown word_order {word_order!r}, expected 'big' or 'little'")
    raw = b"".join(w.to_bytes(2, "big") for w in words)
    (value,) = struct.unpack(">" + fmt, raw)
    return float(value)


def encode_number(
    value: float, data_type: RadarDataType, word_order: WordOrder = "big"
) -> list[int]:
    """Registers holding raw ``value``; integers must be whole and fit the type."""
    fmt, _count = _FORMATS.get(data_type, ("", 0))
    if not fmt:
        registers_needed(data_type)
    if not math.isfinite(value):
        raise FieldError(f"{data_type}: cannot encode non-finite value {value}")
    if data_type == "float32":
        try:
            raw = struct.pack(">f", value)
        except OverflowError:
            raise FieldError(f"float32: {value} does not fit") from None
    else:
        if value != int(value):
            raise FieldError(f"{data_type}: {value} is not a whole number")
        try:
            raw = struct.pack(">" + fmt, int(value))
        except struct.error:
            raise FieldError(f"{data_type}: {value} is out of range") from None
    words = [int.from_bytes(raw[i : i + 2], "big") for i in range(0, len(raw), 2)]
    if word_order == "little":
        words.reverse()
    elif word_order != "big":
        raise FieldError(f"unknown word_order {word_order!r}, expected 'big' or 'little'")
    return words


# ---------------------------------------------------------------------------------------------
# Radar speed


def doppler_to_kmh(doppler_hz: float, mount_angle_deg: float) -> float:
    """Paper A eq. 1: ground speed from the Doppler shift at mounting angle theta."""
    return SPEED_OF_LIGHT_KMH * doppler_hz / (2.0 * _cos_mount(mount_angle_deg) * RADAR_CARRIER_HZ)


def kmh_to_doppler(speed_kmh: float, mount_angle_deg: float) -> float:
    """Inverse of eq. 1 (what a radar at ``mount_angle_deg`` measures at ``speed_kmh``)."""
    return speed_kmh * 2.0 * _cos_mount(mount_angle_deg) * RADAR_CARRIER_HZ / SPEED_OF_LIGHT_KMH


def _cos_mount(mount_angle_deg: float) -> float:
    if not 0.0 <= mount_angle_deg < 90.0:
        raise FieldError(f"mount angle {mount_angle_deg} deg outside 0..90 (exclusive)")
    return math.cos(math.radians(mount_angle_deg))


_TO_KMH = {"km/h": 1.0, "m/s": 3.6, "mm/s": 0.0036}


def to_kmh(value: float, unit: SpeedUnit, mount_angle_deg: float) -> float:
    """A speed (or Doppler shift) in ``unit`` as km/h."""
    if unit == "doppler_hz":
        return doppler_to_kmh(value, mount_angle_deg)
    try:
        return value * _TO_KMH[unit]
    except KeyError:
        raise FieldError(f"unknown speed unit {unit!r}") from None


def from_kmh(speed_kmh: float, unit: SpeedUnit, mount_angle_deg: float) -> float:
    """Inverse of :func:`to_kmh`."""
    if unit == "doppler_hz":
        return kmh_to_doppler(speed_kmh, mount_angle_deg)
    try:
        return speed_kmh / _TO_KMH[unit]
    except KeyError:
        raise FieldError(f"unknown speed unit {unit!r}") from None


@dataclass(frozen=True)
class RadarFormat:
    """How one radar model puts its speed into holding registers."""

    data_type: RadarDataType = "uint16"
    word_order: WordOrder = "big"
    scale: float = 0.01
    unit: SpeedUnit = "km/h"
    mount_angle_deg: float = 49.5

    def __post_init__(self) -> None:
        registers_needed(self.data_type)
        if not math.isfinite(self.scale) or self.scale == 0:
            raise FieldError(f"radar scale must be finite and non-zero (got {self.scale})")
        if self.unit not in ("km/h", "m/s", "mm/s", "doppler_hz"):
            raise FieldError(f"unknown speed unit {self.unit!r}")
        _cos_mount(self.mount_angle_deg)

    @property
    def count(self) -> int:
        return registers_needed(self.data_type)

    def decode_kmh(self, registers: Sequence[int]) -> float:
        """Speed in km/h from the registers the radar answered."""
        raw = decode_number(registers, self.data_type, self.word_order)
        if not math.isfinite(raw):
            raise FieldError(f"radar sent a non-finite {self.data_type} ({raw})")
        return to_kmh(raw * self.scale, self.unit, self.mount_angle_deg)

    def encode_kmh(self, speed_kmh: float) -> list[int]:
        """Registers a radar of this format would hold at ``speed_kmh`` (integers rounded)."""
        raw = from_kmh(speed_kmh, self.unit, self.mount_angle_deg) / self.scale
        if self.data_type != "float32":
            if not math.isfinite(raw):
                raise FieldError(f"{self.data_type}: cannot encode {speed_kmh} km/h")
            raw = float(round(raw))
        return encode_number(raw, self.data_type, self.word_order)


# ---------------------------------------------------------------------------------------------
# Hopper scale (Modbus weight transmitter)

WeightDataType = Literal["int32", "uint16", "int16", "float32"]
WEIGHT_MIN_FRACTION = -0.05  # below -5 % of capacity a load cell is faulty, not light
WEIGHT_MAX_FRACTION = 1.2  # above 120 % of capacity: overload or a bad reading


@dataclass(frozen=True)
class WeightFormat:
    """How a weight transmitter holds the gross weight: one number in 1 or 2 holding
    registers (``int32`` high word first is the common default), ``raw * grams_per_count``
    grams. A reading outside -5 %..120 % of ``capacity_kg`` does not come from a working
    load cell (a transmitter reporting 0x7FFFFFFF on overload, an unwired channel)."""

    data_type: WeightDataType = "int32"
    word_order: WordOrder = "big"
    grams_per_count: float = 1.0
    capacity_kg: float = 3000.0

    def __post_init__(self) -> None:
        registers_needed(self.data_type)
        if not math.isfinite(self.grams_per_count) or self.grams_per_count <= 0:
            raise FieldError(
                f"weight scale must be finite and positive (got {self.grams_per_count})"
            )

    @property
    def count(self) -> int:
        return registers_needed(self.data_type)

    def decode_kg(self, registers: Sequence[int]) -> float:
        """The hopper mass in kg; FieldError for a value no working scale reports."""
        raw = decode_number(registers, self.data_type, self.word_order)
        if not math.isfinite(raw):
            raise FieldError(f"weight is a non-finite {self.data_type} ({raw})")
        kg = raw * self.grams_per_count / 1000.0
        lo, hi = WEIGHT_MIN_FRACTION * self.capacity_kg, WEIGHT_MAX_FRACTION * self.capacity_kg
        if not lo <= kg <= hi:
            raise FieldError(
                f"weight {kg:.1f} kg outside the plausible {lo:g}..{hi:g} kg "
                f"(capacity {self.capacity_kg:g} kg)"
            )
        return kg

    def encode_kg(self, kg: float) -> list[int]:
        """Registers a transmitter of this format holds at ``kg`` (integers rounded)."""
        raw = kg * 1000.0 / self.grams_per_count
        if self.data_type == "float32" and not math.isfinite(raw):
            # what a faulty transmitter sends (NaN on a broken cell): the simulator's fault
            words = [int.from_bytes(struct.pack(">f", raw)[i : i + 2], "big") for i in (0, 2)]
            return words[::-1] if self.word_order == "little" else words
        if self.data_type != "float32":
            if not math.isfinite(raw):
                raise FieldError(f"{self.data_type}: cannot encode {kg} kg")
            raw = float(round(raw))
        return encode_number(raw, self.data_type, self.word_order)


# ---------------------------------------------------------------------------------------------
# WitMotion inclinometer


def inclinometer_span(layout: InclinometerLayout, axis: Axis) -> tuple[int, int]:
    """(first register, count) holding ``axis`` in ``layout``."""
    index = _axis_index(axis)
    if layout == "witmotion16":
        return WITMOTION_ANGLE_BASE + index, 1
    if layout == "witmotion32":
        return WITMOTION_ANGLE_BASE + 2 * index, 2
    raise FieldError(f"unknown inclinometer layout {layout!r}, expected witmotion16|witmotion32")


def _axis_index(axis: str) -> int:
    try:
        return _AXIS_INDEX[axis]
    except KeyError:
        raise FieldError(f"unknown axis {axis!r}, expected roll|pitch|yaw") from None


def decode_angle(registers: Sequence[int], layout: InclinometerLayout) -> float:
    """Angle in degrees from the registers of one axis."""
    if layout == "witmotion16":
        return decode_number(registers, "int16") * WITMOTION16_SCALE_DEG
    if layout == "witmotion32":
        return decode_number(registers, "int32", "little") * WITMOTION32_SCALE_DEG
    raise FieldError(f"unknown inclinometer layout {layout!r}, expected witmotion16|witmotion32")


def encode_angle(angle_deg: float, layout: InclinometerLayout) -> list[int]:
    """Registers an inclinometer would hold at ``angle_deg`` (rounded to its resolution)."""
    if not math.isfinite(angle_deg):
        raise FieldError(f"cannot encode non-finite angle {angle_deg}")
    if layout == "witmotion16":
        raw = round(angle_deg / WITMOTION16_SCALE_DEG)
        if not -32768 <= raw <= 32767:
            raise FieldError(f"witmotion16: angle {angle_deg} deg outside -180..+180")
        return encode_number(raw, "int16")
    if layout == "witmotion32":
        if abs(angle_deg) > 360.0:
            raise FieldError(f"witmotion32: angle {angle_deg} deg outside -360..+360")
        raw = round(angle_deg / WITMOTION32_SCALE_DEG)
        return encode_number(raw, "int32", "little")
    raise FieldError(f"unknown inclinometer layout {layout!r}, expected witmotion16|witmotion32")


# ---------------------------------------------------------------------------------------------
# PWM duty


def encode_duty(pct: float) -> int:
    """Register value for a duty in percent. Out-of-range is an error, not a clamp: the
    control layer clamps on purpose and a value arriving here out of range is a bug."""
    if not math.isfinite(pct) or not 0.0 <= pct <= 100.0:
        raise FieldError(f"duty {pct} % outside 0..100 %")
    return round(pct * DUTY_UNITS_PER_PCT)


def decode_duty(register: int) -> float:
    """Duty in percent from a register value (0..1000)."""
    if not 0 <= register <= DUTY_REGISTER_MAX:
        raise FieldError(f"duty register {register} outside 0..{DUTY_REGISTER_MAX}")
    return register / DUTY_UNITS_PER_PCT


# ---------------------------------------------------------------------------------------------
# PWM module communication-loss watchdog


def encode_comm_timeout(seconds: float) -> int:
    """Register value for a communication-loss timeout (0.1 s steps; 0 switches it off)."""
    if not math.isfinite(seconds) or not 0.0 <= seconds <= (
        COMM_TIMEOUT_REGISTER_MAX / COMM_TIMEOUT_UNITS_PER_S
    ):
        raise FieldError(
            f"comm-loss timeout {seconds} s outside 0..{COMM_TIMEOUT_REGISTER_MAX / 10:g} s"
        )
    return round(seconds * COMM_TIMEOUT_UNITS_PER_S)


def decode_comm_timeout(register: int) -> float:
    """Communication-loss timeout in seconds from a register value (0 = off)."""
    if not 0 <= register <= COMM_TIMEOUT_REGISTER_MAX:
        raise FieldError(
            f"comm-loss timeout register {register} outside 0..{COMM_TIMEOUT_REGISTER_MAX}"
        )
    return register / COMM_TIMEOUT_UNITS_PER_S
