"""``sowgate run`` with its state directory on a tiny disk that fills up while it sows: no seed
is lost, the operator is told at once (MQTT alarm and state, without the store), and once the
disk has room again every seed reaches the store and the dashboard under contiguous ids."""

from __future__ import annotations

import asyncio
import json
import signal
from pathlib import Path
from typing import Any

import pytest

from tests.helpers import eventually
from tests.integration.test_recording_end_to_end import (
    BASE,
    _spawn,
    all_delivered,
    mqtt_overrides,
    received_after_stop,
    recording_machine,
    undelivered_seeds,
)
from tests.mosquitto import Mosquitto, subscriber
from tests.tiny_disk import fill, grow, may_mount, run_in_mount_namespace, tiny_tmpfs

SOWING_S = 22.0
FULL_FOR_S = 6.0  # how long the disk stays full once the store noticed


def _alarms(messages: list[bytes], code: str) -> list[dict[str, Any]]:
    return [a for a in map(json.loads, messages) if a["code"] == code]


def _last_state(messages: list[bytes]) -> dict[str, Any]:
    return json.loads(messages[-1]) if messages else {}


async def test_a_full_state_disk_loses_no_seed_and_raises_its_alarm_without_the_store(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    if not may_mount():
        run_in_mount_namespace(request)
        return
    state = tmp_path / "state"
    db = state / "records.sqlite3"
    with tiny_tmpfs(state), Mosquitto(persistent=True) as broker:
        async with subscriber(broker.port, BASE) as sub, recording_machine(SOWING_S) as machine:
            config = machine.write_config(tmp_path / "sowgate.toml", **mqtt_overrides(broker.port))
            proc = await _spawn(config, state)
            try:
                await eventually(lambda: len(sub.seed_ids()) > 100, 20.0, "seeds on the broker")
                fill(state)  # the card is full: the next page the store needs is refused
                await eventually(
                    lambda: any(a["id"] == 0 and a["active"]
                                for a in _alarms(sub.on("alarms"), "records.store_failed")),
                    15.0, "records.store_failed published live while the disk is full",
                )
                await eventually(lambda: _last_state(sub.on("state")).get("records_held", 0) > 0,
                                 5.0, "records_held in the state")
                published_while_full = len(sub.seed_ids())
                await asyncio.sleep(FULL_FOR_S)
                assert proc.returncode is None  # the daemon rides it out
                held = _last_state(sub.on("state"))["records_held"]
                assert held > 100  # seeds kept coming and are held, not dropped
                assert len(sub.seed_ids()) <= published_while_full + 500  # none from memory
                grow(state)  # space again
                await eventually(lambda: machine.pose().speed_kmh == 0.0, 30.0, "end of pass")
                await eventually(lambda: all_delivered(db, sub), 20.0, "every stored id")
                await eventually(
                    lambda: [a["active"] for a in _alarms(sub.on("alarms"), "records.store_failed")
                             if a["id"] != 0] == [True, False],
                    10.0, "the alarm's raise and clear stored and published after recovery",
                )
                final = _last_state(sub.on("state"))
                assert final["records_held"] == 0 and final["records_lost"] == 0
                assert not _alarms(sub.on("alarms"), "records.lost")
                proc.send_signal(signal.SIGTERM)
                _, stderr = await asyncio.wait_for(proc.communicate(), 15.0)
                assert proc.returncode == 0, stderr.decode()[-2000:]
            finally:
                if proc.returncode is None:
                    proc.kill()
                    await proc.wait()
            # what the stop stored (the recorder's final flush) was published before the exit
            assert undelivered_seeds(db) == 0
            ids = await received_after_stop(db, sub)
    assert len(ids) > published_while_full + held
    assert sorted(set(sub.seed_ids())) == ids == list(range(1, len(ids) + 1))
