"""The rotation test's weighing advice (issue 25 §3): from the scale's σ and the catches in
front of it, each set point's uncertainty and the run length that makes it good enough.

The drills are ``test_monotone_rotation``'s knee drills (logistic under-fill, a soft knee, a
bent motor line): not the controller's model, and not the advice's arithmetic. The advice's
claims are checked by running the truth again as advised, with new scale noise."""

from __future__ import annotations

import json
import random
import statistics
from pathlib import Path

import pytest

from gateway.calibration import fits as cal
from gateway.calibration import weighing
from tests.gateway.calibration.test_fits import run as run_cli
from tests.gateway.calibration.test_monotone_rotation import (
    KneeDrill,
    knee_drill,
    rotation_test,
)

SCALE_G = 2.0  # paper A's "±2 g" scale, one standard deviation


def catches(drill: KneeDrill, duties: list[float], seconds: float | list[float],
            rng: random.Random, scale_g: float = SCALE_G) -> list[float]:
    """What the scale shows for each run of ``seconds`` (one for all, or per run: the truth's
    catch plus σ)."""
    lengths = [seconds] * len(duties) if isinstance(seconds, float) else seconds
    return [drill.flow_g_min(drill.rpm(d)) * t / 60.0 + rng.gauss(0.0, scale_g)
            for d, t in zip(duties, lengths, strict=True)]


def per_run(advice: weighing.WeighingAdvice, duties: list[float]) -> list[float]:
    """Each run's length as the advice's per-set-point list has it."""
    by_key = dict(advice.advised_by_set_point)
    return [by_key[d] for d in duties]


def rapeseed_test(seed: int = 11) -> tuple[KneeDrill, list[float], list[float]]:
    rng = random.Random(seed)
    drill = knee_drill("rapeseed", rng)
    duties, rpm, _ = rotation_test(drill, "rapeseed", rng)
    return drill, [round(d, 3) for d in duties], rpm


def test_the_example_catch_is_said_with_its_numbers() -> None:
    """38 g in 60 s on a ±2 g scale, three runs: ±5.3 % a weighing, ±3.0 % for the mean;
    runs of 300 s bring its mean within 1 % at p90 (±0.61 % one σ; 270 s leaves 0.68 %), a
    ±0.2 g scale would do at 60 s."""
    advice = weighing.weighing_advice([20.0] * 3, [38.0] * 3, 60.0, 2.0)
    (p,) = advice.short
    assert p.per_weighing_pct == pytest.approx(5.26, abs=0.01)
    assert p.se_pct == pytest.approx(3.04, abs=0.01)
    assert p.seconds_needed == 300.0 and p.scale_needed_g == 0.2
    text = " ".join(advice.messages("rapeseed", "{:g} % duty"))
    assert ("rapeseed at 20 % duty: 38 g in 60 s on a ±2 g scale is ±5.3 % (±3.0 % over its "
            "3 runs); run this set point for at least 300 s (or weigh on a ±0.2 g scale)"
            ) in text
    assert "--seconds 300 " in text and "Longer runs, not more of them" in text


def test_the_advice_gives_each_set_point_its_own_length() -> None:
    """A 38 g catch needs 300 s, a 250 g one is within 1 % at 60 s: the advice's --seconds
    list says 300 for the first and keeps 60 for the second, in the order the test ran them
    (not sorted), and the entry keeps both lists; advised_seconds stays the longest."""
    advice = weighing.weighing_advice([40.0] * 3 + [20.0] * 3, [250.0] * 3 + [38.0] * 3,
                                      60.0, 2.0)
    assert advice.advised_by_set_point == ((40.0, 60.0), (20.0, 300.0))
    assert advice.seconds_option == "60,300" and advice.advised_seconds == 300.0
    text = " ".join(advice.messages("rapeseed", "{:g} % duty"))
    assert ("run the test again with --seconds 60,300 (one length per set point, in the order "
            "of the set points; only 20 % duty longer;") in text
    entry = advice.to_entry()
    assert entry["advised_seconds_by_set_point"] == [[40.0, 60.0], [20.0, 300.0]]
    assert entry["seconds_by_set_point"] == [[40.0, 60.0], [20.0, 60.0]]
    assert entry["advised_seconds"] == 300.0 and entry["advised_seconds_option"] == "60,300"
    # the test run as advised: the long set point's catch is 300/60 as big, nothing short
    again = weighing.weighing_advice([40.0] * 3 + [20.0] * 3, [250.0] * 3 + [200.0] * 3,
                                     [60.0] * 3 + [300.0] * 3, 2.0)
    assert again.short == () and again.seconds_option == "60,300"
    (low,) = (p for p in again.set_points if p.set_point == 20.0)
    assert low.seconds == 300.0 and low.se_pct < again.limit_pct


def test_longer_runs_are_advised_not_more_of_them() -> None:
    """Doubling the runs of a set point divides its uncertainty by √2 only: six 60 s runs of
    a 38 g catch are still short, and the length advised for them is shorter than for three
    runs by √2, not by 2."""
    three = weighing.weighing_advice([20.0] * 3, [38.0] * 3, 60.0, 2.0).short[0]
    six = weighing.weighing_advice([20.0] * 6, [38.0] * 6, 60.0, 2.0).short[0]
    assert six.se_pct == pytest.approx(three.se_pct / 2 ** 0.5)
    assert six.seconds_needed < three.seconds_needed < 2 * six.seconds_needed


def test_the_advised_runs_on_the_truth_drill_bring_every_set_point_within_the_target() -> None:
    """A knee drill's rapeseed test at 60 s on ±2 g: the low set points are named with the
    length each needs. The test run again on the truth with those lengths, each set point its
    own (new scale noise, 400 times), puts every set point's mean within the target at
    p90, and the second test's own advice asks at most one 30 s step more of a set
    point (each length is the shortest at the target, so its own noise can put it a hair
    over); the set points that need less run less, so the test is shorter than at the
    longest."""
    drill, duties, _ = rapeseed_test()
    rng = random.Random(5)
    first = weighing.weighing_advice(duties, catches(drill, duties, 60.0, rng), 60.0, SCALE_G)
    assert first.short and min(duties) in {p.set_point for p in first.short}
    seconds = per_run(first, duties)
    assert max(seconds) == first.advised_seconds > 60.0
    assert sum(seconds) < first.advised_seconds * len(duties)
    set_points = sorted(set(duties))
    errs: dict[float, list[float]] = {k: [] for k in set_points}
    for _ in range(400):
        weighed = catches(drill, duties, seconds, rng)
        for k in set_points:
            mean = statistics.fmean(m for d, m in zip(duties, weighed, strict=True) if d == k)
            true = drill.flow_g_min(drill.rpm(k)) * seconds[duties.index(k)] / 60.0
            errs[k].append(abs(mean / true - 1.0) * 100.0)
    for k, e in errs.items():
        p90 = statistics.quantiles(e, n=10)[-1]
        assert p90 <= first.target_pct * 1.15, (k, p90)  # 400 draws: p90 ±~10 %
    again = weighing.weighing_advice(duties, catches(drill, duties, seconds, rng), seconds,
                                     SCALE_G)
    # each length is the shortest (to 30 s) at the target: the second test's own noise can
    # put a set point a hair over it, never more than one step from what it ran
    assert all(p.seconds_needed <= p.seconds + weighing.ROUND_SECONDS for p in again.short)
    assert len(again.short) < len(first.short)


def test_a_fine_scale_needs_no_longer_runs() -> None:
    drill, duties, _ = rapeseed_test()
    rng = random.Random(6)
    fine = weighing.weighing_advice(duties, catches(drill, duties, 60.0, rng, 0.1), 60.0, 0.1)
    assert fine.short == () and fine.messages("rapeseed") == []
    assert fine.advised_seconds == 60.0


def test_runs_that_disagree_beyond_the_scale_are_to_be_repeated_not_lengthened() -> None:
    """One run of a set point 15 % short (the hopper bridged): named to repeat. Wheat's kilogram
    catches scatter by the operator's timing (0.5 %), beyond a 2 g scale but not beyond what
    the rate can take: not named."""
    rng = random.Random(7)
    drill, duties, _ = rapeseed_test()
    weighed = catches(drill, duties, 180.0, rng)
    bad = duties.index(sorted(set(duties))[3])
    weighed[bad] *= 0.85
    named = weighing.unexplained_scatter(duties, weighed, SCALE_G)
    assert [p.set_point for p in named] == [duties[bad]]
    wheat = knee_drill("wheat", rng)
    wd, _, _ = rotation_test(wheat, "wheat", rng)
    timed = [wheat.flow_g_min(wheat.rpm(d)) * (1 + rng.gauss(0.0, 0.005)) for d in wd]
    assert weighing.unexplained_scatter(wd, timed, SCALE_G) == []


def test_the_cli_warns_with_the_numbers_saves_and_keeps_the_advice(tmp_path: Path) -> None:
    """`sowgate calibrate rotation --model paper_a` on a knee drill's 60 s rapeseed catches:
    exit 0 (the readings are consistent), each short set point said with its catch, scale and
    the length it needs, the whole test's `--seconds`; calibration.json keeps the advice."""
    drill, duties, rpm = rapeseed_test(seed=12)
    masses = [round(m, 2) for m in catches(drill, duties, 60.0, random.Random(8))]
    expected = weighing.weighing_advice(duties, masses, 60.0, SCALE_G)

    def calibrate(state_dir: Path, scale_g: str) -> tuple[int, str]:
        return run_cli(["calibrate", "--state-dir", str(state_dir), "rotation", "--channel",
                        "rapeseed", "--model", "paper_a", "--no-wait", "--seconds", "60",
                        "--scale-g", scale_g, "--duties", ",".join(f"{d:.3f}" for d in duties),
                        "--rpm", ",".join(f"{w:.4f}" for w in rpm),
                        "--mass", ",".join(f"{m:.2f}" for m in masses)])

    code, out = calibrate(tmp_path, "2")
    assert code == 0, out
    flat = " ".join(out.split())
    assert "the runs were too short for this scale" in flat
    for p in expected.short:
        assert (f"rapeseed at {p.set_point:.4g} % duty: {p.mean_mass_g:.3g} g in 60 s on a ±2 g "
                f"scale is ±{p.per_weighing_pct:.1f} %") in flat
        assert f"for at least {p.seconds_needed:g} s" in flat
    assert "," in expected.seconds_option  # the low set points only run longer
    assert f"run the test again with --seconds {expected.seconds_option} (" in flat
    assert "repeat those set points" not in flat  # nothing but the scale's noise here
    entry = cal.CalibrationStore(tmp_path).get("rotation.rapeseed")
    assert entry is not None
    assert entry["weighing"]["advised_seconds"] == expected.advised_seconds > 60.0
    assert entry["weighing"]["advised_seconds_by_set_point"] == [
        list(p) for p in expected.advised_by_set_point]
    assert entry["weighing"]["scale_g"] == 2.0

    fine = tmp_path / "fine"
    code, out = calibrate(fine, "0.1")
    assert code == 0, out
    flat = " ".join(out.split())
    assert "too short" not in flat and "every set point's mean within ±1 % on a ±0.1 g" in flat
    doc = json.loads((fine / "calibration.json").read_text())
    assert doc["current"]["rotation.rapeseed"]["weighing"]["advised_seconds"] == 60.0


def test_the_cli_advises_paper_b_runs_too(tmp_path: Path) -> None:
    """Paper B's 30 s runs of one outlet at 10 r/min catch a few grams: named in r/min."""
    speeds = [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]
    masses = [2.0 * 0.5 * n * 30.0 / 60.0 * 10 for n in speeds]  # 2 g/rev ×5: 50..300 g
    code, out = run_cli(["calibrate", "--state-dir", str(tmp_path), "rotation", "--channel",
                         "deep", "--no-wait", "--speeds", ",".join(f"{n:g}" for n in speeds),
                         "--mass", ",".join(f"{m:g}" for m in masses), "--scale-g", "2"])
    assert code == 0, out
    flat = " ".join(out.split())
    assert "deep at 10 r/min: 50 g in 30 s on a ±2 g scale is ±4.0 %" in flat
    assert "for at least 210 s" in flat


def test_a_scale_of_no_error_is_refused(tmp_path: Path) -> None:
    drill, duties, rpm = rapeseed_test()
    masses = catches(drill, duties, 60.0, random.Random(9))
    code, out = run_cli(["calibrate", "--state-dir", str(tmp_path), "rotation", "--channel",
                         "rapeseed", "--model", "paper_a", "--no-wait", "--scale-g", "0",
                         "--duties", ",".join(f"{d:.3f}" for d in duties),
                         "--rpm", ",".join(f"{w:.4f}" for w in rpm),
                         "--mass", ",".join(f"{m:.2f}" for m in masses)])
    assert code != 0 and "--scale-g must be > 0" in " ".join(out.split())
    assert cal.CalibrationStore(tmp_path).get("rotation.rapeseed") is None


def rotation_cli(state: Path, duties: list[float], rpm: list[float], masses: list[float],
                 *extra: str) -> tuple[int, str]:
    return run_cli(["calibrate", "--state-dir", str(state), "rotation", "--channel",
                    "rapeseed", "--model", "paper_a", "--no-wait", "--scale-g", "2",
                    "--duties", ",".join(f"{d:.3f}" for d in duties),
                    "--rpm", ",".join(f"{w:.4f}" for w in rpm),
                    "--mass", ",".join(f"{m:.2f}" for m in masses), *extra])


def test_seconds_per_set_point_is_parsed_and_a_wrong_count_is_refused(tmp_path: Path) -> None:
    """`--seconds` takes one length, or one per set point (eight here, three runs each); four
    lengths for eight set points, or a length of 0, is refused naming the option, before
    anything is saved."""
    drill, duties, rpm = rapeseed_test(seed=13)
    n = len(set(duties))
    assert n == 8 and len(duties) == 3 * n
    masses = catches(drill, duties, 60.0, random.Random(10))
    code, out = rotation_cli(tmp_path, duties, rpm, masses, "--seconds", "300,240,120,60")
    flat = " ".join(out.split())
    assert code != 0 and "--seconds has 4 lengths for 8 set points" in flat, out
    assert "one per set point in the order of --duties" in flat
    code, out = rotation_cli(tmp_path, duties, rpm, masses, "--seconds",
                             ",".join(["60", "0"] + ["60"] * (n - 2)))
    assert code != 0 and "--seconds must be > 0 s (got 0)" in " ".join(out.split()), out
    assert cal.CalibrationStore(tmp_path).get("rotation.rapeseed") is None
    code, out = rotation_cli(tmp_path, duties, rpm, masses, "--seconds", "60")
    assert code == 0, out  # the single length as before
    saved = cal.CalibrationStore(tmp_path).get("rotation.rapeseed")
    assert saved is not None and saved["weighing"]["seconds_by_set_point"] == [
        [d, 60.0] for d in dict.fromkeys(duties)]


def test_runs_of_different_lengths_are_each_turned_into_a_rate_over_their_own_time(
        tmp_path: Path) -> None:
    """The knee drill weighed without error, its set points run 300, 240, 120, 90, 60 … s:
    each catch is over its own run, so the saved curve's knots are the truth's flow at every
    set point (a catch over the wrong length would be off by up to 5×), and the advice on
    those catches has nothing more to ask for."""
    drill, duties, _ = rapeseed_test(seed=14)
    keys = list(dict.fromkeys(duties))
    lengths = [300.0, 240.0, 120.0, 90.0] + [60.0] * (len(keys) - 4)
    seconds = [lengths[keys.index(d)] for d in duties]
    rpm = [drill.rpm(d) for d in duties]
    masses = [drill.flow_g_min(drill.rpm(d)) * t / 60.0 for d, t in zip(duties, seconds,
                                                                          strict=True)]
    code, out = rotation_cli(tmp_path, duties, rpm, masses, "--seconds",
                             ",".join(f"{t:g}" for t in lengths))
    assert code == 0, out
    entry = cal.CalibrationStore(tmp_path).get("rotation.rapeseed")
    assert entry is not None
    knots = entry["result"]["meter_curve"]
    truth = sorted((drill.rpm(k), drill.flow_g_min(drill.rpm(k))) for k in keys)
    assert len(knots) == len(truth)
    for (w, q), (tw, tq) in zip(knots, truth, strict=True):
        assert w == pytest.approx(tw, rel=1e-3) and q == pytest.approx(tq, rel=2e-3)
    assert entry["weighing"]["seconds_by_set_point"] == [
        [k, t] for k, t in zip(keys, lengths, strict=True)]


def test_time_weighted_knots_are_total_catch_over_total_time() -> None:
    """Two set points pooled (a fall within the noise): the pooled knot weighs each by its
    run time, a 300 s set point five times a 60 s one, not by its number of runs."""
    xs = [10.0] * 3 + [11.0] * 3 + [20.0] * 3 + [30.0] * 3 + [40.0] * 3 + [50.0] * 3
    ys = [100.0] * 3 + [99.5] * 3 + [200.0] * 3 + [300.0] * 3 + [400.0] * 3 + [500.0] * 3
    t = [300.0] * 3 + [60.0] * 15
    fit = cal.fit_monotone(xs, ys, "flow", weights=t)
    assert fit.pooled == ((10.0, 11.0),)
    x0, y0 = fit.points[0]
    assert y0 == pytest.approx((300 * 100.0 + 60 * 99.5) / 360)
    assert x0 == pytest.approx((300 * 10.0 + 60 * 11.0) / 360)
    plain = cal.fit_monotone(xs, ys, "flow")
    assert plain.points[0][1] == pytest.approx((100.0 + 99.5) / 2)


def test_a_kitchen_scale_makes_the_advised_test_impractical_and_the_finer_scale_is_named(
) -> None:
    """A knee drill's rapeseed test at 60 s weighed on a ±10 g scale: the advised runs take
    hours end to end (summed here from the advice's own per-set-point lengths), said plainly;
    the scale it names brings the test, run again on the truth with that scale's noise, under
    the practical limit; on paper A's ±2 g the same drill's advice is practical and says
    nothing of it."""
    drill, duties, _ = rapeseed_test()
    rng = random.Random(21)
    coarse = weighing.weighing_advice(duties, catches(drill, duties, 60.0, rng, 10.0), 60.0,
                                      10.0)
    hours = sum(per_run(coarse, duties))
    assert coarse.test_seconds() == pytest.approx(hours) and hours > weighing.PRACTICAL_TEST_S
    assert coarse.impractical
    note = coarse.practical_note("rapeseed")
    assert note is not None
    fine = coarse.practical_scale_g
    assert fine < 10.0
    assert (f"the advised test runs {weighing.duration(hours)} end to end ({len(duties)} "
            f"runs) on a ±10 g scale") in note and "not practical" in note
    assert f"on a ±{fine:g} g scale the advised test takes" in note
    # the named scale, on the truth: its own advice from its own catches is practical
    again = weighing.weighing_advice(duties, catches(drill, duties, 60.0, rng, fine), 60.0,
                                     fine)
    assert again.test_seconds() <= weighing.PRACTICAL_TEST_S * 1.1
    paper_a = weighing.weighing_advice(duties, catches(drill, duties, 60.0, rng), 60.0, 2.0)
    assert paper_a.short and not paper_a.impractical
    assert paper_a.practical_note("rapeseed") is None


def test_later_runs_of_a_set_point_make_up_a_short_first_one() -> None:
    """A first run of 60 s where the catch needs 300 s over three runs: the two runs left run
    (3 × 300 − 60) / 2 = 420 s, and the three together are within the target by the advice's
    own judgement of their catches; a first run long enough leaves the others at nothing more
    than it needs."""
    rate = 38.0 / 60.0  # g/s: 38 g in 60 s
    assert weighing.run_seconds_needed(rate, 2.0, 3) == 300.0
    left = weighing.remaining_run_seconds(rate, 2.0, 3, [60.0])
    assert left == 420.0
    lengths = [60.0, left, left]
    advice = weighing.weighing_advice([20.0] * 3, [rate * t for t in lengths], lengths, 2.0)
    assert advice.short == ()
    # one 30 s step less for the two and the set point is short again: 420 is the shortest
    shorter = [60.0, left - 30.0, left - 30.0]
    assert weighing.weighing_advice([20.0] * 3, [rate * t for t in shorter], shorter,
                                    2.0).short
    assert weighing.remaining_run_seconds(rate, 2.0, 3, [900.0]) == 0.0


def test_the_cli_takes_the_configured_scale_and_says_when_the_test_is_impractical(
    tmp_path: Path,
) -> None:
    """`calibrate rotation --config` with `[calibration] scale_g = 10` and no `--scale-g`:
    the advice is for ±10 g (kept in the entry), and the hours it would take are said with
    the scale to weigh on instead."""
    drill, duties, rpm = rapeseed_test(seed=12)
    masses = [round(m, 2) for m in catches(drill, duties, 60.0, random.Random(8), 10.0)]
    config = tmp_path / "sowgate.toml"
    config.write_text("[calibration]\nscale_g = 10\n")
    code, out = run_cli(["calibrate", "--config", str(config), "--state-dir", str(tmp_path),
                         "rotation", "--channel", "rapeseed", "--model", "paper_a",
                         "--no-wait", "--seconds", "60",
                         "--duties", ",".join(f"{d:.3f}" for d in duties),
                         "--rpm", ",".join(f"{w:.4f}" for w in rpm),
                         "--mass", ",".join(f"{m:.2f}" for m in masses)])
    assert code == 0, out
    flat = " ".join(out.split())
    expected = weighing.weighing_advice(duties, masses, 60.0, 10.0)
    assert expected.impractical
    assert "on a ±10 g scale is" in flat and "not practical" in flat
    assert (f"on a ±{expected.practical_scale_g:g} g scale the advised test takes "
            f"{weighing.duration(expected.test_seconds(expected.practical_scale_g))}") in flat
    entry = cal.CalibrationStore(tmp_path).get("rotation.rapeseed")
    assert entry is not None and entry["weighing"]["scale_g"] == 10.0
    assert entry["weighing"]["impractical"] is True
