"""``sowgate calibrate rotation|speed|tilt|undo|show``: field calibration from the cab.

The timed runs show a rich progress bar; the operator then weighs the catch and types the
mass (or passes ``--mass`` for scripted use). Which mass is asked for is said in ``--help``
and in every prompt: the catch of ``--outlets-weighed N`` outlets (default all of the
channel's); g/rev is stored per outlet, paper A's eq. 6 for the whole machine. A fit outside
the quality gates (``fits.MAX_GPR_CV_PCT`` ...) or a result more than ``fits.LARGE_CHANGE_PCT``
from the value it replaces is shown and refused unless ``--accept-poor-fit`` /
``--accept-large-change``. With ``--drive can`` the CLI itself commands a
``can_pid`` channel's controller over CAN at each speed (stop the daemon first: one owner per
bus); with ``--drive manual`` (default) the operator runs the meter from the HMI and the CLI
only times. Results go to ``<state_dir>/calibration.json`` (previous value kept for undo).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import itertools
import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.prompt import FloatPrompt
from rich.table import Table

from drivers.errors import DriverError
from gateway.calibration import fits as cal
from gateway.config import ConfigError, Settings, load_config, state_dir
from gateway.core.errors import GatewayError

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILED = 1
DEFAULT_B_SPEEDS = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)  # paper B
DEFAULT_B_SECONDS = 30.0
DEFAULT_A_SECONDS = 60.0  # paper A weighs 60 s runs
SPEED_SOURCES = ("radar", "gnss", "isobus")
RUN_DOWN_MAX_S = 3.0  # after a CAN-driven run, follow the shaft until it stops (at most)
PROGRESS_EVERY_S = 10.0  # without a terminal: a "10 s of 30 s" line this often


def _floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more (got {value})")
    return value


def add_calibration_commands(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``calibrate`` and its sub-commands on the daemon's argparse subparsers."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "calibrate", help="rotation test, speed calibration, inclinometer zero, undo"
    )
    p.add_argument("--config", default=argparse.SUPPRESS, help="sowgate TOML config")
    p.add_argument("--state-dir", default=None, help="where calibration.json lives")
    sub = p.add_subparsers(dest="calibrate_command", required=True)

    r = sub.add_parser("rotation", help="rotation (weighing) test of one metering channel")
    r.add_argument("--channel", required=True, help="channel name (or crop for paper A)")
    r.add_argument("--model", choices=("grams_per_rev", "paper_a"), default="grams_per_rev")
    r.add_argument("--speeds", type=_floats, default=None,
                   help="shaft r/min set points (paper B: 10,20,...,60)")
    r.add_argument("--duties", type=_floats, default=None, help="paper A: PWM duty %% per run")
    r.add_argument("--rpm", type=_floats, default=None,
                   help="paper A: measured shaft r/min per run (default: the set speeds)")
    r.add_argument("--seconds", type=float, default=None, help="run length (B 30 s, A 60 s)")
    r.add_argument("--mass", type=_floats, default=None,
                   help="weighed grams per run, in run order (skips the prompts): the catch "
                   "of --outlets-weighed outlets together")
    r.add_argument("--outlets-weighed", type=_positive_int, default=None, metavar="N",
                   help="how many outlets each weighed mass comes from (default: all of the "
                   "channel's [[channel]] outlets in --config, 1 without one; paper A: all "
                   "machine.rows). g/rev is stored "
                   "per outlet; paper A's eq. 6 is scaled to the whole machine by rows/N")
    r.add_argument("--accept-poor-fit", action="store_true",
                   help="save a fit that fails a quality gate (CV, R², set-point span); "
                   "logged and recorded in the entry")
    r.add_argument("--accept-large-change", action="store_true",
                   help=f"save a result more than {cal.LARGE_CHANGE_PCT:g} percent away from the "
                   "value it replaces (the saved one, else the config's)")
    r.add_argument("--min-stable-rpm", type=float, default=cal.PAPER_B_MIN_STABLE_RPM)
    r.add_argument("--working-range", type=_floats, default=None, help="lo,hi r/min")
    r.add_argument("--drive", choices=("manual", "can"), default="manual")
    r.add_argument("--no-wait", action="store_true", help="do not time the runs (masses known)")

    s = sub.add_parser("speed", help="drive a measured distance, store a correction factor")
    s.add_argument("--source", required=True, choices=SPEED_SOURCES, help="speed source")
    s.add_argument("--distance", type=float, default=50.0, help="measured distance (m)")
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--integrated-m", type=float, help="distance the source reported (m)")
    g.add_argument("--samples", type=Path,
                   help="CSV of time_s,speed_kmh logged at a steady interval between the "
                   "start and finish marks (half an interval of travel is added at each end)")

    t = sub.add_parser("tilt", help="inclinometer zero (level) or critical angle (lowered)")
    t.add_argument("--mode", choices=("level", "lowered"), required=True)
    t.add_argument("--sensor", default="inclinometer")
    t.add_argument("--readings", type=_floats, default=None, help="angles in degrees")

    ps = sub.add_parser(
        "positions",
        help="fit the seed position model (delay, lever arm) to surveyed seeds",
        description="Match surveyed seeds to stored records, fit the along-track delay and "
        "the outlets' lever arm by robust least squares, print the errors before and after "
        "(mean, SD, CV) and save the fit (undo: --key positions.survey). Needs at least "
        "20 seeds sown over 3 km/h of speed spread (or --lever-only).",
    )
    ps.add_argument("--survey", type=Path, required=True,
                    help="CSV with a header: id (record id) or utc, lat, lon, optional row")
    ps.add_argument("--lever-only", action="store_true",
                    help="keep the delay, fit the lever arm alone (seeds of one speed)")
    ps.add_argument("--accept-poor-fit", action="store_true",
                    help="save a fit that moves the outlets > 0.5 m or does not help")

    u = sub.add_parser("undo", help="restore the value replaced by the last calibration")
    u.add_argument("--key", default=None,
                   help="e.g. rotation.seed, speed.radar, tilt.inclinometer, positions.survey")

    sub.add_parser("show", help="print the stored calibration")
    return p


def _settings(args: argparse.Namespace) -> Settings | None:
    path = getattr(args, "config", None)
    return load_config(path) if path else None


def _store(args: argparse.Namespace) -> cal.CalibrationStore:
    return cal.CalibrationStore(args.state_dir or state_dir())


def _masses(args: argparse.Namespace, n: int, console: Console,
            ask: Callable[[str], float], outlets_weighed: int = 1) -> list[float]:
    if args.mass is not None:
        if len(args.mass) != n:
            raise cal.CalibrationError(f"--mass has {len(args.mass)} values for {n} runs")
        return list(args.mass)
    return [ask(f"weighed mass of run {i + 1} (g, mass from {outlets_weighed} outlet(s))")
            for i in range(n)]


@dataclass(frozen=True)
class Outlets:
    """Which catch the masses are: ``weighed`` outlets of ``total`` (None: not known)."""

    weighed: int
    total: int | None

    def describe(self) -> str:
        of = f" of {self.total}" if self.total is not None else (
            "; the outlet count is unknown without --config")
        return f"mass from {self.weighed} outlet(s){of}"


def _outlets(args: argparse.Namespace, settings: Settings | None) -> Outlets:
    """The outlets the weighed masses come from, checked against the config."""
    name = args.channel
    if args.model == "paper_a":
        if settings is None:
            if args.outlets_weighed is not None:
                raise cal.CalibrationError(
                    "--outlets-weighed with --model paper_a needs --config: eq. 6 is the whole "
                    "machine's discharge, scaled by machine.rows"
                )
            return Outlets(1, None)
        total = settings.machine.rows
        what = f"machine.rows is {total}"
    else:
        ch = next((c for c in settings.channel if c.name == name), None) if settings else None
        if ch is None:
            return Outlets(args.outlets_weighed or 1, None)
        total = ch.outlets
        what = f"channel {name!r} has {total} outlets"
    weighed = args.outlets_weighed or total
    if weighed > total:
        raise cal.CalibrationError(f"--outlets-weighed {weighed}: {what}")
    return Outlets(weighed, total)


def _check_quality(problems: list[str], args: argparse.Namespace, console: Console) -> None:
    """Refuse a fit that fails a quality gate, unless ``--accept-poor-fit`` (then logged)."""
    if not problems:
        return
    if not args.accept_poor_fit:
        raise cal.CalibrationError(
            "poor fit, nothing saved:\n  - " + "\n  - ".join(problems)
            + "\n  (--accept-poor-fit saves it anyway)"
        )
    for problem in problems:
        log.warning("calibration rotation.%s saved despite a poor fit (--accept-poor-fit): %s",
                    args.channel, problem)
        console.print(f"[yellow]accepted with --accept-poor-fit:[/yellow] {escape(problem)}")


def _check_change(rows: Sequence[tuple[str, float, float]], source: str,
                  args: argparse.Namespace, console: Console) -> bool:
    """Show the result beside the value it replaces; refuse a change over the threshold.

    Returns True when a large change was accepted with ``--accept-large-change``."""
    if not rows:
        return False
    changes = [cal.change_pct(new, old) for _, old, new in rows]
    table = _table(f"rotation.{args.channel}: new result beside the {source} value it replaces",
                   ("value", f"replaces ({source})", "new", "change %"),
                   [(what, f"{old:.2f}", f"{new:.2f}", f"{c:+.1f}")
                    for (what, old, new), c in zip(rows, changes, strict=True)])
    console.print(table)
    worst = max(abs(c) for c in changes)
    if worst <= cal.LARGE_CHANGE_PCT:
        return False
    if not args.accept_large_change:
        raise cal.CalibrationError(
            f"the result is {worst:.0f} % away from the {source} value it replaces (more than "
            f"{cal.LARGE_CHANGE_PCT:g} %): check the outlets weighed (--outlets-weighed) and "
            "the masses; --accept-large-change saves it anyway (if the saved value is the "
            f"mistake: sowgate calibrate undo --key rotation.{args.channel}). Nothing saved"
        )
    log.warning("calibration rotation.%s: %.0f %% change accepted (--accept-large-change)",
                args.channel, worst)
    return True


@dataclass
class CanRun:
    """One rotation-test run driven over CAN in a worker thread (the progress bar keeps
    updating in the main one); ``revolutions`` is the shaft's measured turns, run-down
    included, integrated from the controller's status frames."""

    thread: threading.Thread | None = None
    revolutions: float | None = None
    error: BaseException | None = None

    def join(self) -> None:
        if self.thread is not None:
            self.thread.join()
        if self.error is not None:
            raise self.error


def _timed_runs(labels: Sequence[str], seconds: float, console: Console,
                drive: Callable[[int, float], CanRun] | None, wait: bool) -> list[CanRun]:
    runs: list[CanRun] = []
    if not wait:
        return runs
    if not console.is_terminal:
        # rich's bar is drawn only on a terminal: piped or logged, it printed nothing until
        # every run was over (6 x 30 s). One line per event instead.
        return _timed_runs_plain(labels, seconds, console, drive)
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeRemainingColumn(),
                  console=console, transient=False) as progress:
        for i, label in enumerate(labels):
            task = progress.add_task(f"run {i + 1}: {label}", total=seconds)
            start = time.monotonic()
            run = drive(i, seconds) if drive is not None else None
            while (elapsed := time.monotonic() - start) < seconds:
                progress.update(task, completed=elapsed)
                time.sleep(min(0.2, seconds - elapsed))
            progress.update(task, completed=seconds)
            if run is not None:
                run.join()  # the shaft has run down
                runs.append(run)
    return runs


def _timed_runs_plain(labels: Sequence[str], seconds: float, console: Console,
                      drive: Callable[[int, float], CanRun] | None) -> list[CanRun]:
    """The timed runs for a console that is not a terminal: a line when each run starts,
    every ``PROGRESS_EVERY_S`` while it runs, and when it is done."""
    runs: list[CanRun] = []
    n = len(labels)
    for i, label in enumerate(labels):
        console.print(f"run {i + 1}/{n}: {escape(label)}: started", highlight=False)
        start = time.monotonic()
        run = drive(i, seconds) if drive is not None else None
        next_report = PROGRESS_EVERY_S
        while (elapsed := time.monotonic() - start) < seconds:
            if elapsed >= next_report:
                console.print(f"run {i + 1}/{n}: {next_report:g} s of {seconds:g} s",
                              highlight=False)
                next_report += PROGRESS_EVERY_S
            time.sleep(min(0.2, seconds - elapsed, max(0.0, next_report - elapsed)))
        if run is not None:
            run.join()  # the shaft has run down
            runs.append(run)
        console.print(f"run {i + 1}/{n}: done", highlight=False)
    return runs


def shaft_revolutions(samples: Sequence[tuple[float, float]]) -> float:
    """Turns from (time s, measured r/min) status samples (trapezoid)."""
    return sum((t1 - t0) * (r0 + r1) / 2 / 60.0
               for (t0, r0), (t1, r1) in itertools.pairwise(samples))


def _can_driver(settings: Settings | None, channel: str,
                speeds: Sequence[float]) -> Callable[[int, float], CanRun]:
    """Drive a can_pid channel's controller at each set speed for the run's duration."""
    from drivers.can_bus import CanBus, MeteringCanLink

    if settings is None:
        raise cal.CalibrationError("--drive can needs --config (CAN bus and channel node)")
    ch = next((c for c in settings.channel if c.name == channel and c.drive == "can_pid"), None)
    if ch is None:
        raise cal.CalibrationError(f"no can_pid channel named {channel!r} in the config")
    node = ch.node_id

    async def run(i: int, seconds: float, result: CanRun) -> None:
        can = settings.can
        loop = asyncio.get_running_loop()
        samples: list[tuple[float, float]] = []
        async with CanBus(can.interface, can.channel, can.bitrate) as bus:
            link = MeteringCanLink(bus, [node], command_hz=can.command_hz)
            link.set_target(node, speeds[i])
            task = asyncio.create_task(
                link.run(lambda st, t: samples.append((t, st.measured_rpm))),
                name="calibrate-drive",
            )
            try:
                await asyncio.sleep(seconds)
                link.stop_all()
                # what the shaft delivers while running down lands in the catch too
                stopped_at, deadline = time.monotonic(), loop.time() + RUN_DOWN_MAX_S
                while loop.time() < deadline:
                    await asyncio.sleep(0.1)
                    if samples and samples[-1][0] > stopped_at and samples[-1][1] < 0.5:
                        break
            finally:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
                link.stop_all()
                with contextlib.suppress(DriverError):
                    await link.send_commands()
        result.revolutions = shaft_revolutions(samples) if len(samples) >= 2 else None

    def drive(i: int, seconds: float) -> CanRun:
        result = CanRun()

        def target() -> None:
            try:
                asyncio.run(run(i, seconds, result))
            except BaseException as exc:  # handed to the main thread by join()
                result.error = exc

        result.thread = threading.Thread(target=target, name=f"calibrate-run-{i + 1}")
        result.thread.start()
        return result

    return drive


def _table(title: str, headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> Table:
    table = Table(title=title)
    for h in headers:
        table.add_column(h)
    for row in rows:
        table.add_row(*(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row))
    return table


def _check_rotation_target(settings: Settings | None, name: str, model: str) -> None:
    """With a config, refuse a name the daemon would not apply *before* minutes of runs."""
    if settings is None:
        return
    channels = {c.name: c for c in settings.channel}
    if model == "paper_a":
        ch = channels.get(name)
        if name in settings.control.crops or (ch is not None and ch.drive == "pwm_modbus"):
            return
        known = sorted({*settings.control.crops, *(
            c.name for c in settings.channel if c.drive == "pwm_modbus")})
        raise cal.CalibrationError(
            f"paper_a rotation of {name!r}: not a crop or pwm_modbus channel ({', '.join(known)})"
        )
    if name not in channels:
        names = ", ".join(sorted(channels)) or "none configured"
        raise cal.CalibrationError(f"no [[channel]] named {name!r} (channels: {names})")
    if channels[name].drive != "can_pid":
        raise cal.CalibrationError(
            f"channel {name!r} is pwm_modbus: its rotation test is --model paper_a"
        )


def _previous_gpr(store: cal.CalibrationStore, settings: Settings | None,
                  name: str) -> tuple[float, str] | None:
    """The per-outlet g/rev a new result replaces: the saved one, else the config's."""
    entry = store.get(f"rotation.{name}")
    if entry is not None and entry.get("model") == "grams_per_rev":
        return float(entry["result"]["grams_per_rev"]), "calibration"
    ch = next((c for c in settings.channel if c.name == name), None) if settings else None
    return (ch.grams_per_rev, "config") if ch is not None else None


def _previous_paper_a(store: cal.CalibrationStore, settings: Settings | None,
                      name: str) -> tuple[dict[str, float], dict[str, float], str] | None:
    """Eq. 5 and eq. 6 coefficients a new paper-A fit replaces: saved, else the config's."""
    entry = store.get(f"rotation.{name}")
    if entry is not None and entry.get("model") == "paper_a":
        result = entry["result"]
        return dict(result["motor"]), dict(result["meter"]), "calibration"
    if settings is None:
        return None
    crop_name = name if name in settings.control.crops else next(
        (c.product for c in settings.channel if c.name == name and c.drive == "pwm_modbus"), None)
    crop = settings.control.crops.get(crop_name) if crop_name is not None else None
    if crop is None:
        return None
    motor = {"slope": crop.motor_slope, "intercept": crop.motor_intercept}
    meter = {"a": crop.meter_a, "b": crop.meter_b, "c": crop.meter_c}
    return motor, meter, "config"


def _saved(console: Console, key: str, stored: str) -> None:
    console.print(
        f"saved {key}: {stored}. The daemon applies it at its next start (restart it: "
        f"`systemctl restart sowgate`); `sowgate calibrate undo --key {key}` restores the "
        "value it replaced."
    )


def _rotation(args: argparse.Namespace, console: Console, ask: Callable[[str], float]) -> int:
    settings = _settings(args)
    _check_rotation_target(settings, args.channel, args.model)
    outlets = _outlets(args, settings)
    store = _store(args)
    key = f"rotation.{args.channel}"
    console.print(f"masses asked for: the catch of each run, {outlets.describe()}")
    if args.model == "grams_per_rev":
        speeds = args.speeds or list(DEFAULT_B_SPEEDS)
        seconds = args.seconds or DEFAULT_B_SECONDS
        drive = _can_driver(settings, args.channel, speeds) if args.drive == "can" else None
        driven = _timed_runs([f"{n:g} r/min for {seconds:g} s" for n in speeds], seconds,
                             console, drive, not args.no_wait)
        weighed = _masses(args, len(speeds), console, ask, outlets.weighed)
        masses = [m / outlets.weighed for m in weighed]  # per outlet
        rpm = list(speeds)
        if driven:
            # the shaft's measured turns, spin-up and run-down included, not the set point
            for i, run in enumerate(driven):
                if not run.revolutions:
                    raise cal.CalibrationError(
                        f"run {i + 1}: no shaft feedback from the controller; nothing saved"
                    )
                rpm[i] = run.revolutions / (seconds / 60.0)
            console.print(_table("measured shaft speed", ("set r/min", "effective r/min"),
                                 list(zip(speeds, rpm, strict=True))))
        runs = [cal.RotationRun(n, seconds, m, set_rpm=s if driven else None)
                for n, m, s in zip(rpm, masses, speeds, strict=True)]
        fit = cal.grams_per_rev(runs, args.min_stable_rpm)
        rows: list[tuple[Any, ...]] = [
            (r.rpm, r.mass_g * outlets.weighed, g, res) for r, g, res in
            zip(fit.used, fit.per_run, fit.residuals_g_min, strict=True)]
        rows += [(r.rpm, r.mass_g * outlets.weighed, "excluded (unstable)", "")
                 for r in fit.excluded]
        console.print(_table(f"rotation test {args.channel}", (
            "r/min", f"g weighed ({outlets.weighed} outlet(s))", "g/rev per outlet",
            "residual g/min per outlet"), rows))
        console.print(f"g/rev = {fit.grams_per_rev:.2f}  CV {fit.cv_pct:.2f} %  R² {fit.r2:.4f}")
        console.print(f"{fit.grams_per_rev:.2f} g/rev per outlet ({outlets.describe()})")
        problems = cal.grams_per_rev_problems(fit)
        _check_quality(problems, args, console)
        previous = _previous_gpr(store, settings, args.channel)
        large = False
        if previous is not None:
            large = _check_change([("g/rev per outlet", previous[0], fit.grams_per_rev)],
                                  previous[1], args, console)
        replaces = (None if previous is None
                    else {"grams_per_rev": previous[0], "from": previous[1]})
        store.save(key, cal.to_entry(
            fit, channel=args.channel, model="grams_per_rev",
            outlets_weighed=outlets.weighed, outlets=outlets.total, weighed_mass_g=weighed,
            replaces=replaces, accepted_poor_fit=problems,
            accepted_large_change=large))
        _saved(console, key, f"{fit.grams_per_rev:.2f} g/rev per outlet")
        return EXIT_OK
    # paper A: duty -> speed line and speed -> rate quadratic
    if args.duties is None:
        raise cal.CalibrationError("paper_a rotation needs --duties (PWM % per run)")
    duties = list(args.duties)
    seconds = args.seconds or DEFAULT_A_SECONDS
    _timed_runs([f"duty {d:g} % for {seconds:g} s" for d in duties], seconds, console, None,
                not args.no_wait)
    rpm = list(args.rpm) if args.rpm is not None else [
        ask(f"measured shaft speed of run {i + 1} (r/min)") for i in range(len(duties))
    ]
    weighed = _masses(args, len(duties), console, ask, outlets.weighed)
    # eq. 6 is the whole machine's discharge: a catch from fewer rows scales up by rows/N
    scale = 1.0 if outlets.total is None else outlets.total / outlets.weighed
    rates = [m * scale / (seconds / 60.0) for m in weighed]
    wr = tuple(args.working_range) if args.working_range else (min(rpm), max(rpm))
    if len(wr) != 2:
        raise cal.CalibrationError("--working-range takes two numbers: lo,hi r/min")
    line = cal.fit_motor_line(duties, rpm)
    quad = cal.fit_meter_quadratic(rpm, rates, (wr[0], wr[1]))
    console.print(_table(f"rotation test {args.channel} (paper A)",
                         ("duty %", "r/min", "g/min whole machine", "speed resid.",
                          "rate resid."),
                         list(zip(duties, rpm, rates, line.residuals, quad.residuals,
                                  strict=True))))
    console.print(f"R = {line.slope:.4f}·K {line.intercept:+.4f}  (R² {line.r2:.4f})")
    console.print(f"Q = {quad.a:.4f}·ω² {quad.b:+.4f}·ω {quad.c:+.4f}  (R² {quad.r2:.4f})")
    problems = cal.paper_a_problems(line, quad, duties, rpm)
    _check_quality(problems, args, console)
    previous_a = _previous_paper_a(store, settings, args.channel)
    large = False
    if previous_a is not None:
        motor, meter, source = previous_a
        mid_duty = (min(duties) + max(duties)) / 2
        mid_w = (wr[0] + wr[1]) / 2

        def q(m: dict[str, float], w: float) -> float:
            return m["a"] * w * w + m["b"] * w + m["c"]

        large = _check_change([
            (f"r/min at {mid_duty:.0f} % duty (eq. 5)",
             motor["slope"] * mid_duty + motor["intercept"], line.predict(mid_duty)),
            (f"g/min at {mid_w:.0f} r/min (eq. 6)", q(meter, mid_w), quad.predict(mid_w)),
        ], source, args, console)
    replaces_a = None if previous_a is None else {
        "motor": previous_a[0], "meter": previous_a[1], "from": previous_a[2]}
    store.save(key, cal.to_entry(
        {"motor": line.__dict__, "meter": quad.__dict__, "omega_range": list(wr)},
        channel=args.channel, model="paper_a", outlets_weighed=outlets.weighed,
        outlets=outlets.total, weighed_mass_g=weighed, replaces=replaces_a,
        accepted_poor_fit=problems, accepted_large_change=large))
    _saved(console, key, "eq. 5 and eq. 6 for the whole machine")
    return EXIT_OK


def _speed(args: argparse.Namespace, console: Console) -> int:
    if args.samples is not None:
        try:
            with args.samples.open(encoding="utf-8") as fh:
                samples = [(float(r[0]), float(r[1])) for r in csv.reader(fh)
                           if r and not r[0].startswith("#") and r[0] != "time_s"]
        except (OSError, ValueError, IndexError) as exc:
            raise cal.CalibrationError(f"{args.samples}: unreadable speed log ({exc})") from None
        integrated = cal.integrate_distance(samples, between_marks=True)
    else:
        integrated = args.integrated_m
    res = cal.speed_correction(args.source, args.distance, integrated)
    console.print(f"{res.source}: measured {res.measured_m:g} m, integrated "
                  f"{res.integrated_m:.2f} m -> factor {res.factor:.4f}")
    _store(args).save(f"speed.{res.source}", cal.to_entry(res))
    return EXIT_OK


def _tilt(args: argparse.Namespace, console: Console, ask: Callable[[str], float]) -> int:
    n = cal.LOWERED_READINGS if args.mode == "lowered" else 1
    readings = args.readings
    if readings is None:
        readings = [ask(f"inclinometer reading {i + 1} (°)") for i in range(n)]
    res = (cal.tilt_lowered_critical(readings) if args.mode == "lowered"
           else cal.tilt_level_zero(readings))
    if res.zero_offset_deg is not None:
        console.print(f"zero offset {res.zero_offset_deg:+.2f}° (zeroed = raw − offset)")
    if res.critical_angle_deg is not None:
        console.print(f"critical angle {res.critical_angle_deg:+.2f}° (below → working)")
    entry = cal.save_tilt(_store(args), f"tilt.{args.sensor}", res)
    kept = entry["result"]
    if res.zero_offset_deg is None and kept.get("zero_offset_deg") is not None:
        console.print(f"kept the stored zero offset {kept['zero_offset_deg']:+.2f}°")
    if res.critical_angle_deg is None and kept.get("critical_angle_deg") is not None:
        console.print(f"kept the stored critical angle {kept['critical_angle_deg']:+.2f}°")
    return EXIT_OK


def run_calibration(args: argparse.Namespace, *, console: Console | None = None,
                    ask: Callable[[str], float] | None = None) -> int:
    """Run the chosen ``calibrate`` sub-command; 0 on success, 1 with a message otherwise."""
    con = console or Console()

    def prompt(text: str) -> float:
        return float(FloatPrompt.ask(text, console=con))

    asker = ask or prompt
    try:
        cmd = args.calibrate_command
        if cmd == "rotation":
            return _rotation(args, con, asker)
        if cmd == "speed":
            return _speed(args, con)
        if cmd == "tilt":
            return _tilt(args, con, asker)
        store = _store(args)
        if cmd == "undo":
            key, prev = store.undo(args.key)
            con.print(f"{key}: restored {'(no value)' if prev is None else prev['saved_at']}")
            return EXIT_OK
        con.print_json(json.dumps(store.current()))
        return EXIT_OK
    except ConfigError as exc:
        con.print(f"[red]config error:[/red]\n{escape(str(exc))}")
        return EXIT_FAILED
    except (GatewayError, DriverError, OSError) as exc:
        con.print(f"[red]calibration refused:[/red] {escape(str(exc))}")
        return EXIT_FAILED
