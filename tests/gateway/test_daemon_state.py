"""What the daemon reports as its state: every device a dashboard must see go missing."""

from __future__ import annotations

from pathlib import Path

from gateway.config import parse_config
from gateway.daemon import Daemon
from gateway.optional_parts import state_payload


def test_state_reports_the_screen_and_the_seed_sensors_as_devices(tmp_path: Path) -> None:
    """They used to be absent: a dead screen or seed-tube module was invisible in `state`."""
    settings = parse_config({"gnss": {"enabled": True}, "seed_sensors": {"enabled": True},
                             "mqtt": {"enabled": True}})
    daemon = Daemon(settings, tmp_path / "state")
    try:
        devices = state_payload(daemon).devices
        # nothing opened yet: each is listed, and as not answering
        assert devices == {"gnss": False, "hmi": False, "seed_sensors": False}
        daemon.components["seed_sensors"]._connected = True  # what run() sets once open
        assert state_payload(daemon).devices["seed_sensors"] is True
    finally:
        for close in daemon.closers:
            close()


def test_devices_not_configured_are_not_listed(tmp_path: Path) -> None:
    daemon = Daemon(parse_config({"hmi": {"enabled": False}}), tmp_path / "state")
    assert "hmi" not in daemon.snapshot()["devices"]
    assert "seed_sensors" not in daemon.snapshot()["devices"]
