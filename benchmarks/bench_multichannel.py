"""Paper B's dynamic test in simulation: three channels at 5 km/h, sowgate vs open loop.

Set-up (paper B): 2.55 m, 10 outlets per channel, shallow fertiliser 150 kg/ha at 16.97 g/rev,
deep fertiliser 300 kg/ha at 29.31 g/rev, seed 225 kg/ha at 11.20 g/rev (g/rev per outlet).

The meters are not the controller's model (issue 25): a draw gives every channel's meter its
own law (``draw_meter``): g/rev at 10 r/min within ±5 % of paper B's, a change from 10 to
60 r/min drawn in ``CHANGE_RANGE`` (cells filling less, or a little more, at speed), reached
along a power law of drawn exponent from a drawn knee (cells full up to it). The controller
knows none of it: it sees only the rotation test's weighings.

What runs, all in simulated time (deterministic for a seed):
1. Paper B's rotation test on each drawn meter (30 s at 10..60 r/min, the shaft's turns
   counted to ½ turn, as ``sowgate calibrate rotation --drive can`` does), fitted and saved the
   way the CLI saves it (``grams_per_rev`` + ``grams_per_rev_by_speed`` ->
   ``grams_per_rev_result``) and laid over the config the way the daemon does
   (``gateway.calibration.apply.apply_entries``): the channel then sows on its g/rev curve.
2. sowgate closed loop: every 100 ms the measured speed (GNSS-like, 10 Hz, sigma 0.05 km/h)
   and the channel give the target shaft speed (``gateway.metering.channels.
   channel_target_rpm``), sent through the DBC codec (0.01 r/min quantisation) to the PID +
   hydraulic motor plant; its status frames go through the codec and ``ChannelSupervisor``
   (alarms are counted).
3. Sensitivity, same run and meters: the same rotation test's constant g/rev (paper B's mean
   of the runs >= 20 r/min; what a test at fewer than 5 speeds, or an older file, gives).
4. Open-loop baseline, same run and meters: a fixed shaft speed set once from the nominal
   5 km/h and paper B's catalogue g/rev + 5 %, i.e. a drill without speed following or field
   calibration (its bias is the 5 % plus what the drawn meter does at its speed).

Tractor speed: 5 km/h x (1 + 6 % slow wave (7 s) + 3 % fast wave (2.3 s) + small noise),
mean 5 km/h. Meters: flute pulsation 4 % (12 flutes), 1.5 % random spread per 0.1 rev.
These plant figures and the drawn ranges are assumptions, not measurements: the benchmark
compares control strategies on plants unlike the controller's model; it does not predict a
field CV.

Figures per channel: CV (%) of the applied rate over 1-second windows (rate = mass delivered
in the window / (width x true distance in the window)); bias (%) = total mass / total area
against target; mean |deviation| (%) of the 1-s windows from target. 120 s after 5 s warm-up.
Headline (issue 25): over ``DRAWS`` independent draws (seeds 1..DRAWS: each its own meters,
meter noise, speed noise, GNSS noise and speed-wave phases), median / p90 / worst per channel;
targets judged on p90 (sowgate CV <= paper B's CV for the channel, |bias| <= 1 %). The draws
run in a pool of ``SOWGATE_BENCH_WORKERS`` spawned processes (default 2, as bench_rate).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import random
import statistics
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any

from gateway.calibration.apply import apply_entries
from gateway.calibration.fits import (
    OFF_CURVE_SIGMAS,
    CalibrationError,
    RotationRun,
    grams_per_rev,
    grams_per_rev_by_speed,
    grams_per_rev_problems,
    grams_per_rev_result,
    grams_per_rev_test_problems,
    speeds_on_curve,
    to_entry,
)
from gateway.calibration.lots import rotation_key
from gateway.calibration.weighing import DEFAULT_SCALE_G
from gateway.config import ChannelSection, parse_config
from gateway.metering.channels import ChannelSupervisor, channel_target_rpm, target_shaft_rpm
from protocol import can_metering as cm
from simulator.can_pid import MeterPlant

WIDTH_M = 2.55
OUTLETS = 10
SPEED_KMH = 5.0
CHANNELS = (("shallow", 1, 150.0, 16.97), ("deep", 2, 300.0, 29.31), ("seed", 3, 225.0, 11.20))
CONTROL_DT_S = 0.1  # CAN command / GNSS rate
WARMUP_S = 5.0
RUN_S = 120.0
WINDOW_S = 1.0
OPEN_LOOP_CAL_ERROR = 0.05
PAPER_CV = {"shallow": 3.5, "deep": 3.8, "seed": 3.0}
STRATEGIES = ("sowgate", "constant", "open_loop")

# The drawn meters (assumed ranges, not measured: no published test of a fluted roller's
# g/rev over 10..60 r/min was found; the fall's 10-20 % is issue 25's, the rise of up to 5 %
# a meter whose flutes over-fill at speed, so the sign is not given away)
GPR_SPREAD = 0.05  # this meter's g/rev at 10 r/min against paper B's
CHANGE_RANGE = (-0.20, 0.05)  # its g/rev change from 10 to 60 r/min
FILL_SHAPE_RANGE = (0.6, 1.6)  # the power law's exponent (p < 1 changes early, p > 1 late)
KNEE_RANGE_RPM = (10.0, 35.0)  # cells full up to this speed; the change runs from it to 60


def tractor_speed(t: float, rng: random.Random,
                  phases: tuple[float, float] = (0.0, 1.0)) -> float:
    wave = (0.06 * math.sin(2 * math.pi * t / 7.0 + phases[0])
            + 0.03 * math.sin(2 * math.pi * t / 2.3 + phases[1]))
    return SPEED_KMH * (1 + wave + rng.gauss(0, 0.005))


@dataclass(frozen=True)
class MeterLaw:
    """One drawn meter: what its g/rev does with shaft speed (the truth, never shown to the
    controller, which sees only the rotation test's weighings)."""

    g10: float  # g/rev per outlet at 10 r/min
    change: float  # g/rev at 60 r/min / g/rev at 10 r/min - 1
    shape: float  # power-law exponent
    knee_rpm: float  # g/rev flat up to here

    def plant(self, rng: random.Random, inner_dt_s: float = 0.001) -> MeterPlant:
        return MeterPlant(self.g10, OUTLETS, rng=rng, fill_fall=-self.change,
                          fill_shape=self.shape, fill_knee_rpm=self.knee_rpm,
                          inner_dt_s=inner_dt_s)


def draw_meter(name: str, g_nominal: float, seed: int) -> MeterLaw:
    """Channel ``name``'s meter in draw ``seed`` (its own stream: the same meter whatever
    else the draw changes)."""
    rng = random.Random(f"meter:{seed}:{name}")
    return MeterLaw(g10=g_nominal * (1.0 + rng.uniform(-GPR_SPREAD, GPR_SPREAD)),
                    change=rng.uniform(*CHANGE_RANGE), shape=rng.uniform(*FILL_SHAPE_RANGE),
                    knee_rpm=rng.uniform(*KNEE_RANGE_RPM))


def calibrated_channels(runs: dict[str, list[RotationRun]]) -> tuple[
        dict[str, ChannelSection], dict[str, dict[str, Any]]]:
    """The channels as the daemon sows them after paper B's rotation tests: each test fitted
    and saved as ``sowgate calibrate rotation`` saves it, the entries laid over a config with
    paper B's g/rev by ``apply_entries`` (the daemon's path); also, per channel, what the
    CLI's quality gate says of the test (``problems``: refused without ``--accept-poor-fit``;
    judged as the CLI judges it, on the curve it saves, the catch of all 10 outlets on its
    default ±2 g scale), what the constant g/rev's gates would have said (``constant_gates``,
    the gate before), and the largest of the speeds' distances from the curve through the
    others in σ (``worst_sigmas``; the gate is at ``OFF_CURVE_SIGMAS``)."""
    settings = parse_config({"channel": [
        {"name": name, "node_id": node, "target_rate_kg_ha": target, "grams_per_rev": g,
         "outlets": OUTLETS} for name, node, target, g in CHANNELS]})
    entries: dict[str, Any] = {}
    gates: dict[str, dict[str, Any]] = {}
    for name, channel_runs in runs.items():
        fit = grams_per_rev(channel_runs)
        constant = grams_per_rev_problems(fit)
        try:
            by_speed = grams_per_rev_by_speed(channel_runs)
        except CalibrationError as exc:  # the CLI refuses the test: the config value stays
            gates[name] = {"problems": [str(exc)], "constant_gates": constant,
                           "worst_sigmas": None}
            continue
        judged = speeds_on_curve(channel_runs, scale_g=DEFAULT_SCALE_G,
                                 outlets_weighed=OUTLETS)[0] if by_speed is not None else []
        gates[name] = {
            "problems": grams_per_rev_test_problems(fit, channel_runs, by_speed,
                                                    scale_g=DEFAULT_SCALE_G,
                                                    outlets_weighed=OUTLETS),
            "constant_gates": constant,
            "worst_sigmas": max((j.sigmas for j in judged), default=None)}
        entries[rotation_key(name)] = to_entry(grams_per_rev_result(fit, by_speed),
                                               channel=name, model="grams_per_rev")
    notes, refused = apply_entries(settings, entries)
    if refused or any("not applied" in n for n in notes):
        raise RuntimeError(f"calibration not applied: {notes} {refused}")
    return {ch.name: ch for ch in settings.channel}, gates


def _stats(target: float, mass: list[float], dist: list[float]) -> dict[str, float]:
    rates = []
    for i in range(len(mass) - 1):
        area_ha = WIDTH_M * (dist[i + 1] - dist[i]) / 10_000
        rates.append((mass[i + 1] - mass[i]) / 1000 / area_ha)
    total = (mass[-1] - mass[0]) / 1000 / (WIDTH_M * (dist[-1] - dist[0]) / 10_000)
    return {
        "cv_pct": statistics.pstdev(rates) / statistics.fmean(rates) * 100,
        "bias_pct": (total - target) / target * 100,
        "mean_abs_dev_pct": statistics.fmean(abs(r - target) / target * 100 for r in rates),
    }


def one_draw(seed: int) -> dict[str, Any]:
    """One draw of paper B's dynamic test on drawn meters, the three strategies on the same
    meters and speed profile; returns per-channel figures.
    Seed 1 keeps the speed-wave phases of the earlier one-draw table; other seeds draw them."""
    rng = random.Random(seed)
    phase_rng = random.Random(f"phases:{seed}")
    phases = ((0.0, 1.0) if seed == 1
              else (phase_rng.uniform(0, 2 * math.pi), phase_rng.uniform(0, 2 * math.pi)))
    laws = {name: draw_meter(name, g, seed) for name, _n, _t, g in CHANNELS}
    nodes = {name: node for name, node, *_ in CHANNELS}
    targets = {name: t for name, _n, t, _g in CHANNELS}
    catalogue_g = {name: g for name, _n, _t, g in CHANNELS}
    # the rotation test runs on the meter itself (its own noise stream)
    runs = {name: rotation_runs(laws[name].plant(random.Random(seed * 100 + nodes[name] + 50)))
            for name in targets}
    sowgate, gates = calibrated_channels(runs)
    channels = {
        "sowgate": sowgate,
        "constant": {n: ch.model_copy(update={"grams_per_rev_curve": None})
                     for n, ch in sowgate.items()},
    }
    plants = {strat: {name: laws[name].plant(random.Random(seed * 100 + nodes[name]))
                      for name in targets} for strat in STRATEGIES}
    open_rpm = {
        name: target_shaft_rpm(targets[name], SPEED_KMH, WIDTH_M,
                               catalogue_g[name] * (1 + OPEN_LOOP_CAL_ERROR) * OUTLETS)
        for name in targets
    }
    sup = ChannelSupervisor(list(targets), start=0.0)
    alarms = 0
    dist = 0.0
    steps = round((WARMUP_S + RUN_S) / CONTROL_DT_S)
    per_window = round(WINDOW_S / CONTROL_DT_S)
    dists: list[float] = []
    mass: dict[str, dict[str, list[float]]] = {s: {n: [] for n in targets} for s in STRATEGIES}
    for k in range(steps):
        t = k * CONTROL_DT_S
        true_v = tractor_speed(t, rng, phases)
        measured_v = max(0.0, true_v + rng.gauss(0, 0.05))
        for name in targets:
            rpm = channel_target_rpm(sowgate[name], targets[name], measured_v, WIDTH_M)
            frame_id, data = cm.encode_command(cm.SpeedCommand(nodes[name], rpm, True, k % 256))
            cmd = cm.decode_command(frame_id, data)
            plants["sowgate"][name].command(cmd.target_rpm, cmd.enable, cmd.sequence)
            sup.command(name, cmd.target_rpm, t)
            const_rpm = channel_target_rpm(channels["constant"][name], targets[name],
                                           measured_v, WIDTH_M)
            cmd = cm.decode_command(*cm.encode_command(
                cm.SpeedCommand(nodes[name], const_rpm, True, k % 256)))
            plants["constant"][name].command(cmd.target_rpm, cmd.enable, cmd.sequence)
            plants["open_loop"][name].command(open_rpm[name], True, k % 256)
        for name in targets:
            for strat in STRATEGIES:
                plants[strat][name].advance(CONTROL_DT_S)
            status = cm.decode_status(*cm.encode_status(plants["sowgate"][name].status(
                nodes[name])))
            sup.feedback(name, status.measured_rpm, t + CONTROL_DT_S,
                         status.fault.name if status.faulted else None)
        alarms += sum(1 for a in sup.evaluate(t + CONTROL_DT_S) if a.active)
        dist += true_v / 3.6 * CONTROL_DT_S
        if (k + 1) % per_window == 0 and t + CONTROL_DT_S > WARMUP_S:
            dists.append(dist)
            for strat in STRATEGIES:
                for name in targets:
                    mass[strat][name].append(plants[strat][name].mass_g)
    result: dict[str, Any] = {"channels": {}, "alarms_closed_loop": alarms,
                              "window_s": WINDOW_S, "duration_s": RUN_S, "seed": seed}
    for name in targets:
        truth = plants["sowgate"][name]
        curve = sowgate[name].grams_per_rev_curve
        result["channels"][name] = {
            "target_kg_ha": targets[name],
            "meter": asdict(laws[name]),
            "true_g_per_rev_10": truth.per_rev_g(10.0),
            "true_g_per_rev_60": truth.per_rev_g(60.0),
            "fitted_g_per_rev": round(sowgate[name].grams_per_rev, 3),
            "fitted_curve": None if curve is None else [list(p) for p in curve],
            "calibration_problems": gates[name]["problems"],
            "constant_gate_problems": gates[name]["constant_gates"],
            "curve_worst_sigmas": gates[name]["worst_sigmas"],
            **{strat: _stats(targets[name], mass[strat][name], dists) for strat in STRATEGIES},
            "paper_cv_pct": PAPER_CV[name],
        }
    return result


def _workers() -> int:
    """Processes for the draws: ``SOWGATE_BENCH_WORKERS`` (default 2, as bench_rate; 1 runs
    them in this process)."""
    return max(1, int(os.environ.get("SOWGATE_BENCH_WORKERS", "2")))


def run_main_draws(n: int) -> list[dict[str, Any]]:
    """Seeds 1..n of the dynamic test, in a pool of ``_workers()`` processes."""
    seeds = list(range(1, n + 1))
    workers = _workers()
    if workers == 1:
        return [one_draw(s) for s in seeds]
    # spawn, not fork: ``python -m benchmarks`` runs this under a progress bar's thread, and
    # a forked child could inherit a lock that thread holds (as bench_rate)
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        return list(pool.map(one_draw, seeds))


def summarise(draws: list[dict[str, Any]]) -> dict[str, Any]:
    """Per channel and strategy: (median, p90, worst) of CV % and of |bias| % over the draws,
    the drawn meters' ranges, the rotation tests the CLI would have refused without
    ``--accept-poor-fit``, and each channel's verdict on p90 (sowgate: the g/rev curve)."""
    out: dict[str, Any] = {}
    for name, _node, target, g in CHANNELS:
        per = [d["channels"][name] for d in draws]
        changes = [c["true_g_per_rev_60"] / c["true_g_per_rev_10"] - 1.0 for c in per]
        ch: dict[str, Any] = {
            "target_kg_ha": target, "paper_g_per_rev": g, "paper_cv_pct": PAPER_CV[name],
            "g10_range": (min(c["true_g_per_rev_10"] for c in per),
                          max(c["true_g_per_rev_10"] for c in per)),
            "change_range_pct": (min(changes) * 100, max(changes) * 100),
            # the CLI's gate, on the curve that is saved: a run off the curve through the
            # others, or (fewer speeds) the constant's CV / R²
            "poor_fits": sum(1 for c in per if c["calibration_problems"]),
            "poor_fits_off_curve": sum(1 for c in per if any(
                "OFF_CURVE_SIGMAS" in p for p in c["calibration_problems"])),
            "poor_fits_worst_bias": max((abs(c["sowgate"]["bias_pct"]) for c in per
                                         if c["calibration_problems"]), default=None),
            # the gate before: the constant g/rev's line through the runs, whatever is saved
            "constant_gate_refusals": sum(1 for c in per if c.get("constant_gate_problems")),
            "constant_gate_worst_bias": max((abs(c["sowgate"]["bias_pct"]) for c in per
                                             if c.get("constant_gate_problems")),
                                            default=None),
            "curve_worst_sigmas": max((c["curve_worst_sigmas"] for c in per
                                       if c.get("curve_worst_sigmas") is not None),
                                      default=None),
        }
        for strat in STRATEGIES:
            ch[strat] = {"cv_pct": _dist([c[strat]["cv_pct"] for c in per]),
                         "bias_pct": _dist([c[strat]["bias_pct"] for c in per]),
                         "mean_abs_dev_pct": _dist([c[strat]["mean_abs_dev_pct"]
                                                    for c in per])}
        ch["cv_met"] = ch["sowgate"]["cv_pct"][1] <= PAPER_CV[name]
        ch["bias_met"] = ch["sowgate"]["bias_pct"][1] <= TARGET_BIAS_PCT
        out[name] = ch
    return out


def run(seed: int = 1) -> dict[str, Any]:
    """The dynamic test over DRAWS independent draws (seeds 1..DRAWS; ``seed`` is the draw
    whose alarms and window figures are kept as its one-draw detail), then the g/rev draws;
    returns the summaries and the markdown."""
    draws = run_main_draws(max(DRAWS, seed))
    result: dict[str, Any] = {
        "draws_n": len(draws), "window_s": WINDOW_S, "duration_s": RUN_S,
        "alarms_closed_loop": sum(d["alarms_closed_loop"] for d in draws),
        "channels": summarise(draws), "seed": seed,
        "one_draw": draws[seed - 1],
    }
    result.update(run_draws())
    result["markdown"] = markdown(result) + "\n\n" + "\n".join(draws_markdown(result))
    result.pop("draws")  # keyed by tuples: the figures are in the markdown and the p90s
    return result


# ---- issue 25: meters whose g/rev falls with shaft speed, over independent draws ----------

DRAWS = int(os.environ.get("SOWGATE_BENCH_DRAWS", "20"))
DRAW_RUN_S = 60.0
DRAW_INNER_DT_S = 0.005  # the plant's cycle for the draws (the published run above: 1 ms)
FALLS = (0.0, 0.10, 0.20)  # g/rev fall from 10 to 60 r/min
DRAW_SPEED_RANGE_KMH = (3.5, 5.5)  # shaft speeds ~13..60 r/min: within the test's range
LOT_CHANGE = 0.03  # a new seed lot after the rotation test, ± this
TARGET_BIAS_PCT = 1.0


def _draw_plant(g: float, fall: float, shape: float, lot: float, seed: int) -> MeterPlant:
    return MeterPlant(g, OUTLETS, rng=random.Random(seed), fill_fall=fall, fill_shape=shape,
                      lot_factor=lot, inner_dt_s=DRAW_INNER_DT_S)


def rotation_runs(plant: MeterPlant) -> list[RotationRun]:
    """Paper B's rotation test (30 s at 10..60 r/min, weighed per outlet) on the plant."""
    runs = []
    for n in (10.0, 20.0, 30.0, 40.0, 50.0, 60.0):
        for i in range(20):  # settle 2 s
            plant.command(n, True, i)
            plant.advance(CONTROL_DT_S)
        m0, r0 = plant.mass_g, plant.revs
        for i in range(300):
            plant.command(n, True, i % 256)
            plant.advance(CONTROL_DT_S)
        turns = round((plant.revs - r0) * 2.0) / 2.0  # counted to the nearest half turn
        runs.append(RotationRun(turns / 0.5, 30.0, (plant.mass_g - m0) / plant.outlets,
                                set_rpm=n))
    plant.command(0.0, False, 0)
    plant.advance(1.0)
    return runs


def draw(fall: float, index: int, lot_change: float = 0.0) -> dict[str, dict[str, float]]:
    """One independent draw: each channel's meter (g/rev ±5 %, fall shape), the tractor's mean
    speed, the noise; rotation test, then one run with the constant paper-B g/rev and one with
    the g/rev curve (same speed profile). Returns channel -> strategy -> bias %."""
    rng = random.Random(f"mc:{fall}:{index}:{lot_change}")
    mean_kmh = rng.uniform(*DRAW_SPEED_RANGE_KMH)
    out: dict[str, dict[str, float]] = {}
    for name, node, target, g_nominal in CHANNELS:
        g = g_nominal * (1.0 + rng.uniform(-GPR_SPREAD, GPR_SPREAD))
        shape = rng.uniform(*FILL_SHAPE_RANGE)
        seed = rng.randrange(2**31)
        cal = rotation_runs(_draw_plant(g, fall, shape, 1.0, seed))
        constant = grams_per_rev(cal).grams_per_rev
        curve = grams_per_rev_by_speed(cal)
        lot = 1.0 + lot_change * (1 if rng.random() < 0.5 else -1)
        strategies = {
            "constant": ChannelSection(name=name, target_rate_kg_ha=target, node_id=node,
                                       grams_per_rev=constant, outlets=OUTLETS),
            "curve": ChannelSection(name=name, target_rate_kg_ha=target, node_id=node,
                                    grams_per_rev=constant, outlets=OUTLETS,
                                    grams_per_rev_curve=curve),
        }
        out[name] = {}
        for key, ch in strategies.items():
            plant = _draw_plant(g, fall, shape, lot, seed + 1)
            speed_rng = random.Random(seed + 2)  # the same speed profile for both
            dist = mass0 = 0.0
            steps = round((WARMUP_S + DRAW_RUN_S) / CONTROL_DT_S)
            for k in range(steps):
                t = k * CONTROL_DT_S
                true_v = tractor_speed(t, speed_rng) * mean_kmh / SPEED_KMH
                measured_v = true_v + speed_rng.gauss(0, 0.05)
                rpm = channel_target_rpm(ch, target, max(0.0, measured_v), WIDTH_M)
                plant.command(rpm, True, k % 256)
                plant.advance(CONTROL_DT_S)
                if t + CONTROL_DT_S > WARMUP_S:
                    dist += true_v / 3.6 * CONTROL_DT_S
                elif t + 2 * CONTROL_DT_S > WARMUP_S:
                    mass0 = plant.mass_g
            applied = (plant.mass_g - mass0) / 1000 / (WIDTH_M * dist / 10_000)
            out[name][key] = (applied / target - 1.0) * 100.0
    return out


def _dist(xs: list[float]) -> tuple[float, float, float]:
    a = sorted(abs(x) for x in xs)
    p90 = statistics.quantiles(a, n=10, method="inclusive")[-1] if len(a) > 1 else a[0]
    return statistics.median(a), p90, max(xs, key=abs)


def draws_markdown(result: dict[str, Any]) -> list[str]:
    rows = result["draws"]
    lines = [
        "#### Meters whose g/rev falls with shaft speed (issue 25), over independent draws\n",
        f"{DRAWS} draws per row. Each draw: every channel's meter from `simulator.can_pid."
        "MeterPlant` with g/rev at 10 r/min ±5 % of paper B's, falling by the row's fall from "
        "10 to 60 r/min along a power law of drawn exponent 0.6–1.6 (not the controller's "
        "piecewise cubic), the tractor's mean speed drawn in 3.5–5.5 km/h (shaft speeds "
        "~13–60 r/min across the channels), its own noise; paper B's rotation test on it "
        "(30 s at 10…60 r/min, turns counted to ½ turn), then a "
        f"{DRAW_RUN_S:g} s run with the constant g/rev (paper B: mean of the runs ≥ 20 r/min) "
        "and one with the g/rev curve (`grams_per_rev_by_speed`, inverted by "
        "`channel_target_rpm`), same speed profile (plant cycle "
        f"{DRAW_INNER_DT_S * 1000:g} ms). Cells: bias over the run, median |bias| / **p90 "
        "|bias|** / worst, % (target: p90 ≤ 1 % with g/rev falling 20 %). The g/rev fall is "
        "assumed (paper B calibrates at 10…60 r/min and reports a g/rev per channel; the "
        "10–20 % is the issue's), not measured.\n",
        "| g/rev fall 10→60 r/min | seed lot | channel | constant g/rev | g/rev curve |",
        "|---|---|---|---|---|",
    ]
    for (fall, lot), per in rows.items():
        for name in per:
            c = _dist(per[name]["constant"])
            v = _dist(per[name]["curve"])
            lines.append(
                f"| {fall:.0%} | {lot} | {name} | {c[0]:.2f} / {c[1]:.2f} / {c[2]:+.2f} | "
                f"{v[0]:.2f} / {v[1]:.2f} / {v[2]:+.2f} |")
    lines.append("")
    worst = result["draws_p90_curve_fall20"]
    lines.append(f"- bias p90 with g/rev falling 20 %, g/rev curve, worst channel: "
                 f"{worst:.2f} % — {'met' if worst <= TARGET_BIAS_PCT else '**NOT met**'} "
                 f"(target ≤ {TARGET_BIAS_PCT:g} %). A seed lot changed by ±"
                 f"{LOT_CHANGE:.0%} after the rotation test is a bias no curve removes: only a "
                 "new rotation test with the new lot does.")
    return lines


def run_draws() -> dict[str, Any]:
    rows: dict[tuple[float, str], dict[str, dict[str, list[float]]]] = {}
    cases = [(f, "same", 0.0) for f in FALLS] + [(0.20, f"±{LOT_CHANGE:.0%}", LOT_CHANGE)]
    for fall, lot_label, lot in cases:
        per: dict[str, dict[str, list[float]]] = {}
        for i in range(DRAWS):
            for name, res in draw(fall, i, lot).items():
                for key, b in res.items():
                    per.setdefault(name, {}).setdefault(key, []).append(b)
        rows[(fall, lot_label)] = per
    p90 = max(_dist(rows[(0.20, "same")][n]["curve"])[1] for n in rows[(0.20, "same")])
    p90_const = max(_dist(rows[(0.20, "same")][n]["constant"])[1]
                    for n in rows[(0.20, "same")])
    return {"draws": rows, "draws_p90_curve_fall20": p90,
            "draws_p90_constant_fall20": p90_const}


def _cell(d: tuple[float, float, float], signed: bool = False) -> str:
    worst = f"{d[2]:+.2f}" if signed else f"{abs(d[2]):.2f}"
    return f"{d[0]:.2f} / **{d[1]:.2f}** / {worst}"


def markdown(result: dict[str, Any]) -> str:
    n = result["draws_n"]
    chans = result["channels"]
    lo_change = min(c["change_range_pct"][0] for c in chans.values())
    hi_change = max(c["change_range_pct"][1] for c in chans.values())
    lines = [
        f"Paper B's dynamic test over {n} independent draws (seeds 1…{n}). Each draw gives "
        "every channel's meter its own law, unlike the controller's model: g/rev at 10 r/min "
        f"within ±{GPR_SPREAD * 100:g} % of paper B's, a change from 10 to 60 r/min drawn "
        f"in {CHANGE_RANGE[0] * 100:+g}…{CHANGE_RANGE[1] * 100:+g} % (drawn: {lo_change:+.1f}…"
        f"{hi_change:+.1f} %), reached along a power law of exponent "
        f"{FILL_SHAPE_RANGE[0]:g}–{FILL_SHAPE_RANGE[1]:g} from a knee drawn in "
        f"{KNEE_RANGE_RPM[0]:g}–{KNEE_RANGE_RPM[1]:g} r/min (cells full up to it: a kink "
        "the curve's knots need not sit on), plus the plant's flute pulsation and cell-fill "
        "spread, its own noise, tractor speed noise, GNSS noise and speed-wave phases. These "
        "ranges are assumed, not measured (issue 25's 10–20 % fall; a rise up to 5 % so the "
        "sign is not given away). On each: paper B's rotation test (30 s at 10…60 r/min, "
        "the shaft's turns counted to ½ turn), fitted and saved as `sowgate calibrate "
        "rotation` saves it (`grams_per_rev_by_speed`: the g/rev curve) and laid over the "
        "config as the daemon does (`apply_entries`); then "
        f"{result['duration_s']:g} s at 5 km/h (±6 %/±3 % speed waves) after {WARMUP_S:g} s "
        f"warm-up, {result['window_s']:g}-s windows, sowgate, the sensitivity and the open "
        "loop on the same meters and speed profile. Cells: median / **p90** / worst over the "
        "draws; CV of the 1-s applied rates, |bias| of the run's total against target (worst "
        "shown with its sign).\n",
        "| channel | target kg/ha | g/rev at 10 r/min, drawn (paper B) "
        "| g/rev change 10→60 r/min, drawn | sowgate CV % "
        "| sowgate abs bias % | open-loop CV % | open-loop abs bias % | paper CV % "
        "| sowgate p90 CV ≤ paper | sowgate p90 abs bias ≤ 1 % |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def verdict(ok: bool) -> str:
        return "met" if ok else "**NOT met**"

    for name, c in chans.items():
        s, o = c["sowgate"], c["open_loop"]
        lo, hi = c["g10_range"]
        clo, chi = c["change_range_pct"]
        lines.append(
            f"| {name} | {c['target_kg_ha']:g} | {lo:.2f}–{hi:.2f} ({c['paper_g_per_rev']:.2f}) "
            f"| {clo:+.1f}…{chi:+.1f} % "
            f"| {_cell(s['cv_pct'])} | {_cell(s['bias_pct'], True)} "
            f"| {_cell(o['cv_pct'])} | {_cell(o['bias_pct'], True)} "
            f"| {c['paper_cv_pct']:.1f} | {verdict(c['cv_met'])} | {verdict(c['bias_met'])} |"
        )
    worst_cv = max(chans, key=lambda k: chans[k]["sowgate"]["cv_pct"][1]
                   / chans[k]["paper_cv_pct"])
    worst_bias = max(chans, key=lambda k: chans[k]["sowgate"]["bias_pct"][1])
    all_met = all(c["cv_met"] and c["bias_met"] for c in chans.values())
    poor = sum(c["poor_fits"] for c in chans.values())
    poor_curve = sum(c["poor_fits_off_curve"] for c in chans.values())
    poor_bias = [c["poor_fits_worst_bias"] for c in chans.values()
                 if c["poor_fits_worst_bias"] is not None]
    poor_note = ("" if not poor_bias else
                 f"; those channels' worst |bias|: {max(poor_bias):.2f} %")
    old_gate = sum(c.get("constant_gate_refusals", 0) for c in chans.values())
    old_bias = [c["constant_gate_worst_bias"] for c in chans.values()
                if c.get("constant_gate_worst_bias") is not None]
    old_note = ("" if not old_bias else
                f", channels that sow within {max(old_bias):.2f} % on the curve")
    sigmas = [c["curve_worst_sigmas"] for c in chans.values()
              if c.get("curve_worst_sigmas") is not None]
    sigma_note = ("" if not sigmas else
                  f"; the furthest any speed came from the curve through the others: "
                  f"{max(sigmas):.1f} σ (the gate: {OFF_CURVE_SIGMAS:g} σ)")
    lines.append("")
    lines.append(
        f"- Target (judged on p90, every channel): sowgate CV ≤ paper B's CV for the channel "
        f"and |bias| ≤ {TARGET_BIAS_PCT:g} % — {'met' if all_met else '**NOT met**'}. Closest "
        f"to its CV target: {worst_cv}, p90 CV "
        f"{chans[worst_cv]['sowgate']['cv_pct'][1]:.2f} % against "
        f"{chans[worst_cv]['paper_cv_pct']:.1f} %; largest p90 |bias|: {worst_bias}, "
        f"{chans[worst_bias]['sowgate']['bias_pct'][1]:.2f} %. Rotation tests the CLI "
        f"refuses without `--accept-poor-fit` (applied here as with it), judged as it judges "
        f"them on the g/rev curve it saves (each speed against the curve through the others, "
        f"the 10 outlets' catch on its default ±{DEFAULT_SCALE_G:g} g scale, turns to ±¼): "
        f"{poor} of {n * len(chans)} ({poor_curve} with a run off the curve){poor_note}"
        f"{sigma_note}. The constant g/rev's CV / R² gates, which judged these tests before, "
        f"refuse {old_gate} of them{old_note}. Open loop = fixed shaft speed from nominal "
        "5 km/h and paper B's g/rev + 5 % as a catalogue value (its bias is that 5 % plus "
        "the drawn meter's own g/rev at its speed). The plant's pulsation and spread are "
        "assumptions, not measurements: this compares control strategies on plants unlike "
        "the controller's model; it does not predict a field CV.")
    one = result["one_draw"]
    one_cv = ", ".join(f"{k} {v['sowgate']['cv_pct']:.2f}"
                       for k, v in one["channels"].items())
    lines.append(
        f"- Alarms raised in closed loop over all {n} draws: {result['alarms_closed_loop']}. "
        f"One-draw detail (seed {result['seed']}, the speed-wave phases of the earlier "
        f"one-draw table): sowgate CV % {one_cv}.")
    lines += [
        "",
        "Sensitivity, same draws, meters and speed profiles: the channel sowing on the same "
        "rotation test's constant g/rev (paper B's mean of the runs ≥ 20 r/min; what a test "
        "at fewer than 5 speeds, or a calibration file from before the curve, gives).\n",
        "| channel | constant g/rev: CV % | constant g/rev: abs bias % "
        "| p90 abs bias ≤ 1 % |",
        "|---|---|---|---|",
    ]
    for name, c in chans.items():
        k = c["constant"]
        lines.append(f"| {name} | {_cell(k['cv_pct'])} | {_cell(k['bias_pct'], True)} "
                     f"| {verdict(k['bias_pct'][1] <= TARGET_BIAS_PCT)} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(run()["markdown"])
