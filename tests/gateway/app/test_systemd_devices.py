"""`sowgate check-config --systemd-device-allow`: the drop-in that narrows sowgate.service's
device classes to the configured ports, and systemd credentials in check-config.

The drop-in is proven under a real systemd by `make system-test` (a ttyS the config does not
name refused with EPERM from the running service's device cgroup); here: its content.
"""

from __future__ import annotations

import os
import pty
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.app.systemd_devices import configured_devices, device_allow_dropin
from gateway.config import parse_config
from gateway.config.startup import credential_elsewhere, credential_notes, dashboard_problems

REPO = Path(__file__).resolve().parents[3]


def allowed(text: str) -> list[str]:
    return [ln.split("=", 1)[1] for ln in text.splitlines() if ln.startswith("DeviceAllow=")]


def test_the_configured_ports_replace_the_unit_classes(tmp_path: Path) -> None:
    # a board UART that exists (a pty stands in: not a USB adapter) and an absent adapter
    leader, follower = pty.openpty()
    try:
        board = os.ttyname(follower)
        settings = parse_config({
            "rs485": {"port": board}, "hmi": {"enabled": False},
            "gnss": {"enabled": True, "port": str(tmp_path / "sowgate-gnss")},
            "seed_sensors": {"enabled": False},
        })
        assert configured_devices(settings) == [
            ("rs485.port", board), ("gnss.port", str(tmp_path / "sowgate-gnss"))]
        text = device_allow_dropin(settings, "/etc/sowgate/sowgate.toml")
    finally:
        os.close(leader)
        os.close(follower)
    lines = text.splitlines()
    assert lines.index("[Service]") < lines.index("DeviceAllow=")  # the reset comes first
    # the absent one may be a USB adapter: the USB serial classes stay, ttyS and the rest go
    assert allowed(text) == ["", f"{board} rw", f"{tmp_path / 'sowgate-gnss'} rw",
                             "char-ttyUSB rw", "char-ttyACM rw"]
    assert "char-ttyS" not in text and "gpiochip" not in text


def test_board_uarts_only_allow_no_class_and_parts_that_are_off_open_nothing() -> None:
    leader, follower = pty.openpty()
    try:
        board = os.ttyname(follower)
        settings = parse_config({"rs485": {"port": board}, "hmi": {"port": board}})
        text = device_allow_dropin(settings, "x.toml")
    finally:
        os.close(leader)
        os.close(follower)
    assert allowed(text) == ["", f"{board} rw", f"{board} rw"]
    off = parse_config({"rs485": {"port": board}, "hmi": {"enabled": False, "port": "/dev/x"},
                        "gnss": {"enabled": False, "port": "/dev/y"}})
    assert configured_devices(off) == [("rs485.port", board)]


def test_gpio_seed_sensors_allow_their_chip() -> None:
    settings = parse_config({
        "hmi": {"enabled": False}, "gnss": {"enabled": True, "port": "/dev/ttyAMA0"},
        "seed_sensors": {"enabled": True, "source": "gpio", "gpio_chip": "/dev/gpiochip4",
                         "gpio_lines": [5, 6, 12, 13, 19, 26]},
    })
    assert ("seed_sensors.gpio_chip", "/dev/gpiochip4") in configured_devices(settings)


def test_check_config_prints_the_dropin_only_on_a_good_config(tmp_path: Path) -> None:
    cmd = [sys.executable, "-c", "import sys; from gateway.app.cli import main; sys.exit(main())"]
    good = subprocess.run([*cmd, "check-config", "--systemd-device-allow",
                           str(REPO / "examples/sowgate.toml")],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert good.returncode == 0, good.stderr
    assert good.stdout.startswith("# written by install.sh")
    assert "DeviceAllow=/dev/sowgate-rs485 rw" in good.stdout.splitlines()
    bad = tmp_path / "bad.toml"
    bad.write_text("[rs485]\npoll_hz = -3.0\n")
    refused = subprocess.run([*cmd, "check-config", "--systemd-device-allow", str(bad)],
                             capture_output=True, text=True, timeout=120, cwd=REPO)
    assert refused.returncode == 78
    assert refused.stdout == ""  # install.sh writes no drop-in from a bad config
    assert "rs485.poll_hz" in refused.stderr


def test_a_credential_of_another_unit_is_named_not_called_missing(
        monkeypatch: pytest.MonkeyPatch) -> None:
    path = "/run/credentials/sowgate-dashboard.service/dashboard-password"
    settings = parse_config({"dashboard": {"listen": "0.0.0.0:8080", "password_file": path},
                             "commands": {"enabled": ["start", "stop"]}})
    monkeypatch.delenv("CREDENTIALS_DIRECTORY", raising=False)
    assert credential_elsewhere(path) == "sowgate-dashboard.service"
    assert dashboard_problems(settings) == []
    [note] = credential_notes(settings)
    assert note.startswith(f"dashboard.password_file: {path} is a systemd credential of "
                           "sowgate-dashboard.service")
    # inside the unit the file is checked like any other: missing there is exit 78
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", os.path.dirname(path))
    assert credential_elsewhere(path) is None
    [problem] = dashboard_problems(settings)
    assert problem.startswith("dashboard.password_file:")
    assert credential_elsewhere("/etc/sowgate/dashboard-password") is None
