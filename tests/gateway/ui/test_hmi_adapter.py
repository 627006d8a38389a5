"""The screen as the daemon builds it from ``[hmi]``: the config keys must reach the link."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from drivers.hmi_link import HmiLink
from drivers.tasks import cancel_and_wait
from gateway.app.daemon import Daemon
from gateway.config import parse_config
from gateway.core.commands import AckAlarm
from gateway.state import HopperState
from gateway.ui.touchscreen import hopper_text
from protocol import hmi
from simulator.pty_link import PtyPair
from tests.helpers import eventually


@contextlib.asynccontextmanager
async def open_link(hmi: dict[str, Any], tmp_path: Path) -> AsyncIterator[HmiLink]:
    """The screen link the daemon builds from ``[hmi]``, running and open for the block."""
    daemon = Daemon(parse_config({"hmi": hmi}), tmp_path / "state")
    assert daemon.hmi is not None
    link = daemon.hmi.link
    task = asyncio.create_task(link.run())
    try:
        await eventually(lambda: link.available, what="the HMI port to open")
        yield link
    finally:
        await cancel_and_wait(task)


async def test_hmi_write_timeout_from_the_config_is_what_the_link_waits(tmp_path: Path) -> None:
    """``hmi.write_timeout_s`` was accepted but the link kept its built-in 0.5 s."""
    with PtyPair() as pair:  # nobody reads the screen's end: every write waits it out
        hmi = {"port": pair.device_path, "write_timeout_s": 2.0, "reconnect_max_s": 1.0}
        async with open_link(hmi, tmp_path) as link:
            page = {f"t{i}": "x" * 250 for i in range(3000)}  # far more than a pty buffers
            started = time.monotonic()
            await link.show_many(page)
            waited = time.monotonic() - started
    assert 1.8 <= waited < 4.0


def test_the_alarm_line_shows_the_most_severe_alarm_not_the_oldest(tmp_path: Path) -> None:
    """A full disk (critical) must not hide behind an older warning on the one alarm line."""
    with PtyPair() as pair:
        daemon = Daemon(parse_config({"hmi": {"port": pair.device_path}}), tmp_path / "state")
        assert daemon.hmi is not None
        line = daemon.settings.hmi.objects.alarm
        daemon.alarms.raise_("gnss.not_rtk_fixed", "GNSS fix is rtk_float", "warning")
        assert daemon.hmi.screen_texts()[line] == "GNSS fix is rtk_float"
        daemon.alarms.raise_("records.store_failed", "record store cannot write", "critical")
        daemon.alarms.raise_("gnss.heading_invalid", "no dual-antenna heading", "info")
        assert daemon.hmi.screen_texts()[line] == "record store cannot write"
        daemon.alarms.clear("records.store_failed")
        # a critical alarm keeps the line, cleared, until the operator acknowledges it
        assert daemon.hmi.screen_texts()[line] == (
            "cleared, acknowledge: record store cannot write"
        )
        # the alarm line's ACK button (F=07) acknowledges it, as cmd/ack_alarm does
        daemon.hmi.on_event(hmi.AckAlarm())
        assert daemon.alarms.unacknowledged == []
        assert daemon.hmi.last_message == "acknowledged: records.store_failed"
        assert daemon.hmi.screen_texts()[line] == "GNSS fix is rtk_float"
        daemon.alarms.raise_("records.store_failed", "record store cannot write", "critical")
        assert daemon.execute(AckAlarm("records.store_failed"), "mqtt") == (
            "acknowledged: records.store_failed"
        )


async def test_a_storm_of_bad_frames_costs_a_few_log_lines_and_is_counted_per_reason(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Garbage on the touchscreen line logged one warning per frame (8 239 in 150 s)."""
    from simulator.hmi_peer import HmiPeer

    caplog.set_level(logging.INFO)
    async with HmiPeer() as screen, open_link({"port": screen.device_path}, tmp_path) as link:
        bad_frames = 500
        screen.send_raw(b"\x55\x55\x0a\x00\x00\x00\x0d\x0a" * bad_frames)
        screen.send_raw(b"\x55\x55\x05\x07\x00\x00\x0d\x0a" * 3)  # seed-level flag 7
        await eventually(lambda: link.stats.rejected >= bad_frames + 3,
                         what="every bad frame")
    assert link.stats.rejected_by_reason == {"unknown_function": bad_frames, "bad_field": 3}
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert 1 <= len(warnings) <= 4, [r.getMessage() for r in warnings]


def test_the_hopper_line_is_written_only_on_a_machine_with_a_hopper_scale(tmp_path: Path) -> None:
    with PtyPair() as pair:
        plain = Daemon(parse_config({"hmi": {"port": pair.device_path}}), tmp_path / "a")
        assert plain.hmi is not None
        assert "t_hopper" not in plain.hmi.screen_texts()  # a screen without the object
        daemon = Daemon(parse_config({"hmi": {"port": pair.device_path}, "hopper_scale": {}}),
                        tmp_path / "b")
        assert daemon.hmi is not None and daemon.controller.hopper is not None
        assert daemon.hmi.screen_texts()["t_hopper"] == "-- kg ~x1.000"  # nothing known yet
        hopper = daemon.controller.hopper
        hopper.on_weight(412.4, daemon.clock())
        hopper.tick(daemon.clock(), q_model_g_min=3000.0, seeding=True, speed_kmh=5.0,
                    modelled=True)
        # 412 kg at 3 kg/min; "~": the correction is not applied yet (too little evidence)
        assert daemon.hmi.screen_texts()["t_hopper"] == "412 kg 2.3 h ~x1.000"


def test_the_hopper_line_shows_an_applied_correction_and_minutes_near_empty() -> None:
    state = HopperState(mass_kg=61.7, time_to_empty_min=19.4, discharge_correction=1.0791,
                        correction_estimate=1.08, correction_standard_error=0.006,
                        correction_applied=True, scale_sigma_kg=2.0, windows=5, refills=0)
    assert hopper_text(state) == "62 kg 19 min x1.079"
