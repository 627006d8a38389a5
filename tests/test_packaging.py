"""What systemd/README.md tells a fitter to install really installs: ``make dist`` builds a
wheel, and that wheel alone (in a fresh virtualenv, dependencies from the package index) gives
a working ``sowgate`` command with its data files.

About 25 s here (a local package index); it is the one test of the install path.
"""

from __future__ import annotations

import re
import subprocess
import sys
import venv
from importlib.metadata import version
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _dist_command() -> list[str]:
    """The wheel-building line of the Makefile's ``dist`` target, with this interpreter."""
    makefile = (REPO / "Makefile").read_text()
    target = re.search(r"^dist:.*\n((?:\t.*\n)+)", makefile, re.MULTILINE)
    assert target, "Makefile has no dist target"
    line = next(ln.strip() for ln in target.group(1).splitlines() if "wheel" in ln)
    assert line.startswith("$(BIN)/pip wheel"), line
    return [sys.executable, "-m", "pip", *line.removeprefix("$(BIN)/pip").split()]


@pytest.mark.slow
def test_the_wheel_from_make_dist_installs_a_working_sowgate_command(tmp_path: Path) -> None:
    build = tmp_path / "build"
    build.mkdir()
    # `make dist` writes to dist/ in the checkout; here the same command writes to tmp_path
    cmd = [part if part != "dist" else str(build) for part in _dist_command()]
    subprocess.run(cmd, cwd=REPO, check=True, capture_output=True, timeout=120)
    wheels = list(build.glob("sowgate-*.whl"))
    assert len(wheels) == 1, wheels

    # the dashboard's page and its vendored assets, licence included (no CDN on a cab box)
    import zipfile

    names = set(zipfile.ZipFile(wheels[0]).namelist())
    for asset in ("index.html", "dashboard.js", "dashboard.css", "vendor/uplot/uPlot.iife.min.js",
                  "vendor/uplot/uPlot.min.css", "vendor/uplot/LICENSE"):
        assert f"gateway/dashboard/static/{asset}" in names, asset

    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    pip = subprocess.run(
        [str(env_dir / "bin" / "pip"), "install", "--quiet", str(wheels[0])],
        capture_output=True, text=True, timeout=300,
    )
    assert pip.returncode == 0, pip.stderr
    sowgate = env_dir / "bin" / "sowgate"
    # run outside the checkout, so nothing is imported from the source tree
    got = subprocess.run([str(sowgate), "--version"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60)
    assert got.stdout.strip() == f"sowgate {version('sowgate')}", got.stderr
    dashboard = subprocess.run([str(sowgate), "dashboard", "--help"], cwd=tmp_path,
                               capture_output=True, text=True, timeout=60)
    assert dashboard.returncode == 0 and "--listen" in dashboard.stdout, dashboard.stderr
    check = subprocess.run(
        [str(sowgate), "check-config", str(REPO / "examples" / "sowgate.toml")],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )
    assert check.returncode == 0, check.stderr
    # the installed copy, with the CAN database it reads at run time
    where = subprocess.run(
        [str(env_dir / "bin" / "python"), "-c",
         "import gateway, protocol.can_metering as m; print(gateway.__file__); "
         "print(m.DBC_PATH.is_file())"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )
    assert where.returncode == 0, where.stderr
    installed, dbc = where.stdout.split()
    assert installed.startswith(str(env_dir)) and dbc == "True", where.stdout
