"""The real daemon on the simulated planter: recording alarms stay quiet while all is well,
and a receiver that vanishes mid-field is named in the alarms at once."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import eventually
from tests.integration.conftest import running
from tests.integration.test_recording_end_to_end import recording_machine

RECORDING_ALARMS = {
    "gnss.unavailable", "gnss.not_rtk_fixed", "gnss.heading_invalid",
    "seed_sensors.unavailable", "records.store_failed", "records.lost",
}


async def test_no_recording_alarm_while_sowing_and_one_when_the_receiver_is_unplugged(
    tmp_path: Path,
) -> None:
    async with running(tmp_path, recording_machine(30.0), control={"start_working": True}) as rig:
        tubes = rig.machine.seed_tubes
        await eventually(lambda: len(tubes.truth) >= 100, 20.0, "100 seeds dropped")
        active = {a.code for a in rig.daemon.alarms.active}
        assert not active & RECORDING_ALARMS, active
        rig.machine.gnss.unplug()
        await eventually(
            lambda: rig.daemon.alarms.is_active("gnss.unavailable"), 10.0, "the GNSS alarm"
        )
        (alarm,) = [a for a in rig.daemon.alarms.active if a.code == "gnss.unavailable"]
        assert "seed positions are estimates" in alarm.message
        assert not rig.daemon.alarms.is_active("seed_sensors.unavailable")
        assert not rig.task.done()  # the daemon keeps sowing and recording
