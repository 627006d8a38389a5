"""What the machine takes from the tractor's ISOBUS: the speed it follows and whether it works.

The driver (``drivers.can_bus.IsobusListener``) decodes frames and keeps each source's latest
message with the time its frame arrived. What to make of them is this machine's policy, set
in the ``[isobus]`` table and decided here:

* which speed wins: the first source of ``speed_priority`` (machine-selected, ground-based,
  wheel-based) with a fresh, valid reading, so the machine falls back on its own when the
  tractor stops sending one;
* how old is too old: ``stale_after_s`` (300 ms: ISO 11783-7 sends speed every 100 ms, three
  misses mean it is gone), because a speed that stopped arriving must not keep the meters
  turning;
* when the hitch means "in work": its in-work bits, else its position below
  ``hitch_in_work_below_pct``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final, Protocol

from drivers.can_bus import Heard
from gateway.config.metering import SpeedSource
from protocol import isobus

STALE_AFTER_S: Final = 0.3
DEFAULT_SPEED_PRIORITY: Final[tuple[SpeedSource, ...]] = ("machine_selected", "ground", "wheel")
SOURCE_PGN: Final[dict[str, int]] = {
    "machine_selected": isobus.PGN_MACHINE_SELECTED_SPEED,
    "ground": isobus.PGN_GROUND_SPEED,
    "wheel": isobus.PGN_WHEEL_SPEED,
}


class IsobusReadings(Protocol):
    """What is read from ``drivers.can_bus.IsobusListener``."""

    def latest_speed(self, pgn: int) -> Heard[isobus.SpeedMessage] | None: ...

    def latest_hitch(self) -> Heard[isobus.HitchStatus] | None: ...


@dataclass(frozen=True)
class TractorSpeed:
    source: str
    speed_kmh: float  # 0 when the tractor reports reverse: a seeder never meters backwards
    direction: isobus.Direction
    age_s: float


class TractorInputs:
    """The tractor speed and hitch work state the machine acts on, from the latest readings."""

    def __init__(
        self,
        readings: IsobusReadings,
        *,
        speed_priority: Sequence[str] = DEFAULT_SPEED_PRIORITY,
        stale_after_s: float = STALE_AFTER_S,
        hitch_in_work_below_pct: float | None = None,
    ) -> None:
        unknown = [p for p in speed_priority if p not in SOURCE_PGN]
        if unknown or not speed_priority:
            raise ValueError(
                f"isobus.speed_priority: unknown ISOBUS speed source(s) {unknown}; "
                f"use {list(SOURCE_PGN)}"
            )
        self.readings = readings
        self.speed_priority = tuple(speed_priority)
        self.stale_after_s = stale_after_s
        self.hitch_in_work_below_pct = hitch_in_work_below_pct

    def speed(self, now: float) -> TractorSpeed | None:
        """Best fresh, valid speed in priority order; None if every source is stale/invalid."""
        for source in self.speed_priority:
            heard = self.readings.latest_speed(SOURCE_PGN[source])
            if heard is None:
                continue
            msg, age = heard.message, now - heard.at
            if age > self.stale_after_s or msg.speed_kmh is None:
                continue
            # direction "error"/"n/a" with a valid speed is still used: many tractors send 11
            kmh = 0.0 if msg.direction is isobus.Direction.REVERSE else msg.speed_kmh
            return TractorSpeed(source, kmh, msg.direction, age)
        return None

    def hitch(self, now: float) -> isobus.HitchStatus | None:
        """The rear hitch status if it is fresh."""
        heard = self.readings.latest_hitch()
        if heard is None or now - heard.at > self.stale_after_s:
            return None
        return heard.message

    def hitch_received_at(self) -> float | None:
        """Local time the latest rear hitch message arrived (None: never)."""
        heard = self.readings.latest_hitch()
        return None if heard is None else heard.at

    def working(self, now: float) -> bool | None:
        """In work from the hitch: the in-work bits, else position below the threshold;
        None when the hitch is stale or says neither."""
        h = self.hitch(now)
        if h is None:
            return None
        if h.in_work is isobus.InWork.IN_WORK:
            return True
        if h.in_work is isobus.InWork.OUT_OF_WORK:
            return False
        if self.hitch_in_work_below_pct is not None and h.position_pct is not None:
            return h.position_pct < self.hitch_in_work_below_pct
        return None
