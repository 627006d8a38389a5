"""At start the daemon refuses a calibration that would make a channel sow nothing or run flat
out at its configured rate over the machine's working speeds (``machine.working_speed_kmh``):
it keeps the config value, names the calibration and why, and raises ``calibration.refused``.

The field report: 287.6 g/rev (all 24 outlets' catch) saved as the per-outlet value; the
daemon then commanded 0 r/min to the seed channel with no alarm.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from gateway.app.calibration_check import working_speed_problem
from gateway.app.daemon import Daemon
from gateway.calibration import fits as cal
from gateway.calibration.cli import add_calibration_commands, run_calibration
from gateway.config import ConfigError, Settings, load_config, parse_config


def drill(**machine: Any) -> Settings:
    return parse_config({
        "hmi": {"enabled": False},
        "machine": {"working_width_m": 3.0, "rows": 24, **machine},
        "channel": [{"name": "seed", "target_rate_kg_ha": 225.0, "node_id": 3,
                     "outlets": 24, "grams_per_rev": 11.2, "max_shaft_rpm": 60.0}],
    })


def save_gpr(state: Path, per_outlet: float) -> None:
    runs = [cal.RotationRun(n, 30.0, per_outlet * n / 2) for n in (20.0, 40.0, 60.0)]
    cal.CalibrationStore(state).save("rotation.seed", cal.to_entry(
        cal.grams_per_rev(runs), channel="seed", model="grams_per_rev"))


def start(settings: Settings, state: Path) -> Daemon:
    daemon = Daemon(settings, state)
    for close in daemon.closers:
        close()
    return daemon


def test_the_all_outlets_mass_saved_per_outlet_is_refused_at_start(tmp_path: Path) -> None:
    save_gpr(tmp_path, 287.6)
    settings = drill()
    daemon = start(settings, tmp_path)
    assert settings.channel[0].grams_per_rev == 11.2  # the config value is kept
    assert daemon.alarms.is_active("calibration.refused")
    message = next(a.message for a in daemon.alarms.active if a.code == "calibration.refused")
    assert "rotation.seed" in message and "0 r/min" in message and "4 km/h" in message
    assert any("rotation.seed: refused" in note for note in daemon.calibrations)


def test_a_calibration_that_saturates_the_shaft_is_refused(tmp_path: Path) -> None:
    save_gpr(tmp_path, 2.0)  # 225 kg/ha over 3 m at 12 km/h needs 281 r/min
    settings = drill()
    daemon = start(settings, tmp_path)
    assert settings.channel[0].grams_per_rev == 11.2
    message = next(a.message for a in daemon.alarms.active if a.code == "calibration.refused")
    assert "rotation.seed" in message and "max_shaft_rpm 60" in message


def test_a_sound_calibration_is_applied_without_an_alarm(tmp_path: Path) -> None:
    save_gpr(tmp_path, 11.98)
    settings = drill()
    daemon = start(settings, tmp_path)
    assert settings.channel[0].grams_per_rev == pytest.approx(11.98)
    assert not daemon.alarms.is_active("calibration.refused")


def test_the_working_speed_range_is_configurable() -> None:
    """287.6 g/rev per outlet needs 0.65 r/min at 4 km/h (commanded 0) but 1.3 r/min at 8: a
    drill that never sows below 8 km/h would still turn; 500 g/rev would not."""
    before = drill()
    after = before.model_copy(deep=True)
    after.channel[0].grams_per_rev = 287.6
    assert working_speed_problem(before, after, "rotation.seed") is not None
    fast = drill(working_speed_kmh=[8.0, 12.0])
    after = fast.model_copy(deep=True)
    after.channel[0].grams_per_rev = 287.6
    assert working_speed_problem(fast, after, "rotation.seed") is None
    after.channel[0].grams_per_rev = 500.0
    problem = working_speed_problem(fast, after, "rotation.seed")
    assert problem is not None and "8 km/h" in problem and "8..12" in problem


def test_a_calibration_is_not_blamed_for_what_the_config_value_does_too() -> None:
    """If the configured g/rev already saturates at the top speed, a calibration that does the
    same is not refused for it: the rate or the speed range is the problem, not the weighing."""
    before = drill()
    before.channel[0].max_shaft_rpm = 30.0  # 11.2 g/rev: 50 r/min needed at 12 km/h
    after = before.model_copy(deep=True)
    after.channel[0].grams_per_rev = 11.5
    assert working_speed_problem(before, after, "rotation.seed") is None


def test_a_paper_a_refit_needing_more_than_full_duty_is_refused() -> None:
    before = parse_config({"control": {"crop": "rapeseed"}})
    after = before.model_copy(deep=True)
    crop = after.control.crops["rapeseed"]
    after.control.crops = {**after.control.crops,
                           "rapeseed": crop.model_copy(update={"motor_slope": 0.2})}
    problem = working_speed_problem(before, after, "rotation.rapeseed")
    assert problem is not None and "duty" in problem and "100 %" in problem


@pytest.mark.parametrize("bad", [[12.0, 4.0], [0.0, 12.0], [4.0, 60.0], [4.0]])
def test_a_bad_working_speed_range_names_the_key(bad: list[float]) -> None:
    with pytest.raises(ConfigError, match=r"machine\.working_speed_kmh"):
        parse_config({"machine": {"working_speed_kmh": bad}})


def test_a_small_refit_of_a_channel_near_its_limit_is_not_refused() -> None:
    """The CAN drill example's seed channel (11.2 g/rev x 10 outlets, 225 kg/ha over 3 m)
    saturates from 5.97 km/h; a 2 % lower refit saturates from 5.85 km/h, and a checked speed
    between the two must not turn a sound refit into a refusal."""
    before = parse_config({
        "machine": {"working_width_m": 3.0, "working_speed_kmh": [4.0, 5.9]},
        "channel": [{"name": "seed", "target_rate_kg_ha": 225.0, "node_id": 3,
                     "outlets": 10, "grams_per_rev": 11.2}],
    })
    after = before.model_copy(deep=True)
    after.channel[0].grams_per_rev = 11.0
    assert working_speed_problem(before, after, "rotation.seed") is None
    after.channel[0].grams_per_rev = 5.0  # saturates from 2.7 km/h: the whole range
    assert working_speed_problem(before, after, "rotation.seed") is not None


def test_the_field_report_end_to_end(tmp_path: Path) -> None:
    """CLI then daemon: the 24 outlets' catch is stored per outlet and the seed shaft turns;
    forced through as one outlet's, the daemon refuses it at start instead of sowing nothing."""
    cfg = tmp_path / "drill.toml"
    cfg.write_text(
        '[hmi]\nenabled = false\n[machine]\nworking_width_m = 3.0\nrows = 24\n'
        '[[channel]]\nname = "seed"\ntarget_rate_kg_ha = 225\nnode_id = 3\noutlets = 24\n'
        "grams_per_rev = 11.2\n"
    )
    masses = ",".join(f"{287.6 * n / 2:.3f}" for n in (20, 30, 40, 50, 60))

    def calibrate(state: Path, *extra: str) -> int:
        root = argparse.ArgumentParser(prog="sowgate")
        add_calibration_commands(root.add_subparsers(dest="command"))
        args = root.parse_args(["calibrate", "--config", str(cfg), "--state-dir", str(state),
                                "rotation", "--channel", "seed", "--speeds", "20,30,40,50,60",
                                "--no-wait", "--mass", masses, *extra])
        return run_calibration(args, console=Console(file=io.StringIO()),
                               ask=lambda q: pytest.fail(q))

    good, bad = tmp_path / "good", tmp_path / "bad"
    assert calibrate(good) == 0
    settings = load_config(cfg)
    daemon = start(settings, good)
    assert settings.channel[0].grams_per_rev == pytest.approx(287.6 / 24)
    assert not daemon.alarms.is_active("calibration.refused")

    assert calibrate(bad, "--outlets-weighed", "1") == 1  # a 25x change: refused by the CLI
    assert calibrate(bad, "--outlets-weighed", "1", "--accept-large-change") == 0
    settings = load_config(cfg)
    daemon = start(settings, bad)
    assert settings.channel[0].grams_per_rev == 11.2
    assert daemon.alarms.is_active("calibration.refused")
