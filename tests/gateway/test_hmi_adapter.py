"""The screen as the daemon builds it from ``[hmi]``: the config keys must reach the link."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from drivers.tasks import cancel_and_wait
from gateway.config import parse_config
from gateway.daemon import Daemon
from simulator.pty_link import PtyPair


async def test_hmi_write_timeout_from_the_config_is_what_the_link_waits(tmp_path: Path) -> None:
    """``hmi.write_timeout_s`` was accepted but the link kept its built-in 0.5 s."""
    with PtyPair() as pair:  # nobody reads the screen's end: every write waits it out
        settings = parse_config(
            {"hmi": {"port": pair.device_path, "write_timeout_s": 2.0, "reconnect_max_s": 1.0}}
        )
        daemon = Daemon(settings, tmp_path / "state")
        assert daemon.hmi is not None
        link = daemon.hmi.link
        task = asyncio.create_task(link.run())
        try:
            deadline = time.monotonic() + 5.0
            while not link.available:
                assert time.monotonic() < deadline, "HMI port never opened"
                await asyncio.sleep(0.02)
            page = {f"t{i}": "x" * 250 for i in range(3000)}  # far more than a pty buffers
            started = time.monotonic()
            await link.show_many(page)
            waited = time.monotonic() - started
        finally:
            await cancel_and_wait(task)
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
        assert daemon.hmi.screen_texts()[line] == "GNSS fix is rtk_float"
