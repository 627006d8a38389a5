"""The operator switches seed lots from the touchscreen or the farm office: that lot's
rotation-test fits drive the meter at once, the state says which lot is active, and the
choice survives a restart."""

from __future__ import annotations

import json
from pathlib import Path

import aiomqtt
import pytest

from gateway.calibration import fits as cal
from simulator.machine import SimulatedMachine
from tests.helpers import eventually
from tests.integration.conftest import running, steady_drive
from tests.mosquitto import Mosquitto, subscriber

BASE = "sowgate/seeder-01"
SLOPES = {"default": 0.6671 * 1.05, "2026-B": 0.6671 * 0.95}


def save_wheat_lots(state: Path) -> None:
    store = cal.CalibrationStore(state)
    for lot, slope in SLOPES.items():
        key = "rotation.wheat" if lot == "default" else f"rotation.wheat@{lot}"
        store.save(key, cal.to_entry(
            {"motor": {"slope": slope, "intercept": -19.8309, "r2": 1.0, "residuals": []},
             "meter": {"a": -0.644, "b": 132.212, "c": -398.316, "r2": 1.0, "residuals": []},
             "omega_range": [20.0, 45.0]},
            channel="wheat", crop="wheat", seed_lot=lot, model="paper_a"))


async def test_the_touchscreen_switches_the_seed_lot_and_it_survives_a_restart(
    tmp_path: Path,
) -> None:
    state = tmp_path / "state"
    save_wheat_lots(state)
    overrides = {"control": {"crop": "wheat"}, "hmi": {"objects": {"lot": "t_lot"}}}
    machine = SimulatedMachine(drive=steady_drive(), crop="wheat")
    async with running(tmp_path, machine, **overrides) as rig:
        hmi = machine.hmi
        assert hmi is not None
        controller = rig.daemon.controller
        assert controller.crop_model.motor_slope == pytest.approx(SLOPES["default"])
        await hmi.wait_text("t_lot", lambda s: s == "0 default")
        hmi.select_seed_lot(2, 5)  # wheat, a lot number the list does not have
        await hmi.wait_text("t_msg", lambda s: "no seed lot 5" in s and "1 2026-B" in s)
        assert rig.daemon.state().seed_lot == "default"
        hmi.select_seed_lot(2, 1)  # wheat, lot 1 = 2026-B
        await hmi.wait_text("t_msg", lambda s: s.startswith("wheat: seed lot 2026-B"))
        assert controller.crop_model.motor_slope == pytest.approx(SLOPES["2026-B"])
        assert rig.daemon.state().seed_lot == "2026-B"
        await hmi.wait_text("t_lot", lambda s: s == "1 2026-B")
        await rig.stop()
    machine = SimulatedMachine(drive=steady_drive(), crop="wheat")
    async with running(tmp_path, machine, **overrides) as rig:
        assert rig.daemon.state().seed_lot == "2026-B"
        assert rig.daemon.controller.crop_model.motor_slope == pytest.approx(SLOPES["2026-B"])
        entry = rig.daemon.live_calibration.active_rotation("wheat")
        assert entry is not None and (entry["crop"], entry["seed_lot"]) == ("wheat", "2026-B")


async def test_the_farm_office_switches_the_seed_lot_over_mqtt(tmp_path: Path) -> None:
    save_wheat_lots(tmp_path / "state")
    with Mosquitto() as broker:
        async with subscriber(broker.port, BASE) as sub:
            overrides = {
                "mqtt": {"enabled": True, "port": broker.port},
                "commands": {"enabled": ["seed_lot"]},
                "control": {"crop": "wheat"},
            }
            machine = SimulatedMachine(drive=steady_drive(), crop="wheat")
            async with running(tmp_path, machine, **overrides) as rig:
                await rig.until(lambda: bool(sub.on("status")), what="online")

                async def send(payload: bytes) -> dict[str, object]:
                    count = len(sub.on("cmd/seed_lot/ack")) + 1
                    async with aiomqtt.Client("127.0.0.1", broker.port,
                                              identifier="farm-office") as client:
                        await client.publish(f"{BASE}/cmd/seed_lot", payload, qos=1)
                    await eventually(lambda: len(sub.on("cmd/seed_lot/ack")) >= count, 10.0,
                                     "the ack")
                    return dict(json.loads(sub.on("cmd/seed_lot/ack")[count - 1]))

                ack = await send(b'{"crop": "wheat", "lot": "2026-C"}')
                assert ack["ok"] is False and "default, 2026-B" in str(ack["error"])
                ack = await send(b'{"crop": "wheat", "lot": 2}')
                assert ack["ok"] is False and "lot" in str(ack["error"])
                ack = await send(b'{"crop": "wheat", "lot": "2026-B"}')
                assert ack["ok"] is True and "wheat: seed lot 2026-B" in str(ack["message"])
                assert rig.daemon.controller.crop_model.motor_slope == pytest.approx(
                    SLOPES["2026-B"])
                await rig.until(
                    lambda: any(json.loads(p).get("seed_lot") == "2026-B"
                                for p in sub.on("state")),
                    what="the state payload says 2026-B",
                )
                last = json.loads(sub.on("state")[-1])
                assert last["seed_lots"] == {"wheat": "2026-B"}
