"""AgOpenGPS in the cab: its speed, work state and sections into the controller and channels,
sowgate's alarms back onto its screen (docs/agopengps.md).

``CabInputs`` is the pure part: what the last trusted frames said (sections 1-64, lift,
geo-stop, tool speeds) and what that means for each channel. ``attach_agopengps`` wires it:
the UDP endpoint (``drivers.agopengps_udp``) hands it each frame, PGN 254's speed goes to the
controller as the ``agopengps`` speed source, the work verdict as the ``agopengps`` work-state
source, and every alarm raised is sent as a PGN 221 text.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from gateway.config import AgOpenGpsSection
from protocol import agopengps as aog

if TYPE_CHECKING:
    from gateway.app.wiring import Daemon
    from gateway.core.records import AlarmEvent

log = logging.getLogger(__name__)

N_SECTIONS = 64


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

    def hello_sections(self) -> tuple[bool, ...]:
        return tuple(self.sections[:16])


def attach_agopengps(daemon: Daemon) -> None:
    """The UDP endpoint, the controller feed and the alarm texts (``[agopengps]`` enabled)."""
    import asyncio

    from drivers.agopengps_udp import AgOpenGpsEndpoint
    from gateway.config.agopengps import split_host_port

    cfg = daemon.settings.agopengps
    cab = CabInputs(cfg)

    def on_message(msg: aog.Message, t: float) -> None:
        cab.on_message(msg, t)
        if isinstance(msg, aog.SteerData):
            daemon.controller.on_speed("agopengps", msg.speed_kmh, t)
        if isinstance(msg, aog.SteerData | aog.MachineData | aog.Sections64):
            daemon.controller.on_agopengps_work(cab.working, t)

    endpoint = AgOpenGpsEndpoint(
        on_message,
        agio=split_host_port(cfg.agio) if cfg.agio else None,
        stale_after_s=cfg.stale_after_s,
        max_frames_per_s=cfg.max_frames_per_s,
        hello_sections=cab.hello_sections,
        clock=daemon.clock,
    )
    daemon.parts.agopengps = endpoint
    if daemon.parts.metering is not None:
        daemon.parts.metering.channel_gate = cab.channel_on
    daemon.parts.agopengps_cab = cab

    def on_alarm(event: AlarmEvent) -> None:
        if event.active:
            endpoint.send_text(f"sowgate: {event.message}", cfg.alarm_text_s)

    daemon.alarms.subscribe(on_alarm)

    async def run() -> None:
        host, port = split_host_port(cfg.listen)
        await endpoint.open(host, port)
        log.info("AgOpenGPS: listening on %s", cfg.listen)
        try:
            await asyncio.Event().wait()
        finally:
            endpoint.close()

    daemon.add_task("agopengps", run)
