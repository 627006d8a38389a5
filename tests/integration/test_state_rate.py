"""The daemon publishes its state at the documented rate while seeding, not every control tick."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from gateway.link.payloads import STATE_DECIMALS
from simulator.machine import SimulatedMachine
from tests.integration.conftest import metering, steady_drive
from tests.mosquitto import Mosquitto, subscriber

BASE = "sowgate/seeder-01"


async def test_steady_seeding_publishes_the_state_at_state_hz_with_rounded_values(
    tmp_path: Path,
) -> None:
    """Issue 14: 86 state messages in 29 s at a documented 1 Hz, with 5.999999999999997 in
    them. Over 4 s of steady seeding (speed and duty change on every 3 Hz tick) the state
    now goes out about once a second, every value at its sensor's resolution."""
    with Mosquitto() as broker:
        async with subscriber(broker.port, BASE) as sub:
            machine = SimulatedMachine(drive=steady_drive(speed_kmh=8.0, standing_s=0.5))
            overrides = {"mqtt": {"enabled": True, "port": broker.port, "state_hz": 1}}
            async with metering(tmp_path, machine, **overrides) as (rig, _sim):
                def seeding() -> bool:
                    states = sub.on("state")
                    return bool(states) and json.loads(states[-1])["work_state"] == "seeding"

                await rig.until(seeding, timeout=10.0, what="the state says seeding")
                before = len(sub.on("state"))
                await asyncio.sleep(4.0)
                during = [json.loads(p) for p in sub.on("state")[before:]]
    work_states = {s["work_state"] for s in during}
    assert work_states == {"seeding"}
    # at 1 Hz: 4 periodic messages (5 at a boundary), plus at most a couple for an alarm that
    # came or went; every tick (3 Hz) would be 12
    assert 3 <= len(during) <= 7, [s["alarms"] for s in during]
    for state in during:
        for key, decimals in STATE_DECIMALS.items():
            value = state[key]
            assert value is None or round(value, decimals) == value, (key, value)
