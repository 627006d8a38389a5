"""AgOpenGPS in the cab: its speed, work state and sections into the controller and channels,
sowgate's alarms back onto its screen (docs/agopengps.md).

``gateway.metering.agopengps.CabInputs`` is the pure part. ``attach_agopengps`` wires it:
the UDP endpoint (``drivers.agopengps_udp``) hands it each frame, PGN 254's speed goes to the
controller as the ``agopengps`` speed source, the work verdict as the ``agopengps`` work-state
source, and every alarm raised is sent as a PGN 221 text.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any, Protocol

from gateway.config import Settings
from gateway.metering.agopengps import CabInputs
from protocol import agopengps as aog

if TYPE_CHECKING:
    from drivers.agopengps_udp import AgOpenGpsEndpoint
    from gateway.app.parts import Parts
    from gateway.control.controller import Controller
    from gateway.core.alarms import AlarmBoard
    from gateway.core.records import AlarmEvent

log = logging.getLogger(__name__)


class Daemon(Protocol):
    """What this part needs of the daemon (``gateway.app.wiring.Daemon`` is a superset; not
    imported from there, which imports this module)."""

    settings: Settings
    alarms: AlarmBoard
    controller: Controller
    parts: Parts

    def clock(self) -> float: ...

    def add_task(
        self,
        name: str,
        factory: Callable[[], Coroutine[Any, Any, None]],
        *,
        stop_stage: int | None = None,
    ) -> None: ...


OPEN_RETRY_MAX_S = 30.0
STALE_WATCH_S = 0.5


async def open_until_listening(
    endpoint: AgOpenGpsEndpoint, listen: str, alarms: AlarmBoard, first_retry_s: float = 1.0
) -> None:
    """Bind ``listen``, retrying with a growing pause while it cannot be (the port taken by
    another program, the address not up yet) with ``agopengps.unavailable`` raised: the
    daemon runs on with its other sources meanwhile."""
    import asyncio

    from gateway.config.agopengps import split_host_port

    host, port = split_host_port(listen)
    pause = first_retry_s
    while True:
        try:
            await endpoint.open(host, port)
        except OSError as exc:
            if not alarms.is_active("agopengps.unavailable"):
                log.error("AgOpenGPS: cannot listen on %s: %s; retrying", listen, exc)
            alarms.raise_("agopengps.unavailable", f"cannot listen on {listen}: {exc}")
            await asyncio.sleep(pause)
            pause = min(OPEN_RETRY_MAX_S, pause * 2)
            continue
        alarms.clear("agopengps.unavailable")
        log.info("AgOpenGPS: listening on %s", listen)
        return


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
        if cfg.channel_sides:
            daemon.parts.metering.speed_factor = cab.speed_factor
    daemon.parts.agopengps_cab = cab

    def on_alarm(event: AlarmEvent) -> None:
        if event.active:
            endpoint.send_text(f"sowgate: {event.message}", cfg.alarm_text_s)

    daemon.alarms.subscribe(on_alarm)

    async def run() -> None:
        await open_until_listening(endpoint, cfg.listen, daemon.alarms)
        try:
            while True:  # AgOpenGPS frames carry no time: "stale" is the source gone quiet
                await asyncio.sleep(STALE_WATCH_S)
                cab.watch_staleness(daemon.clock())
        finally:
            endpoint.close()

    daemon.add_task("agopengps", run)
