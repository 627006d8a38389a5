"""Remote operation over MQTT goes through the same command path as the touchscreen."""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path

import aiomqtt

from simulator.machine import SimulatedMachine
from tests.helpers import eventually
from tests.integration.conftest import running, steady_drive
from tests.mosquitto import Mosquitto, Subscriber, subscriber

BASE = "sowgate/seeder-01"


async def _send(port: int, name: str, payload: bytes) -> None:
    async with aiomqtt.Client("127.0.0.1", port, identifier="farm-office") as client:
        await client.publish(f"{BASE}/cmd/{name}", payload, qos=1)


async def _ack(sub: Subscriber, name: str, count: int) -> dict[str, object]:
    topic = f"cmd/{name}/ack"
    await eventually(lambda: len(sub.on(topic)) >= count, 10.0, f"ack #{count} on {topic}")
    return dict(json.loads(sub.on(topic)[count - 1]))


async def test_rate_and_start_over_mqtt_reach_the_controller_and_the_screen(
    tmp_path: Path,
) -> None:
    with Mosquitto() as broker:
        async with subscriber(broker.port, BASE) as sub:
            overrides = {
                "mqtt": {"enabled": True, "port": broker.port},
                "commands": {"enabled": ["rate", "start", "stop"]},
                "control": {"crop": "rapeseed", "rate_kg_ha": 6.0},
            }
            machine = SimulatedMachine(drive=steady_drive(), crop="wheat")
            async with running(tmp_path, machine, **overrides) as rig:
                await rig.until(lambda: bool(sub.on("status")), what="online")
                await _send(broker.port, "rate", b'{"crop": "wheat", "rate_kg_ha": 300}')
                ack = await _ack(sub, "rate", 1)
                assert ack["ok"] is False and "120-225" in str(ack["error"])
                assert rig.daemon.controller.crop == "rapeseed"  # refused: nothing changed

                await _send(broker.port, "rate", b'{"crop": "wheat", "rate_kg_ha": 200}')
                assert (await _ack(sub, "rate", 2))["ok"] is True
                assert (rig.daemon.controller.crop, rig.daemon.controller.rate_kg_ha) == (
                    "wheat",
                    200.0,
                )
                assert machine.hmi is not None
                await machine.hmi.wait_text("t_rate", lambda s: s == "200 kg/ha")

                await _send(broker.port, "zero_tilt", b"{}")
                ack = await _ack(sub, "zero_tilt", 1)
                assert ack["ok"] is False and "is disabled" in str(ack["error"])

                await _send(broker.port, "start", b"{}")
                assert (await _ack(sub, "start", 1))["ok"] is True
                await rig.until(
                    lambda: any(
                        json.loads(p).get("work_state") == "seeding" for p in sub.on("state")
                    ),
                    timeout=10.0,
                    what="retained state shows seeding",
                )


async def test_live_speed_calibration_over_mqtt(tmp_path: Path) -> None:
    with Mosquitto() as broker:
        async with subscriber(broker.port, BASE) as sub:
            overrides = {
                "mqtt": {"enabled": True, "port": broker.port},
                "commands": {"enabled": ["speed_cal"]},
            }
            machine = SimulatedMachine(drive=steady_drive(speed_kmh=7.2, standing_s=0.5))
            async with running(tmp_path, machine, **overrides) as rig:
                await rig.until(lambda: bool(sub.on("status")), what="online")
                await rig.until(lambda: machine.pose().speed_kmh > 7.1, what="steady speed")
                await _send(broker.port, "speed_cal", b'{"action": "start"}')
                assert (await _ack(sub, "speed_cal", 1))["ok"] is True
                start_north = machine.pose().north
                await asyncio.sleep(6.0)  # ~12 m at 2 m/s
                driven = machine.pose().north - start_north
                payload = json.dumps({"action": "finish", "distance_m": driven}).encode()
                await _send(broker.port, "speed_cal", payload)
                ack = await _ack(sub, "speed_cal", 2)
                assert ack["ok"] is True, ack
                # the simulated radar is unbiased: the factor is close to 1
                factor = rig.daemon.controller.sources["radar"].correction
                assert abs(factor - 1.0) < 0.08
                # the farm office gets the calibration result in the ack, factor included
                assert re.search(rf"\bradar \d+\.\d m -> x{factor:.4f}\b", str(ack["message"])), ack
                await _send(broker.port, "speed_cal", b'{"action": "finish", "distance_m": 5}')
                ack = await _ack(sub, "speed_cal", 3)
                assert ack["ok"] is False and "not started" in str(ack["error"])


async def test_hostile_commands_are_refused_and_the_farm_link_stays_up(tmp_path: Path) -> None:
    """Issue 11: ``[`` x 2000 on cmd/rate restarted the daemon's MQTT session (an uncaught
    RecursionError), so anyone allowed to publish commands could keep the link down. Each
    hostile payload is now one refused command; the session, and the machine, carry on."""
    hostile: list[tuple[str, bytes, str]] = [
        ("rate", b"[" * 2000, "nested more than"),
        ("whatever", b"[" * 2000, "unknown command 'whatever'"),
        ("rate", b'{"crop": "wheat", "rate_kg_ha": "200"}',
         "rate_kg_ha: must be a number (got string '200')"),
        ("rate", b'{"crop": "wheat", "rate_kg_ha": NaN}', "rate_kg_ha: must be a finite number"),
        ("rate", b'{"crop": "wheat", "rate_kg_ha": 200, "force": true}', "force: unknown field"),
        ("start", b'\xff{"a": ' * 300, "not UTF-8"),
        ("start", b'{"a": ' * 300, "nested more than"),
    ]
    with Mosquitto() as broker:
        async with subscriber(broker.port, BASE) as sub:
            overrides = {
                "mqtt": {"enabled": True, "port": broker.port},
                "commands": {"enabled": ["rate", "start"]},
                "control": {"crop": "rapeseed", "rate_kg_ha": 6.0},
            }
            machine = SimulatedMachine(drive=steady_drive(), crop="wheat")
            async with running(tmp_path, machine, **overrides) as rig:
                await rig.until(lambda: sub.on("status") == [b"online"], what="online")
                link = rig.daemon.parts.mqtt
                for name, payload, expected_error in hostile:
                    count = len(sub.on(f"cmd/{name}/ack")) + 1
                    await _send(broker.port, name, payload)
                    ack = await _ack(sub, name, count)
                    assert ack["ok"] is False and expected_error in str(ack["error"]), ack
                assert rig.daemon.controller.crop == "rapeseed"  # nothing changed
                # the same session still carries commands
                await _send(broker.port, "rate", b'{"crop": "wheat", "rate_kg_ha": 200}')
                assert (await _ack(sub, "rate", 5))["ok"] is True
                assert rig.daemon.controller.rate_kg_ha == 200.0
                assert (link.stats.connects, link.stats.disconnects) == (1, 0)
                assert sub.on("status") == [b"online"]
