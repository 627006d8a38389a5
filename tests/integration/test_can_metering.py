"""Paper B's channels driven by the daemon over a (virtual) CAN bus, with the work state from
the RS485 machine: seeding meters every channel at its rate, lifting stops them all."""

from __future__ import annotations

import asyncio
import contextlib
import uuid
from pathlib import Path

import pytest

from drivers.can_bus import CanBus
from gateway.metering.channels import target_shaft_rpm
from simulator.can_pid import MeteringControllerSim, MeterPlant
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from tests.integration.conftest import running


async def test_channels_follow_speed_and_all_stop_when_raised(tmp_path: Path) -> None:
    can_channel = f"sowgate-{uuid.uuid4().hex[:8]}"
    drive = Drive(legs=[Leg(0.5, 0.0), Leg(9.0, 5.0), Leg(600.0, 5.0, raised=True)], dt=0.02)
    plants = {1: MeterPlant(grams_per_rev=16.97), 2: MeterPlant(grams_per_rev=11.2)}
    channels = [
        {
            "name": "shallow",
            "product": "fertiliser",
            "target_rate_kg_ha": 150.0,
            "node_id": 1,
            "grams_per_rev": 16.97,
        },
        {
            "name": "seed",
            "product": "wheat",
            "target_rate_kg_ha": 225.0,
            "node_id": 2,
            "grams_per_rev": 11.2,
        },
    ]
    async with CanBus("virtual", can_channel) as bus:
        sim = MeteringControllerSim(bus, plants)
        sim_task = asyncio.create_task(sim.run(), name="can-pid-sim")
        try:
            async with running(
                tmp_path,
                SimulatedMachine(drive=drive),
                control={"start_working": True},
                can={"enabled": True, "interface": "virtual", "channel": can_channel},
                channel=channels,
            ) as rig:
                await rig.until(
                    lambda: plants[1].rpm > 1.0 and plants[2].rpm > 1.0,
                    timeout=10.0,
                    what="both meters turning",
                )
                out = rig.daemon.outputs
                assert out is not None and out.speed_kmh is not None
                want = target_shaft_rpm(225.0, out.speed_kmh, 2.0, 11.2)
                await rig.until(
                    lambda: plants[2].rpm == pytest.approx(want, rel=0.1),
                    timeout=5.0,
                    what=f"seed shaft near {want:.1f} r/min",
                )
                await rig.until(
                    lambda: plants[1].target_rpm == 0.0 and plants[2].target_rpm == 0.0,
                    timeout=12.0,
                    what="every channel stopped after lifting",
                )
                assert not any(a.code.startswith("channel.") for a in rig.daemon.alarms.active)
        finally:
            sim_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sim_task
