"""``sowgate calibrate rotation|speed|tilt|undo|show``: field calibration from the cab.

The timed runs show a rich progress bar; the operator then weighs the catch and types the
mass (or passes ``--mass`` for scripted use). Which mass is asked for is said in ``--help``
and in every prompt: the catch of ``--outlets-weighed N`` outlets (default all of the
channel's); g/rev is stored per outlet, paper A's eq. 6 for the whole machine. A fit outside
the quality gates (paper B's g/rev curve: each speed against the curve through the others,
``fits.OFF_CURVE_SIGMAS``; its constant g/rev, ``fits.MAX_GPR_CV_PCT`` ...) or a result more
than ``fits.LARGE_CHANGE_PCT`` from the value it replaces is shown and refused unless
``--accept-poor-fit`` / ``--accept-large-change``.

Who runs the meter: with ``--drive modbus`` the CLI drives paper A's motor on the RS485 PWM
module (fan at its working duty, watchdog armed), with ``--drive can`` a ``can_pid`` channel's
controller over CAN (its shaft measured); stop the daemon first (one master per bus). Set
point after set point, the motor is off between runs (each run's prompts come then, while the
catch is weighed) and off on any error, Ctrl-C or SIGTERM (``gateway.calibration.drive``).
With ``--drive manual`` (default) the operator runs the meter from the HMI and the CLI only
times. Results go to ``<state_dir>/calibration.json`` (previous value kept for undo).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import json
import logging
import signal
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
from gateway.calibration import drive as drive_mod
from gateway.calibration import fits as cal
from gateway.calibration import lots, presence, weighing
from gateway.config import ConfigError, CropModel, Settings, load_config, state_dir
from gateway.core.errors import GatewayError

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_SIGINT = 130  # the shell's 128 + signal number
EXIT_SIGTERM = 143
DEFAULT_B_SPEEDS = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)  # paper B
DEFAULT_B_SECONDS = 30.0
DEFAULT_A_SECONDS = 60.0  # paper A weighs 60 s runs
DEFAULT_A_RUNS = 6  # paper A duties over the fitted shaft speed range, when not given
SPEED_SOURCES = ("radar", "gnss", "isobus")
# how long the CLI waits for a running daemon to apply a save (it looks every WATCH_S)
DAEMON_PICKUP_S = 2 * presence.WATCH_S + 1.0
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
    r.add_argument("--duties", type=_floats, default=None,
                   help="paper A: PWM duty %% per run (with --drive modbus and --config, "
                   f"default: {DEFAULT_A_RUNS} duties spread over the crop's fitted shaft "
                   "speed range, by its motor line)")
    r.add_argument("--rpm", type=_floats, default=None,
                   help="paper A: measured shaft r/min per run (default: the set speeds)")
    r.add_argument("--seconds", type=_floats, default=None, metavar="S[,S...]",
                   help="run length (B 30 s, A 60 s): one for every run, one per set point "
                   "in the order of --duties/--speeds (repeats of a set point take its "
                   "length), e.g. 300,240,120,60,60,60 as the weighing advice says, or one "
                   "per run (the touchscreen's runs, each as long as it lasted)")
    r.add_argument("--mass", type=_floats, default=None,
                   help="weighed grams per run, in run order (skips the prompts): the catch "
                   "of --outlets-weighed outlets together")
    r.add_argument("--outlets-weighed", type=_positive_int, default=None, metavar="N",
                   help="how many outlets each weighed mass comes from (default: all of the "
                   "channel's [[channel]] outlets in --config, 1 without one; paper A: all "
                   "machine.rows). g/rev is stored "
                   "per outlet; paper A's eq. 6 is scaled to the whole machine by rows/N")
    r.add_argument("--scale-g", type=float, default=None, metavar="G",
                   help="the scale's stated error per weighing, ± G grams (taken as one "
                   "standard deviation; default: --config's [calibration] scale_g, else "
                   f"{weighing.DEFAULT_SCALE_G:g}, paper A's): each set point's "
                   "uncertainty and the run length it needs are worked out from it")
    r.add_argument("--accept-poor-fit", action="store_true",
                   help="save a fit that fails a quality gate (a paper-B run off the g/rev "
                   "curve through the others; the constant g/rev's CV and R² when fewer than "
                   "5 speeds; paper A's R² and set-point span); "
                   "logged and recorded in the entry")
    r.add_argument("--accept-large-change", action="store_true",
                   help=f"save a result more than {cal.LARGE_CHANGE_PCT:g} percent away from the "
                   "value it replaces (the saved one, else the config's)")
    r.add_argument("--seed-lot", default=lots.DEFAULT_LOT, metavar="NAME",
                   help="the seed lot this test is for (default: default); each lot of a crop "
                   "keeps its own fit, and the one just calibrated becomes the crop's active "
                   "lot (switch with: sowgate calibrate seed-lot, MQTT cmd/seed_lot or the "
                   "touchscreen)")
    r.add_argument("--min-stable-rpm", type=float, default=cal.PAPER_B_MIN_STABLE_RPM)
    r.add_argument("--working-range", type=_floats, default=None, help="lo,hi r/min")
    r.add_argument("--drive", choices=("manual", "modbus", "can"), default="manual",
                   help="manual: the operator runs the meter (from the HMI), the CLI times "
                   "the runs; modbus: the CLI drives paper A's motor (and the fan at its "
                   "working duty) on the RS485 PWM module; can: the CLI drives a can_pid "
                   "channel's controller and measures its shaft. Stop the daemon first (one "
                   "master per bus). The motor is off between runs, on any error, on Ctrl-C")
    r.add_argument("--fan-duty", type=float, default=None, metavar="PCT",
                   help="--drive modbus: fan duty during the test (default: the crop's "
                   "fan_high_pct, its seeding duty)")
    r.add_argument("--fan-settle", type=float, default=drive_mod.DEFAULT_FAN_SETTLE_S,
                   metavar="S", help="--drive modbus: seconds the fan runs before the first "
                   "run's motor starts")
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

    lot = sub.add_parser("seed-lot", help="make a seed lot's rotation test the crop's active "
                         "one (as MQTT cmd/seed_lot)")
    lot.add_argument("--crop", required=True, help="crop (or a channel's product)")
    lot.add_argument("--lot", required=True, help="seed lot name; default: the test saved "
                     "without --seed-lot")

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
    for command in sub.choices.values():
        _accept_common_options(command)
    return p


def _accept_common_options(command: argparse.ArgumentParser) -> None:
    """``--config`` and ``--state-dir`` after the sub-command as well as before it.

    ``sowgate calibrate positions --survey s.csv --config FILE`` is how people type it (and
    how the docs showed it); argparse only knew them before ``positions`` and refused the rest.
    SUPPRESS: not given here, the value given before the sub-command (or its default) stays.
    """
    command.add_argument("--config", default=argparse.SUPPRESS,
                         help="sowgate TOML config (also accepted before the sub-command)")
    command.add_argument("--state-dir", default=argparse.SUPPRESS,
                         help="where calibration.json lives (also accepted before the "
                         "sub-command)")


def _settings(args: argparse.Namespace) -> Settings | None:
    path = getattr(args, "config", None)
    return load_config(path) if path else None


def _store(args: argparse.Namespace) -> cal.CalibrationStore:
    return cal.CalibrationStore(args.state_dir or state_dir())


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
    key = lots.rotation_key(args.channel, args.seed_lot)
    table = _table(f"{key}: new result beside the {source} value it replaces",
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
            f"mistake: sowgate calibrate undo --key {key}). Nothing saved"
        )
    log.warning("calibration rotation.%s: %.0f %% change accepted (--accept-large-change)",
                args.channel, worst)
    return True


@dataclass
class TestRuns:
    """What the runs of one rotation test gave: each run's measured shaft turns (None: no
    shaft sensor), the shaft speeds the operator read (paper A, else None) and the masses."""

    turns: list[float | None]
    rpm: list[float] | None
    masses: list[float]


class _Screen:
    """The runs on the console: a rich bar per run on a terminal, else a line when each run
    starts, every ``PROGRESS_EVERY_S`` while it runs, and when it is done (piped or logged,
    rich's bar printed nothing until every run was over)."""

    def __init__(self, console: Console, labels: Sequence[str],
                 seconds: Sequence[float]) -> None:
        self.console, self.labels, self.seconds = console, labels, seconds
        self.progress: Progress | None = None
        self.task: Any = None
        self.next_report = PROGRESS_EVERY_S

    def __call__(self, r: drive_mod.RunReport) -> None:
        n, i = len(self.labels), r.index
        if not self.console.is_terminal:
            if r.event == "started":
                self.next_report = PROGRESS_EVERY_S
                self.console.print(f"run {i + 1}/{n}: {escape(self.labels[i])}: started",
                                   highlight=False)
            elif r.event == "progress" and r.elapsed_s >= self.next_report:
                self.console.print(f"run {i + 1}/{n}: {self.next_report:g} s of "
                                   f"{self.seconds[i]:g} s", highlight=False)
                self.next_report += PROGRESS_EVERY_S
            elif r.event == "done":
                self.console.print(f"run {i + 1}/{n}: done", highlight=False)
            return
        if r.event == "started":
            self.progress = Progress(TextColumn("{task.description}"), BarColumn(),
                                     TimeRemainingColumn(), console=self.console)
            self.progress.start()
            self.task = self.progress.add_task(f"run {i + 1}/{n}: {self.labels[i]}",
                                               total=self.seconds[i])
        elif self.progress is not None:
            self.progress.update(self.task, completed=min(r.elapsed_s, self.seconds[i]))
            if r.event == "done":
                self.progress.stop()
                self.progress = None

    def close(self) -> None:
        if self.progress is not None:
            self.progress.stop()
            self.progress = None


def _run_test(args: argparse.Namespace, console: Console, ask: Callable[[str], float],
              drive: drive_mod.MeterDrive | None, labels: Sequence[str],
              setpoints: Sequence[float], seconds: Sequence[float], outlets: Outlets, *,
              ask_rpm: bool) -> TestRuns:
    """The runs (timed, or driven by ``drive``), then or between them the prompts.

    With the meter driven or timed, each run's prompts come right after it, motor off: the
    catch is weighed before the next run fills the bag. ``--no-wait`` skips the runs (the
    masses are known) and so cannot drive anything."""
    n = len(setpoints)
    if args.mass is not None and len(args.mass) != n:
        raise cal.CalibrationError(f"--mass has {len(args.mass)} values for {n} runs")
    if ask_rpm and args.rpm is not None and len(args.rpm) != n:
        raise cal.CalibrationError(f"--rpm has {len(args.rpm)} values for {n} runs")
    rpm: list[float] = list(args.rpm) if ask_rpm and args.rpm is not None else []
    masses: list[float] = list(args.mass) if args.mass is not None else []

    def mass_question(i: int) -> str:
        return (f"weighed mass of run {i + 1} ({labels[i]}) in g, {outlets.describe()}")

    def rpm_question(i: int) -> str:
        return f"measured shaft speed of run {i + 1} ({labels[i]}) in r/min"

    if args.no_wait:
        if drive is not None:
            raise cal.CalibrationError("--no-wait skips the runs: it cannot drive the meter "
                                       f"(--drive {args.drive})")
        if ask_rpm and args.rpm is None:
            rpm = [ask(rpm_question(i)) for i in range(n)]
        if args.mass is None:
            masses = [ask(mass_question(i)) for i in range(n)]
        return TestRuns([None] * n, rpm if ask_rpm else None, masses)

    async def after_run(i: int, _turns: float | None) -> None:
        if ask_rpm and args.rpm is None:
            rpm.append(await drive_mod.ask_in_thread(ask, rpm_question(i)))
        if args.mass is None:
            masses.append(await drive_mod.ask_in_thread(ask, mass_question(i)))

    screen = _Screen(console, labels, seconds)

    async def session() -> list[float | None]:
        loop = asyncio.get_running_loop()
        me = asyncio.current_task()
        assert me is not None
        # SIGTERM ends the test as Ctrl-C does (asyncio.run turns SIGINT into a cancel)
        terminated = False
        try:
            def on_term() -> None:
                nonlocal terminated
                terminated = True
                me.cancel()
            loop.add_signal_handler(signal.SIGTERM, on_term)
        except (NotImplementedError, RuntimeError, ValueError):  # not the main thread
            pass
        try:
            return await drive_mod.drive_runs(drive, setpoints, seconds, screen, after_run)
        except asyncio.CancelledError:
            if terminated:
                raise Interrupted("terminated (SIGTERM)") from None
            raise
        finally:
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.remove_signal_handler(signal.SIGTERM)

    try:
        turns = asyncio.run(session())
    finally:
        screen.close()
    return TestRuns(turns, rpm if ask_rpm else None, masses)


class Interrupted(Exception):
    """The test was stopped by a signal; the meter is off (``drive_runs``)."""


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


def _previous_entry(store: cal.CalibrationStore, name: str, lot: str,
                    model: str) -> tuple[dict[str, Any], str] | None:
    """The saved entry a new result of ``lot`` replaces: that lot's, else (a lot's first test)
    the default lot's, with where it comes from."""
    for candidate in dict.fromkeys((lot, lots.DEFAULT_LOT)):
        entry = store.get(lots.rotation_key(name, candidate))
        if entry is not None and entry.get("model") == model:
            return entry, ("calibration" if candidate == lot
                           else f"calibration (lot {candidate})")
    return None


def _previous_gpr(store: cal.CalibrationStore, settings: Settings | None,
                  name: str, lot: str) -> tuple[float, str] | None:
    """The per-outlet g/rev a new result replaces: the saved one, else the config's."""
    saved = _previous_entry(store, name, lot, "grams_per_rev")
    if saved is not None:
        return float(saved[0]["result"]["grams_per_rev"]), saved[1]
    ch = next((c for c in settings.channel if c.name == name), None) if settings else None
    return (ch.grams_per_rev, "config") if ch is not None else None


def _previous_paper_a(store: cal.CalibrationStore, settings: Settings | None, name: str,
                      lot: str) -> tuple[dict[str, float], dict[str, float], str] | None:
    """Eq. 5 and eq. 6 coefficients a new paper-A fit replaces: saved, else the config's."""
    saved = _previous_entry(store, name, lot, "paper_a")
    if saved is not None:
        result = saved[0]["result"]
        return dict(result["motor"]), dict(result["meter"]), saved[1]
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


def _activate_lot(console: Console, store: cal.CalibrationStore, settings: Settings | None,
                  name: str, lot: str) -> None:
    """The lot just calibrated is the one in the hopper: make it the crop's active lot."""
    crop = lots.crop_of(settings, name) if settings is not None else None
    if crop is None:
        crop = name  # without a config: a paper-A test is named after its crop
    if lots.active_lots(store.load()).get(crop, lots.DEFAULT_LOT) != lot:
        lots.select_lot(store, crop, lot)
        console.print(f"seed lot {lot} is now {crop}'s active lot")


def _need(settings: Settings | None, what: str) -> Settings:
    if settings is None:
        raise cal.CalibrationError(f"{what} needs --config (the bus and the machine)")
    return settings


def _paper_a_crop_model(settings: Settings | None, name: str) -> CropModel | None:
    """The crop model a paper-A test of ``name`` (a crop or a pwm_modbus channel) refits."""
    if settings is None:
        return None
    crops = settings.control.crops
    if name in crops:
        return crops[name]
    product = next((c.product for c in settings.channel
                    if c.name == name and c.drive == "pwm_modbus"), None)
    return crops.get(product) if product is not None else None


def _default_duties(crop: CropModel) -> list[float]:
    """``DEFAULT_A_RUNS`` duties whose shafts (by the crop's motor line) span its fitted range,
    rounded to 0.5 %, within 1..100 %."""
    lo, hi = crop.omega_min_rpm, crop.omega_max_rpm
    out = []
    for i in range(DEFAULT_A_RUNS):
        w = lo + (hi - lo) * i / (DEFAULT_A_RUNS - 1)
        duty = (w - crop.motor_intercept) / crop.motor_slope
        out.append(min(100.0, max(1.0, round(duty * 2) / 2)))
    return sorted(set(out))


def _saved(console: Console, key: str, stored: str, state: Path) -> None:
    console.print(f"saved {key}: {stored}.")
    _tell_daemon(console, state, key)
    console.print(f"`sowgate calibrate undo --key {key}` restores the value it replaced.")


def _tell_daemon(console: Console, state: Path, key: str | None) -> None:
    """Say whether a running daemon applied what was just saved, or when it will apply."""
    daemon = presence.running_daemon(state)
    if daemon is None:
        console.print("No daemon is running on this state directory: the daemon applies it "
                      "at its next start.")
        return
    pid = daemon["pid"]
    wanted = presence.calibration_signature(state)
    deadline = time.monotonic() + DAEMON_PICKUP_S
    while True:
        daemon = presence.running_daemon(state)
        applied = (daemon or {}).get("calibration") or {}
        if daemon is not None and applied.get("signature") == wanted:
            name = None if key is None else key.partition(".")[2].partition("@")[0]
            notes = [n for n in applied.get("notes", []) if name is None or name in n]
            if not applied.get("ok", True):
                console.print(f"[red]The running daemon (pid {pid}) could not read the file; "
                              "it keeps the values it had[/red]")
            elif notes:
                console.print(f"The running daemon (pid {pid}) applied the file: "
                              f"{escape('; '.join(notes))}")
            else:
                console.print(f"The running daemon (pid {pid}) applied it.")
            return
        if daemon is None or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    console.print(f"[yellow]The running daemon (pid {pid}) has not picked it up within "
                  f"{DAEMON_PICKUP_S:g} s[/yellow]: it applies it at its next start (see its "
                  "log and the calibration.* alarms).")


def _run_lengths(args: argparse.Namespace, set_points: Sequence[float],
                 default: float, option: str) -> list[float]:
    """Each run's length from ``--seconds``: one value for every run, one per distinct set
    point in the order they first appear (``option``: where the set points came from), or
    one per run (a test run at the touchscreen, whose runs of one set point may differ:
    a short first run is made up by the next)."""
    given = list(args.seconds) if args.seconds is not None else [default]
    bad = [t for t in given if not t > 0]
    if bad:
        raise cal.CalibrationError(f"--seconds must be > 0 s (got {bad[0]:g})")
    keys = list(dict.fromkeys(float(k) for k in set_points))
    if len(given) == 1:
        return [given[0]] * len(set_points)
    if len(given) == len(set_points):  # one per run (without repeats: one per set point too)
        return given
    if len(given) != len(keys):
        raise cal.CalibrationError(
            f"--seconds has {len(given)} lengths for {len(keys)} set points: give one length "
            f"for every run, one per set point in the order of {option} (its repeats run "
            f"as long), or one per run ({len(set_points)})")
    by_key = dict(zip(keys, given, strict=True))
    return [by_key[float(k)] for k in set_points]


def _weighing_advice(args: argparse.Namespace, console: Console, set_points: Sequence[float],
                     weighed: Sequence[float], seconds: Sequence[float],
                     label: str) -> dict[str, object]:
    """Each set point's weighing uncertainty on the stated scale, and what to do about the
    ones too uncertain for the rate (``gateway.calibration.weighing``): a warning with the
    numbers, never a refusal. Returns what the calibration entry keeps of it."""
    advice = weighing.weighing_advice(set_points, weighed, seconds, args.scale_g)
    lines = advice.messages(args.channel, label)
    if lines:
        console.print("[yellow]warning[/]: the runs were too short for this scale:")
        for line in lines:
            console.print(f"  - {line}", highlight=False)
    note = advice.practical_note(args.channel)
    if note is not None:  # hours of runs: the scale, not the farmer's patience, is the fix
        console.print(f"[bold yellow]warning[/]: {note}", highlight=False)
    elif advice.set_points:
        worst = max(advice.set_points, key=lambda p: p.se_pct)
        console.print(
            f"weighing: every set point's mean within ±{advice.target_pct:g} % on a "
            f"±{advice.scale_g:g} g scale (worst ±{worst.se_pct:.2f} % at "
            f"{label.format(worst.set_point)})", highlight=False)
    scattered = weighing.unexplained_scatter(set_points, weighed, args.scale_g)
    if scattered:
        console.print(
            "[yellow]warning[/]: runs of one set point disagree by more than the scale "
            "explains at "
            + "; ".join(f"{label.format(p.set_point)} (±{p.scatter_pct:.1f} % between its "
                        f"{p.runs} runs, the scale ±{p.scale_pct:.1f} %)" for p in scattered)
            + ": something else differed between those runs (timing, the flow); repeat "
            "those set points", highlight=False)
    return advice.to_entry()


def _rotation(args: argparse.Namespace, console: Console, ask: Callable[[str], float]) -> int:
    if args.scale_g is not None and not args.scale_g > 0:  # before the runs, not after them
        raise cal.CalibrationError(f"--scale-g must be > 0 g (got {args.scale_g:g})")
    settings = _settings(args)
    if args.scale_g is None:  # the config's scale (the touchscreen's test uses it too)
        configured = settings.calibration.scale_g if settings is not None else None
        args.scale_g = weighing.DEFAULT_SCALE_G if configured is None else configured
    _check_rotation_target(settings, args.channel, args.model)
    outlets = _outlets(args, settings)
    store = _store(args)
    lot = lots.check_lot_name(args.seed_lot)
    key = lots.rotation_key(args.channel, lot)
    crop = lots.crop_of(settings, args.channel) if settings is not None else None
    daemon = presence.running_daemon(store.path.parent) if args.drive != "manual" else None
    if daemon is not None:
        raise cal.CalibrationError(
            f"the daemon (pid {daemon['pid']}) is running and owns the bus: stop it first "
            f"(systemctl stop sowgate), then run --drive {args.drive} again"
        )
    console.print(f"masses asked for: the catch of each run, {outlets.describe()}")
    if args.model == "grams_per_rev":
        speeds = args.speeds or list(DEFAULT_B_SPEEDS)
        seconds = _run_lengths(args, speeds, DEFAULT_B_SECONDS, "--speeds")
        if args.drive == "modbus":
            raise cal.CalibrationError(
                "--drive modbus drives paper A's motor: its rotation test is --model paper_a")
        drive = drive_mod.CanMeterDrive(_need(settings, "--drive can"), args.channel) if (
            args.drive == "can") else None
        labels = [f"{n:g} r/min for {t:g} s" for n, t in zip(speeds, seconds, strict=True)]
        done = _run_test(args, console, ask, drive, labels, speeds, seconds, outlets,
                         ask_rpm=False)
        weighed = done.masses
        masses = [m / outlets.weighed for m in weighed]  # per outlet
        rpm = list(speeds)
        driven = drive is not None
        if driven:
            # the shaft's measured turns, spin-up and run-down included, not the set point
            for i, turns in enumerate(done.turns):
                if not turns:
                    raise cal.CalibrationError(
                        f"run {i + 1}: no shaft feedback from the controller; nothing saved"
                    )
                rpm[i] = turns / (seconds[i] / 60.0)
            console.print(_table("measured shaft speed", ("set r/min", "effective r/min"),
                                 list(zip(speeds, rpm, strict=True))))
        runs = [cal.RotationRun(n, t, m, set_rpm=s if driven else None)
                for n, m, s, t in zip(rpm, masses, speeds, seconds, strict=True)]
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
        advice = _weighing_advice(args, console, speeds, weighed, seconds, "{:.4g} r/min")
        by_speed = cal.grams_per_rev_by_speed(runs)
        if by_speed is not None:
            console.print("g/rev per outlet by shaft speed (used instead of the mean): "
                          + ", ".join(f"{g:.2f} at {n:.0f} r/min" for n, g in by_speed))
            judged, _off = cal.speeds_on_curve(runs, scale_g=args.scale_g,
                                               outlets_weighed=outlets.weighed)
            console.print("each speed's g/rev against the curve through the others: "
                          + ", ".join(f"{s.set_rpm:g} r/min {s.off_pct:+.1f} % (±"
                                      f"{s.sigma_pct:.1f} %)" for s in judged),
                          highlight=False)
        # judged on what is saved: the curve when there is one, else the constant
        problems = cal.grams_per_rev_test_problems(fit, runs, by_speed, scale_g=args.scale_g,
                                                   outlets_weighed=outlets.weighed)
        _check_quality(problems, args, console)
        previous = _previous_gpr(store, settings, args.channel, lot)
        large = False
        if previous is not None:
            large = _check_change([("g/rev per outlet", previous[0], fit.grams_per_rev)],
                                  previous[1], args, console)
        replaces = (None if previous is None
                    else {"grams_per_rev": previous[0], "from": previous[1]})
        store.save(key, cal.to_entry(
            cal.grams_per_rev_result(fit, by_speed), channel=args.channel, crop=crop,
            seed_lot=lot, model="grams_per_rev",
            outlets_weighed=outlets.weighed, outlets=outlets.total, weighed_mass_g=weighed,
            replaces=replaces, accepted_poor_fit=problems,
            accepted_large_change=large, weighing=advice))
        _activate_lot(console, store, settings, args.channel, lot)
        _saved(console, key, f"{fit.grams_per_rev:.2f} g/rev per outlet", store.path.parent)
        return EXIT_OK
    # paper A: duty -> speed line and speed -> rate quadratic
    drive_a: drive_mod.MeterDrive | None = None
    if args.drive == "can":
        raise cal.CalibrationError(
            "--drive can drives a paper-B channel: its rotation test is --model grams_per_rev")
    crop_model = _paper_a_crop_model(settings, args.channel)
    if args.duties is not None:
        duties = list(args.duties)
    elif args.drive == "modbus" and crop_model is not None:
        duties = _default_duties(crop_model)
    else:
        raise cal.CalibrationError("paper_a rotation needs --duties (PWM % per run; with "
                                   "--drive modbus and --config they default to the crop's "
                                   "working range)")
    if args.drive == "modbus":
        s = _need(settings, "--drive modbus")
        fan = args.fan_duty if args.fan_duty is not None else (
            crop_model.fan_high_pct if crop_model is not None else 0.0)
        if not 0.0 <= fan <= 100.0:
            raise cal.CalibrationError(f"--fan-duty must be 0..100 % (got {fan:g})")
        for d in duties:
            if not 0.0 < d <= 100.0:
                raise cal.CalibrationError(f"--duties must be in 0..100 % (got {d:g})")
        drive_a = drive_mod.ModbusMeterDrive(s, fan_pct=fan, fan_settle_s=args.fan_settle)
        console.print(f"driving the motor on the PWM module, fan at {fan:g} %")
    seconds = _run_lengths(args, duties, DEFAULT_A_SECONDS, "--duties")
    labels = [f"duty {d:g} % for {t:g} s" for d, t in zip(duties, seconds, strict=True)]
    done = _run_test(args, console, ask, drive_a, labels, duties, seconds, outlets, ask_rpm=True)
    assert done.rpm is not None
    rpm = done.rpm
    weighed = done.masses
    # eq. 6 is the whole machine's discharge: a catch from fewer rows scales up by rows/N
    scale = 1.0 if outlets.total is None else outlets.total / outlets.weighed
    wr = tuple(args.working_range) if args.working_range else None
    if wr is not None and len(wr) != 2:
        raise cal.CalibrationError("--working-range takes two numbers: lo,hi r/min")
    # the touchscreen's "save" fits the same way (gateway.app.rotation_test)
    pfit = cal.fit_rotation_test(duties, rpm, weighed, seconds, whole_machine=scale,
                                 working_range=None if wr is None else (wr[0], wr[1]))
    line, quad, meter_own, rates = pfit.line, pfit.quad, pfit.meter_own, pfit.rates_g_min
    console.print(_table(f"rotation test {args.channel} (paper A)",
                         ("duty %", "r/min", "g/min whole machine", "speed resid.",
                          "rate resid."),
                         list(zip(duties, rpm, rates, line.residuals, quad.residuals,
                                  strict=True))))
    console.print(f"R = {line.slope:.4f}·K {line.intercept:+.4f}  (R² {line.r2:.4f})")
    console.print(f"Q = {quad.a:.4f}·ω² {quad.b:+.4f}·ω {quad.c:+.4f}  (R² {quad.r2:.4f})")
    if meter_own is not None:
        console.print(
            f"the drill's own curve: {len(meter_own.points)} knots through the set points "
            f"(weighing noise {meter_own.run_cv * 100:.1f} %"
            + "".join(f"; set points {', '.join(f'{k:g}' for k in grp)} pooled: their "
                      "difference is within the noise" for grp in meter_own.pooled)
            + ")")
    advice = _weighing_advice(args, console, duties, weighed, seconds, "{:.4g} % duty")
    problems = pfit.problems
    _check_quality(problems, args, console)
    previous_a = _previous_paper_a(store, settings, args.channel, lot)
    large = False
    if previous_a is not None:
        motor, meter, source = previous_a
        large = _check_change(cal.paper_a_changes(motor, meter, pfit, duties), source, args,
                              console)
    replaces_a = None if previous_a is None else {
        "motor": previous_a[0], "meter": previous_a[1], "from": previous_a[2]}
    store.save(key, cal.to_entry(
        pfit.result(),
        channel=args.channel, crop=crop or args.channel, seed_lot=lot, model="paper_a",
        outlets_weighed=outlets.weighed,
        outlets=outlets.total, weighed_mass_g=weighed, replaces=replaces_a,
        accepted_poor_fit=problems, accepted_large_change=large, weighing=advice))
    _activate_lot(console, store, settings, args.channel, lot)
    _saved(console, key, "eq. 5 and eq. 6 for the whole machine", store.path.parent)
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
    store = _store(args)
    store.save(f"speed.{res.source}", cal.to_entry(res))
    _tell_daemon(console, store.path.parent, f"speed.{res.source}")
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
    store = _store(args)
    entry = cal.save_tilt(store, f"tilt.{args.sensor}", res)
    kept = entry["result"]
    if res.zero_offset_deg is None and kept.get("zero_offset_deg") is not None:
        console.print(f"kept the stored zero offset {kept['zero_offset_deg']:+.2f}°")
    if res.critical_angle_deg is None and kept.get("critical_angle_deg") is not None:
        console.print(f"kept the stored critical angle {kept['critical_angle_deg']:+.2f}°")
    _tell_daemon(console, store.path.parent, None)
    return EXIT_OK


def _seed_lot(args: argparse.Namespace, console: Console, store: cal.CalibrationStore) -> int:
    lot = lots.check_lot_name(args.lot)
    current = store.current()
    settings = _settings(args)
    if settings is not None:
        available = lots.lots_of(settings, current, args.crop)
        if args.crop not in lots.crops(settings):
            raise cal.CalibrationError(f"unknown crop {args.crop!r}; known: "
                                       f"{', '.join(lots.crops(settings))}")
    else:  # without a config: the lots of entries named after the crop
        available = [lots.DEFAULT_LOT, *sorted({
            split[1] for key in current
            if (split := lots.split_rotation_key(key)) is not None and split[0] == args.crop
            and split[1] != lots.DEFAULT_LOT})]
    if lot not in available:
        raise cal.CalibrationError(f"{args.crop} has no rotation test for seed lot {lot!r} "
                                   f"(lots: {', '.join(available)})")
    lots.select_lot(store, args.crop, lot)
    console.print(f"{args.crop}: seed lot {lot} is the active lot")
    _tell_daemon(console, store.path.parent, None)
    return EXIT_OK


def run_calibration(args: argparse.Namespace, *, console: Console | None = None,
                    ask: Callable[[str], float] | None = None) -> int:
    """Run the chosen ``calibrate`` sub-command; 0 on success, 1 with a message otherwise."""
    con = console or Console(soft_wrap=True)  # whole lines: a pipe or a log got them cut at 80

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
        if cmd == "seed-lot":
            return _seed_lot(args, con, store)
        if cmd == "undo":
            key, prev = store.undo(args.key)
            con.print(f"{key}: restored {'(no value)' if prev is None else prev['saved_at']}")
            _tell_daemon(con, store.path.parent, None)
            return EXIT_OK
        con.print_json(json.dumps(store.current()))
        return EXIT_OK
    except ConfigError as exc:
        con.print(f"[red]config error:[/red]\n{escape(str(exc))}")
        return EXIT_FAILED
    except (KeyboardInterrupt, Interrupted) as exc:
        why = "interrupted (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else str(exc)
        con.print(f"[red]calibration {escape(why)}:[/red] the meter is off; nothing saved")
        return EXIT_SIGINT if isinstance(exc, KeyboardInterrupt) else EXIT_SIGTERM
    except EOFError:
        if args.calibrate_command == "tilt":
            scripted = ("--readings scripts it, e.g. --readings 0.4 for --mode level, "
                        f"{cal.LOWERED_READINGS} angles for --mode lowered")
            after = "nothing saved"
        else:
            scripted = "--mass and --rpm script it"
            after = "the meter is off; nothing saved"
        con.print(f"[red]calibration stopped:[/red] no answer at the prompt (standard input "
                  f"closed; {scripted}); {after}")
        return EXIT_FAILED
    except (GatewayError, DriverError, OSError) as exc:
        con.print(f"[red]calibration refused:[/red] {escape(str(exc))}")
        return EXIT_FAILED
