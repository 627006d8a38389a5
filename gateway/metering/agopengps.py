"""What AgOpenGPS's last trusted frames say (sections 1-64, lift, geo-stop, tool speeds) and
what that means for each metering channel and row; pure, every reading stamped with the time
its frame arrived (docs/agopengps.md). Wired by ``gateway.app.agopengps``."""

from __future__ import annotations

import logging

from gateway.config import AgOpenGpsSection
from protocol import agopengps as aog

N_SECTIONS = 64
MIN_CENTRE_SPEED_MPS = 0.3  # below, 229's 0.1 m/s steps make a ratio meaningless


log = logging.getLogger(__name__)


class CabInputs:
    """The latest trusted AgOpenGPS state; every reading carries the time it arrived."""

    def __init__(self, cfg: AgOpenGpsSection) -> None:
        self.cfg = cfg
        self.sections: list[bool] = [False] * N_SECTIONS
        self.hyd_lift = aog.HYD_LIFT_NONE
        self.geo_stop = False
        self.tool_speeds_mps: tuple[float, float] | None = None
        self.speed_kmh: float | None = None
        self.last_t: float | None = None  # any section-bearing frame
        self.stale_spells = 0  # times AgOpenGPS went quiet for stale_after_s
        self._was_fresh = False

    def on_message(self, msg: aog.Message, t: float) -> None:
        if isinstance(msg, aog.SteerData):
            self.sections[:16] = msg.sections
            self.speed_kmh = msg.speed_kmh
        elif isinstance(msg, aog.MachineData):
            self.sections[:16] = msg.sections
            self.hyd_lift, self.geo_stop = msg.hyd_lift, msg.geo_stop
        elif isinstance(msg, aog.Sections64):
            self.sections[:] = msg.sections
            if msg.left_speed_mps is not None and msg.right_speed_mps is not None:
                self.tool_speeds_mps = (msg.left_speed_mps, msg.right_speed_mps)
        else:
            return
        self.last_t = t

    def watch_staleness(self, now: float) -> bool:
        """Count and log AgOpenGPS going quiet and coming back; True while fresh."""
        fresh = self.fresh(now)
        if self._was_fresh and not fresh:
            self.stale_spells += 1
            log.warning("AgOpenGPS silent for %g s: its speed, work state and sections are "
                        "stale, the next sources decide", self.cfg.stale_after_s)
        elif fresh and not self._was_fresh and self.stale_spells:
            log.info("AgOpenGPS frames again")
        self._was_fresh = fresh
        return fresh

    def fresh(self, now: float) -> bool:
        return self.last_t is not None and now - self.last_t <= self.cfg.stale_after_s

    @property
    def working(self) -> bool:
        """Some section on, the lift not up and no geo-stop (AgOpenGPS's "out of bounds")."""
        return any(self.sections) and self.hyd_lift != aog.HYD_LIFT_RAISE and not self.geo_stop

    def channel_on(self, channel: str, now: float) -> bool:
        """A channel mapped to sections meters only while one of them is on; unmapped
        channels, and every channel while AgOpenGPS is stale, follow the work state alone
        (the work-state priority list decides what a lost AgOpenGPS means)."""
        mapped = [i for i, m in enumerate(self.cfg.sections) if m.channel == channel]
        if not mapped or not self.fresh(now):
            return True
        return any(self.sections[i] for i in mapped)

    def rows_off(self, now: float) -> set[int]:
        """Rows (1-based) whose section AgOpenGPS has switched off: not sown."""
        if not self.fresh(now):
            return set()
        return {r for i, m in enumerate(self.cfg.sections) if not self.sections[i] for r in m.rows}

    def speed_factor(self, channel: str, now: float) -> float:
        """The ground speed of the half of the tool ``channel`` feeds over the machine's.

        PGN 229 gives the far-left (L) and far-right (R) tool speeds; across a rigid tool the
        speed varies linearly, so the centre runs at C = (L + R) / 2 and the left half's mean
        speed is (L + C) / 2. The factor is that over C (1.0 on a straight line, unmapped
        channels, a stale AgOpenGPS or a standing tool), so the primary speed source stays the
        one metering follows. Bounded to 0..2: the inner half of a tight curve may stand.
        """
        side = self.cfg.channel_sides.get(channel)
        if side is None or self.tool_speeds_mps is None or not self.fresh(now):
            return 1.0
        left, right = self.tool_speeds_mps
        centre = (left + right) / 2.0
        if centre < MIN_CENTRE_SPEED_MPS:
            return 1.0
        edge = left if side == "left" else right
        return max(0.0, min(2.0, (edge + centre) / 2.0 / centre))

    def hello_sections(self) -> tuple[bool, ...]:
        return tuple(self.sections[:16])
