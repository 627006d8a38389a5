"""``sowgate calibrate rotation|speed|tilt|undo|show``: field calibration from the cab.

The timed runs show a rich progress bar; the operator then weighs the catch and types the
mass (or passes ``--mass`` for scripted use). With ``--drive can`` the CLI itself commands a
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
                   help="weighed grams per run, in run order (skips the prompts)")
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

    u = sub.add_parser("undo", help="restore the value replaced by the last calibration")
    u.add_argument("--key", default=None, help="e.g. rotation.seed, speed.radar, tilt.inclinometer")

    sub.add_parser("show", help="print the stored calibration")
    return p


def _settings(args: argparse.Namespace) -> Settings | None:
    path = getattr(args, "config", None)
    return load_config(path) if path else None


def _store(args: argparse.Namespace) -> cal.CalibrationStore:
    return cal.CalibrationStore(args.state_dir or state_dir())


def _masses(args: argparse.Namespace, n: int, console: Console,
            ask: Callable[[str], float]) -> list[float]:
    if args.mass is not None:
        if len(args.mass) != n:
            raise cal.CalibrationError(f"--mass has {len(args.mass)} values for {n} runs")
        return list(args.mass)
    return [ask(f"weighed mass of run {i + 1} (g)") for i in range(n)]


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


def _rotation(args: argparse.Namespace, console: Console, ask: Callable[[str], float]) -> int:
    settings = _settings(args)
    _check_rotation_target(settings, args.channel, args.model)
    store = _store(args)
    if args.model == "grams_per_rev":
        speeds = args.speeds or list(DEFAULT_B_SPEEDS)
        seconds = args.seconds or DEFAULT_B_SECONDS
        drive = _can_driver(settings, args.channel, speeds) if args.drive == "can" else None
        driven = _timed_runs([f"{n:g} r/min for {seconds:g} s" for n in speeds], seconds,
                             console, drive, not args.no_wait)
        masses = _masses(args, len(speeds), console, ask)
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
        rows: list[tuple[Any, ...]] = [(r.rpm, r.mass_g, g, res) for r, g, res in
                zip(fit.used, fit.per_run, fit.residuals_g_min, strict=True)]
        rows += [(r.rpm, r.mass_g, "excluded (unstable)", "") for r in fit.excluded]
        console.print(_table(f"rotation test {args.channel}", ("r/min", "g", "g/rev",
                                                               "residual g/min"), rows))
        console.print(f"g/rev = {fit.grams_per_rev:.2f}  CV {fit.cv_pct:.2f} %  R² {fit.r2:.4f}")
        store.save(f"rotation.{args.channel}", cal.to_entry(fit, channel=args.channel,
                                                             model="grams_per_rev"))
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
    masses = _masses(args, len(duties), console, ask)
    rates = [m / (seconds / 60.0) for m in masses]
    wr = tuple(args.working_range) if args.working_range else (min(rpm), max(rpm))
    if len(wr) != 2:
        raise cal.CalibrationError("--working-range takes two numbers: lo,hi r/min")
    line = cal.fit_motor_line(duties, rpm)
    quad = cal.fit_meter_quadratic(rpm, rates, (wr[0], wr[1]))
    console.print(_table(f"rotation test {args.channel} (paper A)",
                         ("duty %", "r/min", "g/min", "speed resid.", "rate resid."),
                         list(zip(duties, rpm, rates, line.residuals, quad.residuals,
                                  strict=True))))
    console.print(f"R = {line.slope:.4f}·K {line.intercept:+.4f}  (R² {line.r2:.4f})")
    console.print(f"Q = {quad.a:.4f}·ω² {quad.b:+.4f}·ω {quad.c:+.4f}  (R² {quad.r2:.4f})")
    store.save(f"rotation.{args.channel}", cal.to_entry(
        {"motor": line.__dict__, "meter": quad.__dict__, "omega_range": list(wr)},
        channel=args.channel, model="paper_a"))
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
