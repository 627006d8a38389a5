"""Paper B's rotation test is judged on the g/rev curve it saves (issue 25 §3).

A test at 5 or more shaft speeds saves g/rev as a function of speed, and the channel sows on
that curve; the constant g/rev is then only kept for older readers. The gate that refuses a
test must judge that curve: each speed's g/rev against the curve through the other speeds,
against what the scale and the turn count explain, and name the run to repeat. Judging the
constant's straight line (mass against turns) refused meters whose g/rev simply changes with
speed, which the curve sows within 0.34 % (benchmarks/bench_multichannel.py: 12 of 60).

The truth meters here are built in the test and are not the curve's form (a monotone cubic in
g/min): full cells up to a knee, then each turn delivering less along an exponential approach
(``1 − e^(−(n − knee)/τ)``) scaled so g/rev at 60 r/min is ``change`` off that at 10 r/min.
The catch of 10 outlets is weighed on a ±2 g scale (paper A's); the turns are the set speed
times 30 s (``--drive manual``) or, in the family check, counted to the nearest ½ turn.
"""

from __future__ import annotations

import json
import math
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from gateway.calibration import fits as cal
from tests.gateway.calibration.test_fits import run as run_cli

G10 = 16.97  # paper B's shallow fertiliser, g/rev per outlet
OUTLETS = 10
SCALE_G = 2.0
SECONDS = 30.0
SPEEDS = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)


@dataclass(frozen=True)
class KneeMeter:
    knee_rpm: float
    tau_rpm: float  # how quickly past the knee the change is made
    change: float  # g/rev at 60 r/min against 10 r/min, minus 1

    def grams_per_rev(self, rpm: float) -> float:
        def made(n: float) -> float:
            return 1.0 - math.exp(-max(0.0, n - self.knee_rpm) / self.tau_rpm)

        return G10 * (1.0 + self.change * made(rpm) / made(60.0))


def catches(meter: KneeMeter, rng: random.Random,
            wrong: tuple[float, float] | None = None) -> list[float]:
    """What the scale shows for each run: 10 outlets' catch, ±2 g; ``wrong``: (the set speed
    whose catch is mis-weighed, by this factor)."""
    out = []
    for n in SPEEDS:
        grams = meter.grams_per_rev(n) * n * SECONDS / 60.0 * OUTLETS + rng.gauss(0.0, SCALE_G)
        out.append(grams * (wrong[1] if wrong is not None and wrong[0] == n else 1.0))
    return out


def runs_of(weighed: list[float]) -> list[cal.RotationRun]:
    return [cal.RotationRun(n, SECONDS, m / OUTLETS) for n, m in zip(SPEEDS, weighed,
                                                                    strict=True)]


def calibrate(tmp_path: Path, weighed: list[float], *extra: str) -> tuple[int, str]:
    return run_cli(["calibrate", "--state-dir", str(tmp_path), "rotation", "--channel",
                    "shallow", "--speeds", ",".join(f"{n:g}" for n in SPEEDS),
                    "--outlets-weighed", str(OUTLETS), "--scale-g", f"{SCALE_G:g}",
                    "--mass", ",".join(f"{m:.2f}" for m in weighed), "--no-wait", *extra])


def saved(tmp_path: Path) -> dict[str, Any] | None:
    path = tmp_path / "calibration.json"
    if not path.exists():
        return None
    entry: dict[str, Any] = json.loads(path.read_text())["current"]["rotation.shallow"]
    return entry


# g/rev falling 20 % from 10 to 60 r/min, made early (τ 8 r/min) or nearly straight (τ 100)
FALLING = [KneeMeter(knee, tau, -0.20) for knee in (20.0, 30.0, 35.0) for tau in (8.0, 100.0)]


@pytest.mark.parametrize("meter", FALLING, ids=lambda m: f"knee{m.knee_rpm:g}-tau{m.tau_rpm:g}")
def test_a_meter_whose_g_per_rev_falls_20_pct_from_a_knee_is_accepted_on_its_curve(
        tmp_path: Path, meter: KneeMeter) -> None:
    weighed = catches(meter, random.Random(1))
    # the constant g/rev's straight line does not fit this meter: its gates refuse it (what
    # the CLI did with this test before it judged the curve it saves)
    assert cal.grams_per_rev_problems(cal.grams_per_rev(runs_of(weighed)))
    code, out = calibrate(tmp_path, weighed)
    assert code == 0, out
    entry = saved(tmp_path)
    assert entry is not None and entry["accepted_poor_fit"] == []
    assert entry["result"]["gpr_model"] == "per_speed_curve"
    for n, g in entry["result"]["grams_per_rev_curve"]:  # the curve follows the meter
        assert g == pytest.approx(meter.grams_per_rev(n), rel=0.01)


# meters on which a 10 % mistake at 40 r/min is beyond what shape and weighing explain
MISWEIGHED = [KneeMeter(20.0, 8.0, -0.20), KneeMeter(25.0, 30.0, -0.20),
              KneeMeter(35.0, 100.0, -0.20), KneeMeter(15.0, 20.0, 0.05)]


@pytest.mark.parametrize("factor", [1.10, 0.90])
@pytest.mark.parametrize("meter", MISWEIGHED,
                         ids=lambda m: f"knee{m.knee_rpm:g}-tau{m.tau_rpm:g}-{m.change:+g}")
def test_one_catch_mis_weighed_by_10_pct_is_refused_naming_that_run(
        tmp_path: Path, meter: KneeMeter, factor: float) -> None:
    weighed = catches(meter, random.Random(2), wrong=(40.0, factor))
    code, out = calibrate(tmp_path, weighed)
    assert code == 1, out
    assert "repeat the 40 r/min run" in out and out.count("repeat the ") == 1, out
    assert "off the curve through the others" in out and "--accept-poor-fit" in out
    assert saved(tmp_path) is None
    code, out = calibrate(tmp_path, weighed, "--accept-poor-fit")
    assert code == 0, out
    entry = saved(tmp_path)
    assert entry is not None
    assert [p.split(":")[0] for p in entry["accepted_poor_fit"]] == ["repeat the 40 r/min run"]


def _family(seed: int) -> tuple[KneeMeter, list[cal.RotationRun]]:
    """A meter of issue 25's range (change −20…+5 %, knee 10–35 r/min, τ 5–100 r/min) and
    its test: ±2 g on the 10 outlets' catch, turns counted to the nearest ½ turn."""
    rng = random.Random(f"family:{seed}")
    meter = KneeMeter(rng.uniform(10.0, 35.0), rng.uniform(5.0, 100.0),
                      rng.uniform(-0.20, 0.05))
    runs = []
    for n in SPEEDS:
        turns = n * SECONDS / 60.0 * (1.0 + rng.gauss(0.0, 0.002))  # the shaft's own speed
        mass = meter.grams_per_rev(n) * turns * OUTLETS + rng.gauss(0.0, SCALE_G)
        counted = round(turns * 2.0) / 2.0
        runs.append(cal.RotationRun(counted * 60.0 / SECONDS, SECONDS, mass / OUTLETS,
                                    set_rpm=n))
    return meter, runs


def _named(runs: list[cal.RotationRun]) -> set[float]:
    return {s.set_rpm for s in cal.speeds_on_curve(runs, scale_g=SCALE_G,
                                                   outlets_weighed=OUTLETS)[1]}


def test_meters_across_issue_25s_range_are_not_refused_where_the_constant_gate_was() -> None:
    family = [_family(seed) for seed in range(60)]
    assert all(not _named(runs) for _, runs in family)
    old = sum(1 for _, runs in family if cal.grams_per_rev_problems(cal.grams_per_rev(runs)))
    assert old >= 6  # the constant's line refused about one in five of these


@pytest.mark.parametrize("rpm", [30.0, 40.0, 50.0])
def test_a_run_10_pct_off_in_the_middle_of_the_range_is_named_and_no_other(rpm: float) -> None:
    hits = 0
    for seed in range(20):
        for factor in (1.10, 0.90):
            _, runs = _family(seed)
            runs = [r if r.set_rpm != rpm else cal.RotationRun(r.rpm, r.seconds,
                                                                 r.mass_g * factor, r.set_rpm)
                    for r in runs]
            named = _named(runs)
            assert named <= {rpm}, (seed, factor, named)
            hits += rpm in named
    assert hits >= 36  # of 40: a steep change right beside it can hide a 10 % mistake


def test_a_mistake_at_the_top_end_is_named_with_the_run_beside_it() -> None:
    """The 60 r/min run is judged on the others' curve carried on from 50 r/min: a 10 %
    mistake at 60 and a 10 % mistake at 50 throw it the same way, so both are named; a meter
    steepening towards the end hides it (the rest is not refused in its name)."""
    named = 0
    for seed in range(20):
        for factor in (1.10, 0.90):
            _, runs = _family(seed)
            runs = [r if r.set_rpm != 60.0 else cal.RotationRun(r.rpm, r.seconds,
                                                                  r.mass_g * factor, r.set_rpm)
                    for r in runs]
            off = cal.speeds_on_curve(runs, scale_g=SCALE_G, outlets_weighed=OUTLETS)[1]
            assert [(s.set_rpm, s.beside_rpm) for s in off] in ([], [(60.0, 50.0)])
            named += bool(off)
            if off:
                assert off[0].problem().startswith("repeat the 60 r/min run and the 50 r/min")
    assert named >= 15


def test_a_catch_that_makes_the_delivery_fall_with_speed_is_refused_outright(
        tmp_path: Path) -> None:
    weighed = catches(KneeMeter(25.0, 30.0, -0.20), random.Random(3), wrong=(40.0, 0.65))
    code, out = calibrate(tmp_path, weighed, "--accept-poor-fit")
    assert code == 1 and "repeat set point(s) 30, 40" in out, out
    assert saved(tmp_path) is None


def test_with_fewer_than_5_speeds_the_constant_is_saved_and_its_own_gates_judge_it() -> None:
    meter = KneeMeter(30.0, 100.0, -0.20)
    runs = [cal.RotationRun(n, SECONDS, meter.grams_per_rev(n) * n * SECONDS / 60.0)
            for n in (20.0, 40.0, 60.0)]
    assert cal.grams_per_rev_by_speed(runs) is None
    fit = cal.grams_per_rev(runs)
    problems = cal.grams_per_rev_test_problems(fit, runs, None, scale_g=SCALE_G)
    assert problems == cal.grams_per_rev_problems(fit) and any("R²" in p for p in problems)


def test_the_tests_own_scatter_between_repeats_widens_what_is_explained() -> None:
    """Repeats that scatter by 4 % (a bridging hopper) make a 6 % step at one speed noise;
    the same step on repeats that agree is a run to repeat."""
    meter = KneeMeter(20.0, 30.0, -0.10)
    rng = random.Random(4)

    def runs(scatter: float) -> list[cal.RotationRun]:
        return [cal.RotationRun(n, SECONDS, meter.grams_per_rev(n) * n * SECONDS / 60.0
                                * (1.0 + (0.06 if n == 40.0 else 0.0))
                                * (1.0 + scatter * (1 if i else -1) + rng.gauss(0.0, 0.001)))
                for n in SPEEDS for i in range(2)]

    assert cal.speeds_on_curve(runs(0.0), scale_g=0.1)[1][0].set_rpm == 40.0
    assert cal.speeds_on_curve(runs(0.04), scale_g=0.1)[1] == []


def test_a_run_with_nothing_weighed_is_named_not_saved_as_a_knot() -> None:
    """An empty bag at 10 r/min still rises in g/min (0 then more): the curve through the
    others says it is a run to repeat, whatever the scale."""
    meter = KneeMeter(20.0, 30.0, -0.10)
    runs = [cal.RotationRun(n, SECONDS, 0.0 if n == 10.0 else
                            meter.grams_per_rev(n) * n * SECONDS / 60.0) for n in SPEEDS]
    off = cal.speeds_on_curve(runs, scale_g=SCALE_G)[1]
    assert [(s.set_rpm, s.off_pct) for s in off] == [(10.0, -100.0)]
