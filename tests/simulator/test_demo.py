"""What ``sowgate demo`` tells the user: what runs, the applied rate from the simulator's truth,
and what to do next."""

from __future__ import annotations

import logging
import re
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

import pytest

from gateway.app.cli import main as cli_main
from gateway.state import ActiveAlarmState, MachineState, RecorderState
from simulator.demo import program, status_line, summary, truth_report
from simulator.machine import STARTUP_TRANSIENT_S, Truth
from tests.helpers import run_sowgate, sowgate_env

ROOT = Path(__file__).resolve().parents[2]
WIDTH_M = 2.0
STEP_S = 0.1
SPEED_MS = 1.0  # 3.6 km/h


def _sow(truth: Truth, seconds: float, kg_ha: float) -> None:
    """Sow ``seconds`` at 1 m/s, discharging exactly ``kg_ha``."""
    for _ in range(round(seconds / STEP_S)):
        moved = SPEED_MS * STEP_S
        grams = kg_ha * 1000 * moved * WIDTH_M / 1e4
        truth.record(grams, moved, STEP_S, sowing=True, width_m=WIDTH_M)


def _stand(truth: Truth, seconds: float) -> None:
    for _ in range(round(seconds / STEP_S)):
        truth.record(0.0, 0.0, STEP_S, sowing=False, width_m=WIDTH_M)


def test_start_of_every_pass_is_kept_apart_from_settled_sowing() -> None:
    truth = Truth()
    for _ in range(2):  # two passes, each starting under-dosed while catching up
        _sow(truth, STARTUP_TRANSIENT_S, 3.0)
        _sow(truth, 20.0, 6.0)
        _stand(truth, 2.0)
    assert truth.sown_m == pytest.approx(2 * (STARTUP_TRANSIENT_S + 20.0))
    assert truth.settled_m == pytest.approx(40.0)
    assert truth.settled_kg_ha() == pytest.approx(6.0)
    assert truth.applied_kg_ha() == pytest.approx((5 * 3.0 + 20 * 6.0) / 25)
    report = truth_report(truth, 6.0)
    assert report["settled_rate_error_pct"] == pytest.approx(0.0, abs=1e-9)
    assert report["rate_error_pct"] == pytest.approx(-10.0)
    line = summary(report, 6.0)
    assert line.startswith("demo finished: 50.0 m sown, applied 5.40 kg/ha")
    assert "(target 6, error -10.00 %)" in line
    assert f"after the first {STARTUP_TRANSIENT_S:g} s of each pass 6.00 kg/ha" in line
    assert "error +0.00 % over 40.0 m" in line


def test_nothing_sown_is_said_not_reported_as_zero_error() -> None:
    truth = Truth()
    _stand(truth, 4.0)
    line = summary(truth_report(truth, 6.0), 6.0)
    assert "nothing sown yet" in line
    assert "%" not in line  # the old line read "applied 0.00 kg/ha ..., error +0.00 %"


def test_a_run_that_never_left_the_start_up_is_flagged_not_representative() -> None:
    truth = Truth()
    _stand(truth, 4.0)
    _sow(truth, 2.0, 1.0)
    report = truth_report(truth, 6.0)
    assert report["settled_kg_ha"] is None
    line = summary(report, 6.0)
    assert "2.0 m sown" in line and "error -83.33 %" in line
    assert "not representative" in line and "--duration 60" in line


# ---------------------------------------------------------------- the demo as a newcomer runs it


def _run_demo(cwd: Path, *args: str, env: dict[str, str] | None = None) -> tuple[str, str]:
    """``sowgate demo --no-tui ARGS`` in its own process, in ``cwd``: (stdout, stderr)."""
    proc = run_sowgate(
        "demo", "--no-tui", *args,
        cwd=cwd, timeout=90, env=sowgate_env(env={"PYTHONPATH": str(ROOT), **(env or {})}),
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout, proc.stderr


def test_the_demo_says_what_runs_keeps_its_store_and_says_what_to_do_next(
    tmp_path: Path,
) -> None:
    proc = run_sowgate(
        "demo", "--no-tui", "--duration", "7",
        cwd=tmp_path, timeout=90, env=sowgate_env(env={"PYTHONPATH": str(ROOT)}, clean=True),
    )
    assert proc.returncode == 0, proc.stderr
    out, err = proc.stdout, proc.stderr
    state = tmp_path / "sowgate-demo"
    # at start: the simulated devices and their ptys, the config, the store, MQTT, how to stop
    for device in ("RS485", "touchscreen", "GNSS", "seed-tube sensors"):
        assert re.search(rf"{device}.* on /\S+", out), out
    assert "config: sowgate-demo/demo.toml" in out, out
    assert (state / "demo.toml").is_file()
    assert "record store: " in out and "records.sqlite3" in out, out
    assert "MQTT: off" in out and "SOWGATE_MQTT__ENABLED=true" in out, out
    assert "Ctrl-C" in out, out
    # at the end: what was done, and the export to try on the store that was kept
    assert "demo finished: " in out and "motor and fan set to 0" in out, out
    assert "sowgate export --state-dir sowgate-demo --output demo-seeds.csv" in out, out
    assert (state / "records.sqlite3").is_file()
    # --no-tui: a status line every few seconds, and none of pymodbus's chatter
    assert re.search(r"simulator\.demo: (pre_seed|seeding|paused|turning), ", err), err
    assert "Server listening" not in err and "Repeating...." not in err, err

    # the next step it printed works on what it kept
    code = cli_main(["export", "--state-dir", str(state), "--output",
                     str(tmp_path / "demo-seeds.csv")])
    assert code == 0
    assert (tmp_path / "demo-seeds.csv").read_text().startswith("id,")
    # and so does the field report it printed after it
    assert ("sowgate report --config sowgate-demo/demo.toml --state-dir sowgate-demo "
            "--output demo-report.html") in out, out
    assert (tmp_path / "demo-seeds.csv").read_text().count("\n") > 1  # it sowed
    code = cli_main(["report", "--config", str(state / "demo.toml"), "--state-dir", str(state),
                     "--output", str(tmp_path / "demo-report.html")])
    assert code == 0
    assert "<h2>Seed map</h2>" in (tmp_path / "demo-report.html").read_text()


def test_the_demo_uses_the_state_dir_it_is_given_and_names_it_in_the_export_command(
    tmp_path: Path,
) -> None:
    chosen = tmp_path / "my-demo"
    out, _err = _run_demo(tmp_path, "--duration", "3", "--state-dir", str(chosen))
    assert (chosen / "records.sqlite3").is_file()
    assert not (tmp_path / "sowgate-demo").exists()
    assert f"sowgate export --state-dir {chosen} --output demo-seeds.csv" in out, out


def test_the_status_line_says_state_speed_outputs_and_what_was_sown() -> None:
    now = datetime(2026, 4, 1, 8, 0, tzinfo=UTC)
    seeds = RecorderState(
        method="interpolated", records_stored=456, pending=0, buffered=0, queued=0,
        unpositioned=0, extrapolated=0, bad_edges=0, store_errors=0, records_lost=0,
        implausible_edges=0, last_error=None, rows={},
    )
    state = MachineState(
        machine_id="m1", utc=now, work_state="seeding", mode="working", speed_kmh=5.234,
        speed_source="radar", tilt_deg=None, raised=False, crop="wheat",
        target_rate_kg_ha=200.0, commanded_rate_kg_ha=200.0, motor_duty_pct=38.6,
        fan_duty_pct=80.0, devices={}, area_ha=0.0123, seed_mass_kg=0.0,
        alarms=(ActiveAlarmState("gnss.not_rtk_fixed", "warning", "no RTK", now),), seeds=seeds,
    )
    line = status_line(state)
    assert line == (
        "seeding, 5.23 km/h [radar], motor 38.6 % fan 80.0 %, 0.0123 ha, "
        "456 seeds recorded, alarms: gnss.not_rtk_fixed"
    )
    quiet = status_line(replace(state, speed_kmh=None, alarms=(), seeds=None))
    assert "no speed" in quiet and "alarms: none" in quiet and "seeds" not in quiet


def test_pymodbus_logging_is_silent_unless_verbose() -> None:
    from gateway.app.cli import setup_logging

    pymodbus = logging.getLogger("pymodbus")
    before = pymodbus.level
    try:
        setup_logging(verbose=False)
        assert pymodbus.getEffectiveLevel() == logging.CRITICAL
        setup_logging(verbose=True)
        assert pymodbus.getEffectiveLevel() == logging.DEBUG
    finally:
        pymodbus.setLevel(before)


async def test_make_demo_piped_serves_the_dashboard_and_stops_cleanly_on_ctrl_c(
    tmp_path: Path,
) -> None:
    """``make demo | tee demo.log`` (``sowgate demo --dashboard`` into a pipe): a private
    mosquitto, the dashboard process and a URL that shows the simulated seeder's seeds; status
    lines arrive while it runs (not at the end); and Ctrl-C, which the terminal sends to the
    whole foreground process group, stops the daemon first: it drains into the broker, which
    the demo stops after it, so no record is left unacknowledged and no traceback is shown."""
    import asyncio
    import json
    import os
    import signal
    import urllib.request

    from tests.helpers import eventually, sowgate_argv

    env = sowgate_env(env={"PYTHONPATH": str(ROOT)}, clean=True)
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    with out.open("wb") as sink, err.open("wb") as errors:
        proc = await asyncio.create_subprocess_exec(
            *sowgate_argv("demo", "--dashboard", "--state-dir", str(tmp_path / "demo")),
            env=env, stdin=asyncio.subprocess.DEVNULL, stdout=sink, stderr=errors,
            start_new_session=True)  # its own process group, as a shell job has
        try:
            await eventually(lambda: "dashboard: open http://" in out.read_text(), 60.0,
                             "the dashboard's URL", detail=out.read_text)
            text = out.read_text()
            url = re.search(r"dashboard: open (http://\S+)", text)
            assert url is not None
            assert "MQTT: broker 127.0.0.1:" in text  # the private one
            assert "view: standard output is not a terminal" in text, text

            def seeds() -> int:
                with urllib.request.urlopen(url.group(1) + "api/health", timeout=5) as resp:
                    return int(json.load(resp)["machines"].get("seeder-01", 0))

            await eventually(lambda: seeds() > 0, 60.0, "seeds on the dashboard")
            # a progress line while it runs: flushed into the pipe, not held to the end
            await eventually(lambda: re.search(r"\d\d:\d\d:\d\d (pre_seed|seeding|paused|"
                                               r"turning), ", out.read_text()) is not None,
                             60.0, "a status line on standard output", detail=out.read_text)
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in the terminal
            assert await asyncio.wait_for(proc.wait(), 60.0) == 0, err.read_text()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    text, errors_text = out.read_text(), err.read_text()
    assert "demo finished: " in text and "motor and fan set to 0" in text, text
    assert "Traceback" not in errors_text and "MqttError" not in errors_text, errors_text
    assert "not acknowledged" not in errors_text, errors_text

    def reachable() -> bool:
        try:
            urllib.request.urlopen(url.group(1), timeout=2).close()
        except OSError:
            return False
        return True

    assert not reachable()  # the dashboard stopped with the demo (and its broker)


def test_the_next_steps_name_sowgate_as_the_user_can_type_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """`make demo` on a fresh clone runs .venv/bin/sowgate, which is not on PATH: the printed
    `sowgate report ...` must be a command that runs in the same shell."""
    import os
    import sys

    entry = Path(sys.executable).parent / "sowgate"
    assert entry.exists(), "install the project so the sowgate entry point exists"
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    monkeypatch.chdir(entry.parent.parent.parent)  # the checkout, as `make demo` runs it
    assert program() == os.path.join(entry.parent.parent.name, "bin", "sowgate")
    monkeypatch.chdir(tmp_path)  # elsewhere: the absolute path
    assert program() == str(entry.absolute())
    monkeypatch.setenv("PATH", f"{entry.parent}:/usr/bin:/bin")  # an activated venv
    assert program() == "sowgate"
