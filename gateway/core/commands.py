"""Operator commands, whatever screen or topic they come from.

The HMI and MQTT both translate their input into these values and hand them to one
``CommandSink`` (the controller), so validation and effects are identical on every path: a rate
the touchscreen would refuse is refused over MQTT with the same words.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol


@dataclass(frozen=True)
class SetRate:
    crop: str
    rate_kg_ha: float


@dataclass(frozen=True)
class SetChannelRate:
    """Target rate of one ``[[channel]]`` (the rate outside the prescription map)."""

    channel: str
    rate_kg_ha: float


@dataclass(frozen=True)
class Start:
    pass


@dataclass(frozen=True)
class Stop:
    pass


@dataclass(frozen=True)
class ZeroTilt:
    pass


@dataclass(frozen=True)
class CriticalTilt:
    """Paper B's attitude calibration, live: with the implement lowered to the ground, the
    mean of the last 3 inclinometer readings becomes the critical angle."""


@dataclass(frozen=True)
class EmptySeed:
    pass


@dataclass(frozen=True)
class SeedLevelMonitoring:
    enabled: bool


@dataclass(frozen=True)
class CalibrateSpeed:
    """Paper A's speed calibration, live: ``start`` at a marker, drive a measured distance,
    ``finish`` with that distance; every speed source that reported gets its factor."""

    action: str  # "start" | "finish" | "cancel"
    distance_m: float | None = None


@dataclass(frozen=True)
class AckAlarm:
    """The operator has seen a critical alarm: it may leave the screens once it has cleared.
    ``code`` None acknowledges every critical alarm waiting (the cab's one "ACK" button)."""

    code: str | None = None


@dataclass(frozen=True)
class SelectSeedLot:
    """Make ``lot`` the active seed lot of ``crop``: its rotation-test fits apply at once
    (``gateway.calibration.lots``)."""

    crop: str
    lot: str


@dataclass(frozen=True)
class RotationTest:
    """A step of paper A's rotation test run from the touchscreen
    (``gateway.app.rotation_test``): ``run`` at duty ``value`` %, the run's shaft ``rpm`` and
    weighed ``mass`` (g, whole machine), ``save`` (``save_confirmed``: a large change the
    operator confirmed), ``cancel``."""

    action: str
    value: float = 0.0


Command = (
    SetRate
    | SetChannelRate
    | Start
    | Stop
    | ZeroTilt
    | CriticalTilt
    | EmptySeed
    | SeedLevelMonitoring
    | CalibrateSpeed
    | AckAlarm
    | SelectSeedLot
    | RotationTest
)


class CommandSink(Protocol):
    def execute(self, command: Command, source: str) -> str:
        """Apply ``command``; return a short confirmation, raise ``CommandError`` if refused.

        A refused command changes nothing.
        """
        ...
