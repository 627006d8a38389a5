"""The shipped systemd unit is valid, hardened (exposure ≤ 2.5) and has the contract's settings.

`systemd-analyze verify` insists that ExecStart's binary exists. The unit names the packaged
path /usr/bin/sowgate, which a dev machine does not have, so the verify test checks a copy
whose ExecStart points at this checkout's real entry point (.venv/bin/sowgate, the venv
alternative documented in the unit) and changes nothing else.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "sowgate.service"
DASHBOARD_UNIT = REPO / "systemd" / "sowgate-dashboard.service"
INGEST_UNIT = REPO / "systemd" / "sowgate-ingest.service"
UNITS = [
    pytest.param(UNIT, "sowgate run --config /etc/sowgate/sowgate.toml", id="daemon"),
    pytest.param(DASHBOARD_UNIT, "sowgate dashboard --config /etc/sowgate/sowgate.toml",
                 id="dashboard"),
    pytest.param(INGEST_UNIT, "sowgate ingest --config /etc/sowgate/sowgate.toml", id="ingest"),
]
UDEV = REPO / "systemd" / "99-sowgate.rules"
MAX_EXPOSURE = 2.5


def systemd_analyze() -> str:
    found = shutil.which("systemd-analyze")
    if found is None:
        pytest.fail("systemd-analyze is required (apt-get install systemd)")
    return found


def directives(unit: Path = UNIT) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in unit.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        key, _, value = line.partition("=")
        out.setdefault(key.strip(), []).append(value.strip())
    return out


@pytest.mark.parametrize(("unit", "command"), UNITS)
def test_unit_verifies_without_any_warning(tmp_path: Path, unit: Path, command: str) -> None:
    entry = Path(sys.executable).parent / "sowgate"
    assert entry.exists(), "install the project (`make`) so the sowgate entry point exists"
    text = unit.read_text()
    assert f"ExecStart=/usr/bin/{command}" in text
    copy = tmp_path / unit.name
    copy.write_text(text.replace("ExecStart=/usr/bin/sowgate", f"ExecStart={entry}"))
    result = subprocess.run(
        [systemd_analyze(), "verify", str(copy)], capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 0, result.stderr
    # verify exits 0 on unknown keys and typos; any output at all is a defect in the unit
    assert result.stderr.strip() == "" and result.stdout.strip() == "", result.stderr


def test_verify_catches_a_typo_so_the_test_above_is_meaningful(tmp_path: Path) -> None:
    entry = Path(sys.executable).parent / "sowgate"
    copy = tmp_path / "sowgate.service"
    copy.write_text(
        UNIT.read_text()
        .replace("ExecStart=/usr/bin/sowgate", f"ExecStart={entry}")
        .replace("NoNewPrivileges=yes", "NoNewPrivilege=yes")
    )
    result = subprocess.run(
        [systemd_analyze(), "verify", str(copy)], capture_output=True, text=True, timeout=60,
    )
    assert "Unknown key" in result.stderr


@pytest.mark.parametrize(("unit", "command"), UNITS)
def test_security_exposure_is_at_most_2_5(unit: Path, command: str) -> None:
    result = subprocess.run(
        [systemd_analyze(), "security", "--offline=yes", "--no-pager", str(unit)],
        capture_output=True, text=True, timeout=60,
    )
    match = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", result.stdout)
    assert match, result.stdout[-500:] + result.stderr
    score = float(match.group(1))
    assert score <= MAX_EXPOSURE, f"exposure {score} > {MAX_EXPOSURE}"


def test_unit_has_the_contract_settings() -> None:
    d = directives()
    assert d["Type"] == ["notify"]
    assert d["NotifyAccess"] == ["main"]
    assert d["WatchdogSec"] and d["WatchdogSec"][0] != "0"
    assert d["RestartPreventExitStatus"] == ["78"]
    assert d["Restart"] == ["on-failure"]
    assert d["StateDirectory"] == ["sowgate"] and d["ConfigurationDirectory"] == ["sowgate"]
    assert d["SupplementaryGroups"] == ["dialout"]
    assert d["DevicePolicy"] == ["closed"]
    allowed = " ".join(d["DeviceAllow"])
    for dev in ("char-ttyUSB", "char-ttyS", "char-ttyAMA", "char-gpiochip"):
        assert dev in allowed
    assert d["ProtectSystem"] == ["strict"]
    assert d["NoNewPrivileges"] == ["yes"]
    assert "AF_CAN" in d["RestrictAddressFamilies"][0].split()
    assert "@system-service" in d["SystemCallFilter"]


def test_exit_code_78_matches_the_config_error_exit() -> None:
    from gateway.config import EXIT_CONFIG

    assert directives()["RestartPreventExitStatus"] == [str(EXIT_CONFIG)]
    assert directives(DASHBOARD_UNIT)["RestartPreventExitStatus"] == [str(EXIT_CONFIG)]
    assert directives(INGEST_UNIT)["RestartPreventExitStatus"] == [f"{EXIT_CONFIG} 65"]


def test_the_dashboard_unit_is_hardened_like_the_daemon_and_opens_no_device() -> None:
    """The web page is the part reachable from the network: it gets less than the daemon,
    never more. It opens no serial port, so no dialout and no device node at all."""
    daemon, page = directives(), directives(DASHBOARD_UNIT)
    same = ("ProtectSystem", "ProtectHome", "PrivateTmp", "NoNewPrivileges", "DynamicUser",
            "CapabilityBoundingSet", "MemoryDenyWriteExecute", "RestrictNamespaces",
            "SystemCallFilter", "SystemCallArchitectures", "ConfigurationDirectory",
            "ProtectKernelTunables", "ProtectKernelModules", "ProtectControlGroups", "UMask")
    for key in same:
        assert page.get(key) == daemon[key], key
    assert page["PrivateDevices"] == ["yes"] and "DeviceAllow" not in page
    assert "SupplementaryGroups" not in page
    assert page["RestrictAddressFamilies"] == ["AF_UNIX AF_INET AF_INET6"]
    assert page["Restart"] == ["on-failure"]
    assert "StateDirectory" not in page  # it keeps nothing: the store is the daemon's


def test_the_ingest_unit_is_hardened_like_the_dashboard_and_restarts_always() -> None:
    """The farm server's writer: no device, no state, no port; the network for the broker and
    PostgreSQL. A database or broker away is a restart (always), a bad config is not (78),
    nor a schema newer than the code (65, gateway.farm_server.cli.EXIT_SCHEMA)."""
    from gateway.farm_server.cli import EXIT_SCHEMA

    page, ingest = directives(DASHBOARD_UNIT), directives(INGEST_UNIT)
    for key in ("ProtectSystem", "ProtectHome", "PrivateTmp", "NoNewPrivileges", "DynamicUser",
                "CapabilityBoundingSet", "MemoryDenyWriteExecute", "RestrictNamespaces",
                "SystemCallFilter", "PrivateDevices", "PrivateUsers", "RestrictAddressFamilies",
                "ConfigurationDirectory", "UMask"):
        assert ingest.get(key) == page[key], key
    assert "StateDirectory" not in ingest and "DeviceAllow" not in ingest
    assert ingest["Restart"] == ["always"]
    assert str(EXIT_SCHEMA) in ingest["RestartPreventExitStatus"][0].split()


def test_udev_rule_names_every_device() -> None:
    rules = UDEV.read_text()
    for name in ("sowgate-rs485", "sowgate-gnss", "sowgate-seeds", "sowgate-hmi"):
        assert f'SYMLINK+="{name}"' in rules
    active = [ln for ln in rules.splitlines() if ln.strip() and not ln.startswith("#")]
    assert all("GROUP=\"dialout\"" in ln for ln in active if "SYMLINK" in ln)
