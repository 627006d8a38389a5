"""install.sh, run as a fitter runs it, into a fake root (``--root DIR``; no systemctl there).

What it must do on the cab box: install a version offline into /opt/sowgate/<version>, point
/opt/sowgate/current and /usr/bin/sowgate at it, install the units, create the config from the
example only if there is none, run check-config and stop there (exit 78) if it fails; an
upgrade keeps the store, calibration files, config and udev rule, and the version it replaced
stays for ``--rollback``. The stand-in sowgate wheel (tests/deploy/fake_bundle.py) keeps each
install to a few seconds; the real bundle is installed the same way by `make system-test`.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from tests.deploy.fake_bundle import make_bundle

REPO = Path(__file__).resolve().parents[2]
CONFIG = "etc/sowgate/sowgate.toml"
# ~10 s an install (python3 -m venv + ensurepip), over a minute on a busy box
pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]


def install(bundle: Path, root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    # no index at all, even the machine's own: the bundle's wheels are all there is
    env.update(PIP_CONFIG_FILE=os.devnull, PIP_NO_INDEX="1")
    return subprocess.run([str(bundle / "install.sh"), "--root", str(root), *args],
                          capture_output=True, text=True, timeout=180, env=env)


def current(root: Path) -> str:
    return os.readlink(root / "opt/sowgate/current")


def previous(root: Path) -> str:
    return os.readlink(root / "opt/sowgate/previous")


def installed_version(root: Path) -> str:
    out = subprocess.run([str(root / "opt/sowgate/current/bin/sowgate"), "--version"],
                         capture_output=True, text=True, timeout=60, check=True)
    return out.stdout.strip()


@pytest.fixture
def root(tmp_path: Path) -> Path:
    (tmp_path / "root").mkdir()
    return tmp_path / "root"


def test_a_fresh_install_puts_everything_in_place(tmp_path: Path, root: Path) -> None:
    bundle = make_bundle(tmp_path / "b", "1.0.0")
    done = install(bundle, root)
    assert done.returncode == 0, done.stderr
    assert current(root) == "1.0.0"
    assert installed_version(root) == "sowgate 1.0.0"
    assert os.readlink(root / "usr/bin/sowgate") == "/opt/sowgate/current/bin/sowgate"
    for unit in ("sowgate.service", "sowgate-dashboard.service"):
        shipped = (REPO / "systemd" / unit).read_bytes()
        assert (root / "etc/systemd/system" / unit).read_bytes() == shipped, unit
    rule = (REPO / "systemd/99-sowgate.rules").read_bytes()
    assert (root / "etc/udev/rules.d/99-sowgate.rules").read_bytes() == rule
    assert (root / CONFIG).read_bytes() == (REPO / "examples/sowgate.toml").read_bytes()
    assert "ok" in done.stdout  # check-config ran on it
    # the unit's device classes narrowed to the example config's ports
    devices = (root / "etc/systemd/system/sowgate.service.d/devices.conf").read_text()
    assert devices.splitlines()[:2] == ["[Service]", "DeviceAllow="]
    assert "DeviceAllow=/dev/sowgate-rs485 rw" in devices.splitlines()
    assert "/dev/sowgate-rs485" in done.stdout
    assert "nothing started" in done.stdout
    assert not (root / "opt/sowgate/previous").exists()
    nothing = install(bundle, root, "--rollback")
    assert nothing.returncode != 0
    assert "no previous version to go back to" in nothing.stderr
    assert current(root) == "1.0.0"


def test_an_upgrade_keeps_config_rule_store_and_calibration_and_rolls_back(
    tmp_path: Path, root: Path
) -> None:
    assert install(make_bundle(tmp_path / "a", "1.0.0"), root).returncode == 0
    # the fitter's edits and the daemon's state
    (root / CONFIG).write_text('[machine]\nid = "seeder-07"\n')
    (root / "etc/udev/rules.d/99-sowgate.rules").write_text("# my adapters\n")
    state = root / "var/lib/private/sowgate"
    state.mkdir(parents=True)
    (state / "records.sqlite3").write_bytes(b"store")
    (state / "calibration.json").write_text("{}")
    kept = {p: p.read_bytes() for p in [root / CONFIG, root / "etc/udev/rules.d/99-sowgate.rules",
                                        state / "records.sqlite3", state / "calibration.json"]}

    up = install(make_bundle(tmp_path / "b", "1.1.0"), root)
    assert up.returncode == 0, up.stderr
    assert "started from 1.0.0's packages" in up.stdout  # pip installs only what differs
    assert (current(root), previous(root)) == ("1.1.0", "1.0.0")
    assert installed_version(root) == "sowgate 1.1.0"
    assert "kept /etc/sowgate/sowgate.toml" in up.stdout
    assert {p: p.read_bytes() for p in kept} == kept
    # regenerated from the kept config, which names no port: no device at all
    devices = root / "etc/systemd/system/sowgate.service.d/devices.conf"
    assert devices.read_text().split() == ["[Service]", "DeviceAllow="]

    back = install(make_bundle(tmp_path / "c", "1.1.0"), root, "--rollback")
    assert back.returncode == 0, back.stderr
    assert (current(root), previous(root)) == ("1.0.0", "1.1.0")
    assert installed_version(root) == "sowgate 1.0.0"
    assert {p: p.read_bytes() for p in kept} == kept
    # and forward again: rollback swaps the two
    assert install(make_bundle(tmp_path / "d", "1.1.0"), root, "--rollback").returncode == 0
    assert current(root) == "1.1.0"
    # a third version: the oldest goes, current and previous stay
    assert install(make_bundle(tmp_path / "e", "1.2.0"), root).returncode == 0
    versions = sorted(p.name for p in (root / "opt/sowgate").iterdir())
    assert versions == ["1.1.0", "1.2.0", "current", "previous"]
    assert {p: p.read_bytes() for p in kept} == kept


def test_a_bad_config_exits_78_and_a_missing_wheel_keeps_the_installed_version(
    tmp_path: Path, root: Path
) -> None:
    (root / "etc/sowgate").mkdir(parents=True)
    (root / CONFIG).write_text("broken = true\n")
    done = install(make_bundle(tmp_path / "a", "1.0.0"), root)
    assert done.returncode == 78
    assert "machine.broken: not a key" in done.stderr
    assert "sowgate was NOT restarted" in done.stderr
    assert (root / CONFIG).read_text() == "broken = true\n"  # never replaced by the example
    assert current(root) == "1.0.0"  # installed, waiting for a good config

    # pip may use the bundle's wheels only: one missing and nothing changes (a new pin: the
    # copy of 1.0.0's packages an upgrade starts from does not have it either)
    broken = install(make_bundle(tmp_path / "b", "1.1.0", with_dependency=False,
                                 dep_version="2.0"), root)
    assert broken.returncode not in (0, 78)
    assert "pip could not install the bundle's wheels" in broken.stderr
    assert "sowgate-fake-dep" in broken.stderr.lower().replace("_", "-")
    assert current(root) == "1.0.0"
    assert not (root / "opt/sowgate/1.1.0").exists()
    assert installed_version(root) == "sowgate 1.0.0"


def test_a_bundle_for_another_architecture_or_damaged_is_refused(
    tmp_path: Path, root: Path
) -> None:
    other = make_bundle(tmp_path / "a", "1.0.0", arch="riscv64")
    refused = install(other, root)
    assert refused.returncode != 0
    assert "this bundle is for riscv64" in refused.stderr
    damaged = make_bundle(tmp_path / "b", "1.0.0")
    (damaged / "systemd/sowgate.service").write_text("[Service]\n")
    refused = install(damaged, root)
    assert refused.returncode != 0
    assert "the bundle is incomplete or damaged" in refused.stderr
    assert not (root / "opt").exists()
