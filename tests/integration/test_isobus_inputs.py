"""Tractor ISOBUS speed and rear-hitch status drive the daemon's control, with fallback."""

from __future__ import annotations

import asyncio
import uuid
from pathlib import Path

import pytest

from drivers.can_bus import CanBus
from drivers.tasks import cancel_and_wait
from gateway.control.rate_model import plan_duty
from gateway.control.work_state import WorkState
from gateway.metering.channels import ChannelStatus
from protocol import isobus
from simulator.can_pid import TractorSimulator
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from tests.integration.conftest import running


async def test_isobus_speed_and_hitch_drive_the_work_state_and_duty(tmp_path: Path) -> None:
    channel = f"isobus-{uuid.uuid4().hex[:8]}"
    # the simulated radar sees a standing machine: only the tractor says we are moving
    machine = SimulatedMachine(drive=Drive(legs=[Leg(600.0, 0.0)], dt=0.05))
    async with CanBus("virtual", channel) as bus:
        tractor = TractorSimulator(bus, speed_kmh=5.0, in_work=isobus.InWork.IN_WORK)
        task = asyncio.create_task(tractor.run(), name="tractor-ecu")
        try:
            overrides = {
                "control": {"start_working": True},
                "speed": {"source": "isobus_then_radar"},
                "isobus": {
                    "enabled": True,
                    "interface": "virtual",
                    "channel": channel,
                    "work_state_source": "hitch",
                },
            }
            async with running(tmp_path, machine, **overrides) as rig:
                await rig.until(lambda: rig.state() is WorkState.SEEDING, what="seeding")
                out = rig.daemon.outputs
                assert out is not None and out.speed_source == "isobus"
                model = rig.daemon.controller.crop_model
                want = plan_duty(rig.daemon.controller.rate_kg_ha, 2.0, 5.0, model).duty_pct
                assert out.motor_pct == pytest.approx(want, abs=0.5)
                # the hitch goes out of work: every output follows the table (turning)
                tractor.in_work = isobus.InWork.OUT_OF_WORK
                await rig.until(lambda: rig.state() is WorkState.TURNING, what="turning")
                # the tractor ECU goes quiet: the radar (standing) takes over
                tractor.silent = True
                await rig.until(
                    lambda: (
                        rig.daemon.outputs is not None
                        and rig.daemon.outputs.speed_source == "radar"
                    ),
                    timeout=6.0,
                    what="fallback to radar",
                )
        finally:
            await cancel_and_wait(task)


async def test_paper_b_drill_without_any_rs485_bus(tmp_path: Path) -> None:
    """rs485.enabled = false: tractor speed and hitch over ISOBUS, a CAN metering channel;
    no radar/inclinometer/PWM polling and none of their 'not answering' alarms."""
    from simulator.can_pid import MeteringControllerSim, MeterPlant

    isobus_channel = f"isobus-{uuid.uuid4().hex[:8]}"
    can_channel = f"meter-{uuid.uuid4().hex[:8]}"
    machine = SimulatedMachine(drive=Drive(legs=[Leg(600.0, 0.0)], dt=0.05))
    async with CanBus("virtual", isobus_channel) as tbus, CanBus("virtual", can_channel) as mbus:
        tractor = TractorSimulator(tbus, speed_kmh=5.0, in_work=isobus.InWork.IN_WORK)
        plant = MeterPlant(grams_per_rev=11.2, outlets=10)
        tasks = [
            asyncio.create_task(tractor.run(), name="tractor-ecu"),
            asyncio.create_task(MeteringControllerSim(mbus, {1: plant}).run(), name="pid"),
        ]
        try:
            overrides = {
                "rs485": {"enabled": False},
                "hmi": {"enabled": False},
                "control": {"start_working": True},
                "speed": {"source": "isobus"},
                "isobus": {"enabled": True, "interface": "virtual", "channel": isobus_channel,
                           "work_state_source": "hitch"},
                "can": {"enabled": True, "interface": "virtual", "channel": can_channel},
                "channel": [{"name": "seed", "product": "wheat", "target_rate_kg_ha": 225.0,
                             "node_id": 1, "grams_per_rev": 11.2, "outlets": 10}],
            }
            async with running(tmp_path, machine, **overrides) as rig:

                def seed() -> ChannelStatus:
                    return rig.daemon.parts.metering.status().channels["seed"]

                await rig.until(lambda: rig.state() is WorkState.SEEDING, what="seeding")
                await rig.until(lambda: (seed().measured_rpm or 0.0) > 10.0, what="turning")
                codes = {a.code for a in rig.daemon.alarms.active}
                assert not {c for c in codes if c.endswith(".unavailable")}, codes
                assert "inclinometer.lost" not in codes
                assert rig.machine.rs485 is not None
                assert rig.daemon.bus.stats == {}  # never polled
                tractor.in_work = isobus.InWork.OUT_OF_WORK
                await rig.until(lambda: seed().target_rpm == 0.0, what="raised -> stop")
        finally:
            for task in tasks:
                await cancel_and_wait(task)
