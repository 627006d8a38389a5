"""The dashboard's MQTT session against a real mosquitto and the daemon's real MQTT link: the
same ``[mqtt]`` settings (TLS, client certificate, password file) reach the same broker, a lost
broker is noticed and left behind, and commands go only where they can be executed."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from drivers.backoff import Backoff
from gateway.config import Settings, parse_config
from gateway.dashboard.model import Fleet, MachineView
from gateway.dashboard.subscriber import CommandRefused, DashboardSubscriber
from tests.gateway.link.test_mqtt import MACHINE, drops, make_settings, running_link
from tests.gateway.link.test_mqtt_tls import Pki, pki, tls_broker, tls_settings
from tests.helpers import eventually
from tests.mosquitto import Mosquitto

__all__ = ["pki", "tls_broker"]  # fixtures, used by name


@contextlib.asynccontextmanager
async def dashboard(settings: Settings) -> AsyncIterator[tuple[Fleet, DashboardSubscriber]]:
    fleet = Fleet(settings.mqtt.topic_prefix)
    sub = DashboardSubscriber(settings, fleet, backoff=Backoff(initial_s=0.1, cap_s=0.5))
    task = asyncio.create_task(sub.run(), name="test-dashboard-mqtt")
    try:
        yield fleet, sub
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_over_tls_with_the_daemons_credentials_every_seed_arrives_once(
    tls_broker: Mosquitto, pki: Pki, tmp_path: Path
) -> None:
    settings = tls_settings(tls_broker.port, pki, ca=pki.ca, password_file=pki.password_file)
    async with dashboard(settings) as (fleet, _sub):
        await eventually(lambda: fleet.broker_connected, what="dashboard connected over TLS")
        async with running_link(settings, tmp_path / "r.db") as run:
            run.store.add_seeds(drops(600))
            run.store.flush()
            await eventually(lambda: run.store.backlog() == 0, what="outbox drained")
            view = await _machine(fleet)
            await eventually(lambda: view.seed_count == 600, what="600 seeds on the dashboard")
            assert view.status == "online" and view.duplicates == 0


async def test_a_lost_broker_is_reported_and_the_session_resumes_without_duplicates(
    tmp_path: Path,
) -> None:
    with Mosquitto(persistent=True) as broker:
        settings = make_settings(broker.port)
        async with dashboard(settings) as (fleet, _sub), running_link(
            settings, tmp_path / "r.db"
        ) as run:
            await eventually(lambda: fleet.broker_connected, what="connected")
            run.store.add_seeds(drops(300))
            run.store.flush()
            view = await _machine(fleet)
            await eventually(lambda: view.seed_count == 300, what="first 300 seeds")
            broker.stop()
            await eventually(lambda: not fleet.broker_connected, what="broker lost noticed")
            assert "127.0.0.1" in fleet.broker_error
            run.store.add_seeds(drops(500))  # recorded meanwhile, waiting in the outbox
            run.store.flush()
            broker.start()
            await eventually(lambda: fleet.broker_connected, what="reconnected")
            await eventually(lambda: view.seed_count == 800, what="every seed, once")
            assert sorted(view.seen) == list(range(1, 801))


async def test_commands_go_only_to_a_machine_online_and_only_if_enabled(tmp_path: Path) -> None:
    with Mosquitto() as broker:
        settings = parse_config({
            "machine": {"id": MACHINE},
            "mqtt": {"enabled": True, "port": broker.port},
            "commands": {"enabled": ["stop"]},
        })
        async with dashboard(settings) as (fleet, sub):
            await eventually(lambda: fleet.broker_connected, what="connected")
            with pytest.raises(CommandRefused, match="unknown machine"):
                await sub.send_command(MACHINE, "stop", {})
            fleet.handle(f"sowgate/{MACHINE}/status", b"offline")
            with pytest.raises(CommandRefused, match="offline"):
                await sub.send_command(MACHINE, "stop", {})
            with pytest.raises(CommandRefused, match="not enabled"):
                await sub.send_command(MACHINE, "start", {})
            async with running_link(make_settings(broker.port, enabled=["stop"]),
                                    tmp_path / "r.db") as run:
                await eventually(lambda: fleet.machines[MACHINE].status == "online",
                                 what="machine online")
                request_id = await sub.send_command(MACHINE, "stop", {})
                await eventually(lambda: "stop" in fleet.machines[MACHINE].acks, what="the ack")
                ack = fleet.machines[MACHINE].acks["stop"]
                assert ack["request_id"] == request_id and ack["ok"] is True
                assert run.link.stats.commands_ok == 1


async def _machine(fleet: Fleet) -> MachineView:
    await eventually(lambda: MACHINE in fleet.machines, what="the machine seen")
    return fleet.machines[MACHINE]
