"""A rotation test cannot silently mislead: units are explicit, poor fits and large changes are
refused with the reason, and the result is stored per outlet.

The field report behind these: on a 24-outlet paper-B drill the masses of all 24 outlets were
typed in, 287.6 g/rev was saved as the channel's *per-outlet* value (25.7x the configured
11.2), and the daemon then commanded 0 r/min to the seed channel with no alarm.
"""

from __future__ import annotations

import argparse
import io
import json
from collections.abc import Callable
from pathlib import Path

import pytest
from rich.console import Console

from gateway.calibration import fits as cal
from gateway.calibration.cli import add_calibration_commands, run_calibration

SPEEDS = (20.0, 30.0, 40.0, 50.0, 60.0)
SECONDS = 30.0


def parse(argv: list[str]) -> argparse.Namespace:
    root = argparse.ArgumentParser(prog="sowgate")
    add_calibration_commands(root.add_subparsers(dest="command"))
    return root.parse_args(argv)


def run(argv: list[str], ask: Callable[[str], float] | None = None) -> tuple[int, str]:
    out = io.StringIO()
    console = Console(file=out, width=160)
    code = run_calibration(parse(argv), console=console,
                           ask=ask or (lambda q: pytest.fail(f"unexpected prompt {q!r}")))
    return code, out.getvalue()


def masses_for(total_g_per_rev: float, speeds: tuple[float, ...] = SPEEDS) -> str:
    """What the scale shows for 30 s runs of a meter delivering ``total_g_per_rev``."""
    return ",".join(f"{total_g_per_rev * n * SECONDS / 60:.4f}" for n in speeds)


def drill_config(tmp_path: Path, *, outlets: int = 24, grams_per_rev: float = 11.2) -> str:
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(
        "[machine]\nworking_width_m = 3.0\nrows = 24\n"
        f'[[channel]]\nname = "seed"\ntarget_rate_kg_ha = 225\nnode_id = 3\n'
        f"outlets = {outlets}\ngrams_per_rev = {grams_per_rev}\n"
    )
    return str(cfg)


def rotation(tmp_path: Path, cfg: str | None, *extra: str) -> list[str]:
    head = ["calibrate", "--state-dir", str(tmp_path)]
    if cfg is not None:
        head[1:1] = ["--config", cfg]
    speeds = ",".join(f"{n:g}" for n in SPEEDS)
    return [*head, "rotation", "--channel", "seed", "--speeds", speeds, "--no-wait", *extra]


def saved(tmp_path: Path, key: str = "rotation.seed") -> dict[str, object] | None:
    return cal.CalibrationStore(tmp_path).get(key)


# ---- units: which mass, stored per outlet --------------------------------------------------


def test_masses_from_all_24_outlets_are_stored_per_outlet(tmp_path: Path) -> None:
    cfg = drill_config(tmp_path)
    code, out = run(rotation(tmp_path, cfg, "--mass", masses_for(287.6)))
    assert code == 0, out
    entry = saved(tmp_path)
    assert entry is not None
    assert entry["outlets_weighed"] == 24 and entry["outlets"] == 24
    assert entry["result"]["grams_per_rev"] == pytest.approx(287.6 / 24)  # type: ignore[index]
    assert "11.98 g/rev per outlet" in out
    assert "24 outlet(s)" in out


def test_fewer_outlets_weighed_scale_to_per_outlet(tmp_path: Path) -> None:
    cfg = drill_config(tmp_path)
    code, out = run(rotation(tmp_path, cfg, "--outlets-weighed", "2",
                             "--mass", masses_for(2 * 11.5)))
    assert code == 0, out
    entry = saved(tmp_path)
    assert entry is not None and entry["outlets_weighed"] == 2
    assert entry["result"]["grams_per_rev"] == pytest.approx(11.5)  # type: ignore[index]


def test_a_25x_mistake_is_refused_side_by_side(tmp_path: Path) -> None:
    """All 24 outlets weighed but declared as one: 287.6 per outlet against 11.2 configured."""
    cfg = drill_config(tmp_path)
    code, out = run(rotation(tmp_path, cfg, "--outlets-weighed", "1",
                             "--mass", masses_for(287.6)))
    assert code == 1, out
    assert "11.20" in out and "287.60" in out  # shown side by side
    assert "--accept-large-change" in out
    assert saved(tmp_path) is None
    code, out = run(rotation(tmp_path, cfg, "--outlets-weighed", "1",
                             "--mass", masses_for(287.6), "--accept-large-change"))
    assert code == 0, out
    entry = saved(tmp_path)
    assert entry is not None and entry["accepted_large_change"] is True
    assert entry["replaces"] == {"grams_per_rev": 11.2, "from": "config"}


def test_a_large_change_is_measured_against_the_saved_value(tmp_path: Path) -> None:
    cfg = drill_config(tmp_path, grams_per_rev=11.2)
    assert run(rotation(tmp_path, cfg, "--mass", masses_for(24 * 13.0)))[0] == 0  # +16 %
    code, out = run(rotation(tmp_path, cfg, "--mass", masses_for(24 * 8.0)))  # -38 % of 13.0
    assert code == 1 and "13.00" in out and "8.00" in out, out
    code, out = run(rotation(tmp_path, cfg, "--mass", masses_for(24 * 10.5)))  # -19 % of 13.0
    assert code == 0, out
    entry = saved(tmp_path)
    assert entry is not None
    assert entry["replaces"] == {"grams_per_rev": pytest.approx(13.0), "from": "calibration"}


def test_help_and_prompt_say_which_mass_is_asked_for(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse(["calibrate", "rotation", "--help"])
    helptext = " ".join(capsys.readouterr().out.split())
    assert "--outlets-weighed" in helptext and "default: all" in helptext
    questions: list[str] = []

    def ask(q: str) -> float:
        questions.append(q)
        return 11.2 * 3 * 20 * 0.1 / 60 if len(questions) == 1 else 11.2 * 3 * 40 * 0.1 / 60

    cfg = drill_config(tmp_path)
    code, out = run(["calibrate", "--config", cfg, "--state-dir", str(tmp_path), "rotation",
                     "--channel", "seed", "--speeds", "20,40", "--seconds", "0.1",
                     "--outlets-weighed", "3"], ask=ask)
    assert code == 0, out
    assert all("mass from 3 outlet(s)" in q for q in questions), questions


def test_outlets_weighed_above_the_channel_outlets_is_refused(tmp_path: Path) -> None:
    code, out = run(rotation(tmp_path, drill_config(tmp_path), "--outlets-weighed", "25",
                             "--mass", masses_for(287.6)))
    assert code == 1 and "--outlets-weighed 25" in out and "24 outlets" in out


# ---- fit quality gates -------------------------------------------------------------------


def test_the_scattered_weighings_of_the_field_report_are_refused_for_their_cv(
    tmp_path: Path,
) -> None:
    argv = ["calibrate", "--state-dir", str(tmp_path), "rotation", "--channel", "seed",
            "--speeds", "20,40,60", "--no-wait", "--mass", "3360,1000,10080"]
    code, out = run(argv)
    assert code == 1, out
    assert "CV" in out and f"{cal.MAX_GPR_CV_PCT:g} %" in out and "--accept-poor-fit" in out
    assert saved(tmp_path) is None
    code, out = run([*argv, "--accept-poor-fit"])
    assert code == 0, out
    entry = saved(tmp_path)
    assert entry is not None
    reasons = entry["accepted_poor_fit"]
    assert isinstance(reasons, list) and any("CV" in r for r in reasons)


def test_gpr_quality_names_each_failed_gate() -> None:
    runs = [cal.RotationRun(n, 30.0, m) for n, m in ((20, 3360), (40, 1000), (60, 10080))]
    problems = cal.grams_per_rev_problems(cal.grams_per_rev(runs))
    assert any("CV" in p for p in problems) and any("R²" in p for p in problems)
    good = [cal.RotationRun(n, 30.0, 11.2 * n / 2) for n in (20, 40, 60)]
    assert cal.grams_per_rev_problems(cal.grams_per_rev(good)) == []


def test_paper_a_poor_r2_and_narrow_range_are_refused() -> None:
    duties = [30.0, 45.0, 60.0, 75.0, 90.0]
    rpm = [0.7 * d - 20.0 for d in duties]
    scattered = [r + e for r, e in zip(rpm, (6.0, -7.0, 8.0, -6.0, 5.0), strict=True)]
    line = cal.fit_motor_line(duties, scattered)
    quad = cal.fit_meter_quadratic(rpm, [-0.6 * w * w + 130 * w - 400 for w in rpm])
    problems = cal.paper_a_problems(line, quad, duties, rpm)
    assert any("eq. 5" in p and "R²" in p for p in problems), problems
    narrow = [40.0, 41.0, 42.0]
    nrpm = [0.7 * d - 20.0 for d in narrow]
    nline = cal.fit_motor_line(narrow, nrpm)
    nquad = cal.fit_meter_quadratic(nrpm, [-0.6 * w * w + 130 * w - 400 for w in nrpm])
    problems = cal.paper_a_problems(nline, nquad, narrow, nrpm)
    assert any("span" in p for p in problems), problems
    good = cal.fit_motor_line(duties, rpm)
    assert cal.paper_a_problems(good, quad, duties, rpm) == []


# ---- paper A: the whole machine's discharge ---------------------------------------------


def _paper_a_argv(tmp_path: Path, cfg: str, masses: list[float], *extra: str) -> list[str]:
    w = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0]
    duty = [(x + 19.8309) / 0.6671 for x in w]
    return ["calibrate", "--config", cfg, "--state-dir", str(tmp_path), "rotation",
            "--channel", "wheat", "--model", "paper_a", "--no-wait",
            "--duties", ",".join(map(str, duty)), "--rpm", ",".join(map(str, w)),
            "--mass", ",".join(map(str, masses)), *extra]


def test_paper_a_scales_fewer_rows_weighed_to_the_whole_machine(tmp_path: Path) -> None:
    cfg = tmp_path / "a.toml"
    cfg.write_text("[machine]\nrows = 6\n")
    w = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0]
    whole = [-0.644 * x * x + 132.212 * x - 398.316 for x in w]  # 60 s runs: g == g/min
    code, out = run(_paper_a_argv(tmp_path, str(cfg), [m * 2 / 6 for m in whole],
                                  "--outlets-weighed", "2"))
    assert code == 0, out
    entry = saved(tmp_path, "rotation.wheat")
    assert entry is not None and entry["outlets_weighed"] == 2 and entry["outlets"] == 6
    meter = entry["result"]["meter"]  # type: ignore[index]
    assert meter["b"] == pytest.approx(132.212)
    # the same masses declared as the whole machine's are a 3x change: refused
    code, out = run(_paper_a_argv(tmp_path, str(cfg), [m * 2 / 6 for m in whole]))
    assert code == 1 and "--accept-large-change" in out, out


def test_saving_says_when_the_daemon_applies_it_and_how_to_undo(tmp_path: Path) -> None:
    code, out = run(rotation(tmp_path, drill_config(tmp_path), "--mass", masses_for(24 * 11.4)))
    assert code == 0, out
    text = " ".join(out.split())
    assert "next start" in text and "sowgate calibrate undo --key rotation.seed" in text
    saved_doc = json.loads((tmp_path / "calibration.json").read_text())
    assert saved_doc["history"][-1]["previous"] is None
