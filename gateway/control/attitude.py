"""Is the implement raised or working? Paper A's critical-angle rule, made robust.

Paper A zeroes the inclinometer on level ground and calls the implement raised when the zeroed
angle is at or above the critical angle φ = 0°. Its own Table 5 shows the flaw: a sensor offset
of 0.13–0.15° made a level implement read +0.15° and count as raised. Here raising needs the
angle to clear φ by the hysteresis band, and lowering needs it to fall back below φ, so offset
and vibration around φ cannot flip the state.
"""

from __future__ import annotations

from gateway.control.speed import Hysteresis


def zeroed_tilt(raw_deg: float, zero_offset_deg: float) -> float:
    """Tilt relative to the level-ground reading, wrapped to (-180, 180]."""
    d = (raw_deg - zero_offset_deg + 180.0) % 360.0 - 180.0
    return 180.0 if d == -180.0 else d


class Attitude:
    def __init__(self, critical_angle_deg: float, hysteresis_deg: float) -> None:
        self._band = Hysteresis(critical_angle_deg + hysteresis_deg, critical_angle_deg)

    def update(self, tilt_deg: float) -> bool:
        """Feed a zeroed tilt; returns True when raised."""
        return self._band.update(tilt_deg)

    @property
    def raised(self) -> bool | None:
        return self._band.state

    def forget(self) -> None:
        """Sensor lost: the next reading decides afresh."""
        self._band.state = None
