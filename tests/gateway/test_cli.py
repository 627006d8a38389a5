"""The command line a fitter uses in the field."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from gateway.cli import main

ROOT = Path(__file__).resolve().parents[2]


def test_the_shipped_example_config_is_valid(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(ROOT / "examples" / "sowgate.toml")]) == 0
    assert "ok (machine seeder-01, 6 rows)" in capsys.readouterr().out


def test_check_config_prints_one_line_per_problem_and_exits_78(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = tmp_path / "bad.toml"
    f.write_text('[rs485]\nbaudrate = 5\n[radar]\nunit = "mph"\n')
    assert main(["check-config", str(f)]) == 78
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("rs485.baudrate: ")
    assert err[1].startswith("radar.unit: ")


def test_run_with_an_unknown_screen_encoding_exits_78_naming_the_key(tmp_path: Path) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text('[hmi]\nencoding = "nonesuch"\n')
    proc = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "run", "--config", str(f)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 78, proc.stderr
    assert proc.stderr.startswith("hmi.encoding: unknown text encoding")
    assert "Traceback" not in proc.stderr


def test_run_with_a_missing_config_exits_78(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "run", "--config", str(tmp_path / "none.toml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 78
    assert "config file not found" in proc.stderr


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["run"],
        ["check-config"],
        ["demo"],
        ["decode-gnss"],
        ["export"],
        ["calibrate"],
        ["calibrate", "rotation"],
        ["calibrate", "speed"],
        ["calibrate", "tilt"],
        ["calibrate", "undo"],
        ["calibrate", "show"],
    ],
)
def test_every_command_has_working_help(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        main([*argv, "--help"])
    assert info.value.code == 0
    assert "usage: sowgate" in capsys.readouterr().out
