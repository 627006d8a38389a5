"""AgOpenGPS in the cab, end to end: a fake AgIO on loopback UDP drives the real daemon.

The daemon (with the simulated machine's RS485 radar standing still and two CAN metering
channels on a virtual bus) takes its speed and work state from AgOpenGPS's PGN 254/239/229,
meters only the channel whose section is on, each half of the tool at its own speed in a
curve, answers AgIO's hello, shows its alarms on the AgOpenGPS screen as PGN 221 and falls
back (radar speed; raised, every channel stopped) when the frames stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import uuid
from collections.abc import AsyncIterator
from pathlib import Path

from drivers.can_bus import CanBus
from drivers.tasks import cancel_and_wait
from gateway.control.work_state import WorkState
from gateway.metering.channels import ChannelStatus
from protocol import agopengps as aog
from simulator.can_pid import MeteringControllerSim, MeterPlant
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from tests.integration.conftest import running


class FakeAgIO:
    """What AgIO does on the LAN: broadcasts AgOpenGPS's frames to the module port at 10 Hz and
    receives what modules send (hello replies, PGN 221 texts) on its own port."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = int(self.sock.getsockname()[1])
        self.speed_kmh = 6.0
        self.sections = [True, False] + [False] * 14
        self.tool_speeds_mps = (1.7, 1.7)  # far left, far right: straight ahead
        self.sending = True
        self.received: list[bytes] = []

    async def broadcast(self, to: tuple[str, int]) -> None:
        while True:
            if self.sending:
                self.sock.sendto(aog.encode_steer_data(self.speed_kmh, self.sections), to)
                self.sock.sendto(aog.encode_machine_data(self.speed_kmh, self.sections), to)
                self.sock.sendto(aog.encode_sections_64(self.sections, *self.tool_speeds_mps), to)
            await asyncio.sleep(0.1)

    async def listen(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            self.received.append(await loop.sock_recv(self.sock, 1024))

    def frames(self, pgn: int) -> list[aog.Frame]:
        return [f for f in map(aog.decode_frame, self.received) if f.pgn == pgn]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.asynccontextmanager
async def tasks(*coros: object) -> AsyncIterator[None]:
    started = [asyncio.create_task(c) for c in coros]  # type: ignore[arg-type]
    try:
        yield
    finally:
        for t in started:
            await cancel_and_wait(t)


async def test_agopengps_drives_speed_and_sections_answers_and_falls_back(
    tmp_path: Path,
) -> None:
    can_channel = f"meter-{uuid.uuid4().hex[:8]}"
    listen_port = free_udp_port()
    agio = FakeAgIO()
    machine = SimulatedMachine(  # its radar sees a standing machine
        drive=Drive(legs=[Leg(600.0, 0.0)], dt=0.05),
        settings_overrides={"machine": {"working_width_m": 3.0, "rows": 10}},
    )
    plants = {n: MeterPlant(grams_per_rev=11.2, outlets=10) for n in (1, 2)}
    channels = [
        {"name": side, "product": "wheat", "target_rate_kg_ha": 100.0, "node_id": node,
         "grams_per_rev": 11.2, "outlets": 10}
        for side, node in (("left", 1), ("right", 2))
    ]
    overrides = {
        "control": {"start_working": True},
        "speed": {"source": "agopengps_then_radar"},
        "isobus": {"enabled": False, "work_state_source": "agopengps"},  # no tractor CAN
        "can": {"enabled": True, "interface": "virtual", "channel": can_channel},
        "channel": channels,
        "agopengps": {
            "listen": f"127.0.0.1:{listen_port}",
            "agio": f"127.0.0.1:{agio.port}",
            "sections": [{"channel": "left", "rows": [1, 2, 3, 4, 5]},
                         {"channel": "right", "rows": [6, 7, 8, 9, 10]}],
            "channel_sides": {"left": "left", "right": "right"},
        },
    }
    async with CanBus("virtual", can_channel) as bus, tasks(
        MeteringControllerSim(bus, plants).run(),
        agio.broadcast(("127.0.0.1", listen_port)),
        agio.listen(),
    ), running(tmp_path, machine, **overrides) as rig:
        metering = rig.daemon.parts.metering
        assert metering is not None

        def ch(name: str) -> ChannelStatus:
            return metering.status().channels[name]

        # AgOpenGPS's speed meters, only section 1's channel turns
        await rig.until(lambda: rig.state() is WorkState.SEEDING, what="seeding")
        out = rig.daemon.outputs
        assert out is not None and out.speed_source == "agopengps"
        assert out.speed_kmh is not None and abs(out.speed_kmh - 6.0) < 0.05
        await rig.until(lambda: (ch("left").measured_rpm or 0.0) > 5.0, what="left turning")
        assert ch("right").target_rpm == 0.0
        cab = rig.daemon.parts.agopengps_cab
        assert cab is not None and cab.rows_off(rig.daemon.clock()) == {6, 7, 8, 9, 10}

        # the speed follows AgOpenGPS; section 2 on starts the right channel
        left_at_6 = ch("left").target_rpm  # straight ahead: the tool speeds change nothing
        agio.speed_kmh, agio.sections[1] = 9.0, True
        await rig.until(lambda: ch("right").target_rpm > 0.0, what="right started")
        await rig.until(lambda: ch("left").target_rpm > left_at_6 * 1.3, what="left faster")

        # a left-hand curve (PGN 229: far left 1.0 m/s, far right 3.0 m/s): the right half
        # runs at 1.25x the machine's speed, the left at 0.75x, and so do their shafts
        agio.tool_speeds_mps = (1.0, 3.0)
        await rig.until(
            lambda: abs(ch("right").target_rpm / max(ch("left").target_rpm, 1e-9) - 5 / 3)
            < 0.01,
            what="curve compensation",
        )

        # the hello is answered with PGN 123 carrying the sections
        agio.sock.sendto(aog.hello_from_agio(), ("127.0.0.1", listen_port))
        await rig.until(lambda: bool(agio.frames(123)), what="hello reply")
        assert agio.frames(123)[-1].data[0] == 0b11

        # all sections off: not working, every channel stops
        agio.sections[:2] = [False, False]
        await rig.until(lambda: rig.state() is WorkState.TURNING, what="not working")
        await rig.until(lambda: ch("left").target_rpm == 0.0, what="left stopped")

        # a stranger on the LAN floods "all sections on at 20 km/h": nothing moves
        endpoint = rig.daemon.parts.agopengps
        assert endpoint is not None
        stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        stranger.bind(("127.0.0.2", 0))
        with stranger:
            for burst in range(1, 6):
                for _ in range(100):
                    stranger.sendto(aog.encode_steer_data(20.0, [True] * 16),
                                    ("127.0.0.1", listen_port))
                await rig.until(lambda n=burst: endpoint.rejected["untrusted_sender"] == n * 100,
                                what=f"stranger burst {burst} dropped")
        out = rig.daemon.outputs
        assert out is not None and out.speed_kmh is not None and abs(out.speed_kmh - 9.0) < 0.05
        assert rig.state() is WorkState.TURNING
        assert ch("left").target_rpm == 0.0 and ch("right").target_rpm == 0.0

        # AgOpenGPS goes quiet: radar speed, raised (critical alarm shown on its screen)
        agio.sections[:2] = [True, True]
        await rig.until(lambda: rig.state() is WorkState.SEEDING, what="seeding again")
        agio.sending = False
        await rig.until(
            lambda: rig.daemon.outputs is not None
            and rig.daemon.outputs.speed_source == "radar",
            timeout=15.0, what="fallback to the radar",
        )
        await rig.until(lambda: rig.daemon.alarms.is_active("agopengps.lost"), what="lost")
        await rig.until(lambda: cab.stale_spells == 1, what="the silence counted")
        await rig.until(lambda: ch("left").target_rpm == 0.0 and ch("right").target_rpm == 0.0,
                        what="every channel stopped")
        await rig.until(
            lambda: any(b"AgOpenGPS" in f.data[2:] for f in agio.frames(221)),
            what="the alarm as a PGN 221 text",
        )
        assert dict(endpoint.rejected) == {"untrusted_sender": 500}
