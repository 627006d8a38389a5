"""``sowgate demo``: the daemon driving the simulated machine, with a scripted operator.

It is the first thing a newcomer runs, so it says what it does: at start, the simulated
devices and their ptys, the config (written to ``<state dir>/demo.toml``), the record store,
MQTT (off, and how to turn it on, or the broker and topics) and how to stop it; at the end,
the applied rate, that motor and fan were set to 0, and the export and the field report to try
next. The store is kept (``./sowgate-demo`` unless ``--state-dir`` says otherwise), never the
real state directory, so simulated seeds never mix with a field's.

With ``channels=True`` paper B's three metering channels (shallow and deep fertiliser, seed)
run as well: simulated PID controllers and hydraulic motors (``simulator.can_pid``) answer on
a python-can ``virtual`` bus, and the daemon drives them through the DBC like real ones.

With ``dashboard=True`` (``make demo``) the web dashboard runs too, in its own process as in
the field (``sowgate dashboard`` on the demo's config), with start/stop/rate and alarm
acknowledgement enabled: on the broker the environment names (``SOWGATE_MQTT__*``), else on a
private mosquitto on a free port when one is installed. Its URL is printed at start.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.tasks import cancel_and_wait
from gateway.app.cli import setup_logging
from gateway.app.daemon import Daemon
from gateway.ui.terminal import run_with_live_view
from simulator.machine import STARTUP_TRANSIENT_S

if TYPE_CHECKING:
    from gateway.config import Settings
    from gateway.state import MachineState
    from simulator.machine import SimulatedMachine, Truth

log = logging.getLogger(__name__)

# paper B: targets at 5 km/h (kg/ha) and the weighed displacement per outlet (g/rev)
PAPER_B_CHANNELS = (
    ("shallow", "fertiliser", 150.0, 16.97),
    ("deep", "fertiliser", 300.0, 29.31),
    ("seed", "wheat", 225.0, 11.20),
)
PAPER_B_OUTLETS = 10  # 10 rows
DEFAULT_STATE_DIR = Path("sowgate-demo")  # relative: next to where the demo was started
CONFIG_FILE = "demo.toml"
STATUS_EVERY_S = 5.0  # --no-tui: one status line this often
BROKER_PROBE_S = 1.0
DASHBOARD_PORT = 8080  # the dashboard's default; a free port when it is taken
DEMO_COMMANDS = ["start", "stop", "rate", "ack_alarm"]
MOSQUITTO_PATHS = ("/usr/sbin/mosquitto", "/usr/bin/mosquitto", "/usr/local/sbin/mosquitto")


HOPPER_DEMO_BIAS = 0.08  # --hopper-scale: the drill's true discharge over its model, - 1
MIN_MEASURED_M = 1.0  # sown before the demo shows an applied rate: less is no measurement


def _error_pct(applied: float | None, target: float) -> float | None:
    return None if applied is None or target <= 0 else (applied / target - 1.0) * 100.0


def _pct(value: float) -> str:
    return f"{round(value, 2) + 0.0:+.2f} %"  # + 0.0: never print "-0.00 %"


def truth_report(truth: Truth, target_kg_ha: float) -> dict[str, Any]:
    """The simulator's ground truth as the demo shows it: the whole-run applied rate and, apart,
    the rate after each pass's start-up transient (see ``simulator.machine.Truth``).

    A rate is None until ``MIN_MEASURED_M`` has been sown: over the first centimetres off
    standstill nothing has left the meter yet, and the view showed "rate error -100.00 %"
    for what was no measurement at all.
    """
    applied = truth.applied_kg_ha() if truth.sown_m >= MIN_MEASURED_M else None
    settled = truth.settled_kg_ha() if truth.settled_m >= MIN_MEASURED_M else None
    return {
        "sown_m": truth.sown_m,
        "applied_kg_ha": applied,
        "rate_error_pct": _error_pct(applied, target_kg_ha),
        "settled_m": truth.settled_m,
        "settled_kg_ha": settled,
        "settled_rate_error_pct": _error_pct(settled, target_kg_ha),
    }


def summary(report: dict[str, Any], target_kg_ha: float) -> str:
    """The closing line of ``sowgate demo``.

    Why not just the whole-run error: a drive starts from standstill, and for the first seconds
    of every pass the speed filter and the motor lag the tractor, so a demo of a few seconds
    reports -10 % or worse although the controller holds the rate once under way (and
    printed "+0.00 %" when nothing had been sown at all). The line says how much was sown and
    keeps the start-up part apart, so neither figure is read out of context.
    """
    applied = report["applied_kg_ha"]
    if applied is None:
        return (
            "demo finished: nothing sown yet (the simulated tractor had not started a pass); "
            "run longer, e.g. --duration 60"
        )
    whole = (
        f"{report['sown_m']:.1f} m sown, applied {applied:.2f} kg/ha "
        f"(target {target_kg_ha:g}, error {_pct(report['rate_error_pct'])})"
    )
    settled = report["settled_kg_ha"]
    if settled is None:
        return (
            f"demo finished: {whole}, all of it in the start-up of a pass (speed filter and "
            "motor catching up from standstill), so not representative; "
            "run longer, e.g. --duration 60"
        )
    return (
        f"demo finished: {whole}; after the first {STARTUP_TRANSIENT_S:g} s of each pass "
        f"{settled:.2f} kg/ha (error {_pct(report['settled_rate_error_pct'])} "
        f"over {report['settled_m']:.1f} m)"
    )


def paper_b_channel_config(can_channel: str) -> dict[str, Any]:
    """Config overrides for the three CAN channels on the virtual bus ``can_channel``."""
    return {
        "can": {"enabled": True, "interface": "virtual", "channel": can_channel},
        "channel": [
            {
                "name": name,
                "product": product,
                "target_rate_kg_ha": rate,
                "drive": "can_pid",
                "node_id": node,
                "grams_per_rev": g_per_rev,
                "outlets": PAPER_B_OUTLETS,
            }
            for node, (name, product, rate, g_per_rev) in enumerate(PAPER_B_CHANNELS, start=1)
        ],
    }


async def run_demo(
    duration_s: float | None,
    tui: bool,
    crop: str = "rapeseed",
    channels: bool = False,
    state: Path | None = None,
    hopper_scale: bool = False,
    dashboard: bool = False,
    status_on_stdout: bool = False,
) -> int:
    """The demo; ``tui`` False: a status line every ``STATUS_EVERY_S``, logged to standard
    error, or with ``status_on_stdout`` printed (and flushed) to standard output, where a live
    view would have been had it been a terminal (``make demo | tee demo.log``)."""
    from simulator.machine import SimulatedMachine

    code = {"rapeseed": 1, "wheat": 2}[crop]
    state = state if state is not None else DEFAULT_STATE_DIR
    async with contextlib.AsyncExitStack() as stack:
        machine = await stack.enter_async_context(
            SimulatedMachine(
                crop=crop, loop_drive=True, with_gnss=True, with_seed_tubes=True,
                # a hopper on load cells, and a drill 8 % off its model for the scale to find
                hopper=_hopper_demo() if hopper_scale else None,
                discharge_bias=HOPPER_DEMO_BIAS if hopper_scale else 0.0,
            )
        )
        overrides: dict[str, Any] = {}
        plants: dict[str, Any] = {}
        if channels:
            overrides = paper_b_channel_config(f"sowgate-demo-{os.getpid()}")
            plants = await _start_controllers(stack, overrides["can"]["channel"])
        state.mkdir(parents=True, exist_ok=True)
        dashboard_lines: list[str] = []
        if dashboard:
            dashboard_lines = _dashboard_overrides(stack, machine.settings(**overrides), overrides)
        settings = machine.settings(**overrides)
        machine.write_config(state / CONFIG_FILE, **overrides)
        if dashboard and settings.mqtt.enabled:
            dashboard_lines = _start_dashboard(stack, state, settings)
        daemon = Daemon(settings, state)
        assert machine.hmi is not None
        model = settings.control.crops[crop]
        text = await start_text(machine, settings, state, duration_s, tui, channels,
                                status_on_stdout)
        print("\n".join([text, *dashboard_lines]), flush=True)

        async def operator() -> None:
            await asyncio.sleep(1.0)
            assert machine.hmi is not None
            machine.hmi.select(code, model.default_rate_kg_ha)
            await asyncio.sleep(0.5)
            machine.hmi.press_start()
            if duration_s is not None:
                await asyncio.sleep(max(0.0, duration_s - 1.5))
                daemon.request_stop()

        def truth() -> dict[str, Any]:
            return truth_report(machine.truth, daemon.controller.rate_kg_ha)

        helpers = [asyncio.create_task(operator(), name="demo-operator")]
        if not tui:
            helpers.append(asyncio.create_task(_log_status(daemon, status_on_stdout),
                                               name="demo-status"))
        try:
            if tui:
                await run_with_live_view(daemon.state, daemon.run(), truth)
            else:
                await daemon.run()
        finally:
            for task in helpers:
                await cancel_and_wait(task)
        print(summary(truth(), daemon.controller.rate_kg_ha), flush=True)
        area_ha = machine.truth.area_m2 / 1e4
        for name, _product, rate, _g in PAPER_B_CHANNELS if channels else ():
            mass_kg = plants[name].mass_g / 1000
            applied_ch = mass_kg / area_ha if area_ha > 0 else 0.0
            print(f"channel {name}: applied {applied_ch:.1f} kg/ha (target {rate:g})", flush=True)
        print(end_text(machine, state, channels), flush=True)
    return 0


def _hopper_demo() -> Any:
    from simulator.plant import HopperTruth

    return HopperTruth(initial_kg=300.0, noise_kg=2.0, refills=((600.0, 400.0),))
def _free_port(preferred: int | None = None) -> int:
    for port in ([preferred] if preferred else []) + [0]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return int(s.getsockname()[1])
    raise OSError("no free port")


def _find_mosquitto() -> str | None:
    for candidate in MOSQUITTO_PATHS:
        if Path(candidate).exists():
            return candidate
    return shutil.which("mosquitto")


def _stop_process(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _dashboard_overrides(
    stack: contextlib.AsyncExitStack, settings: Settings, overrides: dict[str, Any]
) -> list[str]:
    """Config for the dashboard: the broker the environment names, else a private mosquitto
    (started here, stopped with the demo); commands on. Lines to print if it cannot run."""
    overrides["commands"] = {"enabled": DEMO_COMMANDS}
    if settings.mqtt.enabled:
        return []
    mosquitto = _find_mosquitto()
    if mosquitto is None:
        return ["dashboard: not started: it needs an MQTT broker and mosquitto is not "
                "installed (apt-get install mosquitto, or make mosquitto)"]
    port = _free_port()
    scratch = tempfile.TemporaryDirectory(prefix="sowgate-demo-broker-")
    stack.callback(scratch.cleanup)
    conf = Path(scratch.name) / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
                    "log_dest none\n", encoding="utf-8")
    # its own session: Ctrl-C in the terminal signals the whole foreground process group, and
    # a broker that went with it left the daemon's last records unacknowledged ("published
    # after the next start", which the next demo's new broker never does). The demo stops it
    # itself, after the daemon has drained (the exit stack unwinds after daemon.run()).
    proc = subprocess.Popen([mosquitto, "-c", str(conf)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    stack.callback(_stop_process, proc)
    _wait_listening(port, proc, "mosquitto")
    overrides["mqtt"] = {"enabled": True, "host": "127.0.0.1", "port": port,
                         "reconnect_max_s": 2.0}
    return []


def _wait_listening(port: int, proc: subprocess.Popen[bytes], what: str) -> None:
    deadline = time.monotonic() + 15.0
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            if proc.poll() is not None:
                raise RuntimeError(f"{what} exited with {proc.returncode}") from None
            if time.monotonic() > deadline:
                raise RuntimeError(f"{what} did not listen on port {port}") from None
            time.sleep(0.05)


def _start_dashboard(
    stack: contextlib.AsyncExitStack, state: Path, settings: Settings
) -> list[str]:
    """``sowgate dashboard`` on the demo's config, in its own process; its URL."""
    port = _free_port(DASHBOARD_PORT)
    log_path = state / "dashboard.log"
    with log_path.open("ab") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway.app.cli", "dashboard", "--config",
             str(state / CONFIG_FILE), "--listen", f"127.0.0.1:{port}"],
            stdin=subprocess.DEVNULL, stdout=out, stderr=out,
            start_new_session=True,  # as the broker: stopped by the demo, not by Ctrl-C
        )
    stack.callback(_stop_process, proc)
    _wait_listening(port, proc, f"sowgate dashboard (see {log_path})")
    m = settings.mqtt
    return [
        f"dashboard: open http://127.0.0.1:{port}/ in a browser (MQTT broker "
        f"{m.host}:{m.port}; start, stop, rate and alarm acknowledgement enabled; its log: "
        f"{_shown(log_path)})",
    ]


def _shown(path: Path) -> str:
    """A path as the user can type it back (relative ones as given)."""
    return shlex.quote(str(path))


def program() -> str:
    """``sowgate`` as the user can type it in this shell: after ``make demo`` on a fresh
    clone the entry point is ``.venv/bin/sowgate``, not on PATH, and a bare ``sowgate report``
    said "command not found" to exactly the new user the printed next steps are for."""
    entry = Path(sys.executable).parent / "sowgate"
    if not entry.exists():
        return "sowgate"
    found = shutil.which("sowgate")
    if found is not None and Path(found).resolve() == entry.resolve():
        return "sowgate"
    try:
        return shlex.quote(str(entry.absolute().relative_to(Path.cwd())))
    except ValueError:
        return shlex.quote(str(entry.absolute()))


async def start_text(
    machine: SimulatedMachine,
    settings: Settings,
    state: Path,
    duration_s: float | None,
    tui: bool,
    channels: bool,
    status_on_stdout: bool = False,
) -> str:
    """What the demo tells the user before it starts: what runs where, and how to stop."""
    assert machine.rs485 is not None and machine.hmi is not None
    lines = [
        f"sowgate demo: the daemon drives a simulated {machine.crop} seeder "
        "(a scripted operator selects the crop and presses start after 1.5 s)",
        f"  RS485 radar, inclinometer and PWM module on {machine.rs485.device_path}",
        f"  TJC touchscreen on {machine.hmi.device_path}",
    ]
    if machine.gnss is not None:
        lines.append(f"  UM982 GNSS receiver on {machine.gnss.device_path}")
    if machine.seed_tubes is not None:
        lines.append(
            f"  seed-tube sensors ({settings.machine.rows} rows) on "
            f"{machine.seed_tubes.device_path}"
        )
    if channels:
        lines.append(
            f"  3 CAN metering controllers (paper B) on virtual bus {settings.can.channel}"
        )
    lines += [
        f"config: {_shown(state / CONFIG_FILE)} (its device paths exist only while the demo "
        "runs; SOWGATE_* environment variables override it)",
        f"record store: {_shown(state / 'records.sqlite3')} (kept after the demo; earlier "
        "demo runs stay in it, delete the folder to start afresh)",
        *await _mqtt_lines(settings),
        "view: live in this terminal; \"actually applied\" is what the simulated meter "
        "really put on the ground (only a simulator knows it), against the target rate"
        if tui
        else f"view: standard output is not a terminal, so a status line every "
        f"{STATUS_EVERY_S:g} s here instead of the live view"
        if status_on_stdout
        else "status: a line every few seconds on standard error",
        f"runs for {duration_s:g} s (Ctrl-C stops it sooner)"
        if duration_s is not None
        else "runs until Ctrl-C",
    ]
    return "\n".join(lines)


async def _mqtt_lines(settings: Settings) -> list[str]:
    m = settings.mqtt
    if not m.enabled:
        return [
            "MQTT: off. To publish, start a broker and run e.g. "
            "SOWGATE_MQTT__ENABLED=true SOWGATE_MQTT__HOST=localhost SOWGATE_MQTT__PORT=1883 "
            "sowgate demo"
        ]
    base = f"{m.topic_prefix}/{settings.machine.id}"
    try:
        _reader, writer = await asyncio.wait_for(
            asyncio.open_connection(m.host, m.port), BROKER_PROBE_S
        )
    except (OSError, TimeoutError):
        reach = "not reachable now: the daemon keeps retrying and keeps every record meanwhile"
    else:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()
        reach = "reachable"
    return [
        f"MQTT: broker {m.host}:{m.port} ({reach})",
        f"  topics {base}/status, /state, /seeds, /alarms (docs/mqtt.md); watch them with "
        f"mosquitto_sub -h {m.host} -p {m.port} -t '{base}/#' -v",
    ]


def end_text(machine: SimulatedMachine, state: Path, channels: bool) -> str:
    """What was done (the outputs are off) and what to try next on the store that was kept."""
    assert machine.rs485 is not None
    duty = machine.rs485.duty_pct
    motor, fan = duty.get("motor", 0.0), duty.get("fan", 0.0)
    if motor == 0.0 and fan == 0.0:
        outputs = "motor and fan set to 0 (the simulated PWM module reads 0 %)"
    else:
        outputs = f"WARNING: the PWM module still reads motor {motor:.1f} %, fan {fan:.1f} %"
    sowgate = program()
    lines = [
        outputs,
        f"next: the seeds it recorded, with per-row spacing quality: "
        f"{sowgate} export --state-dir {_shown(state)} --output demo-seeds.csv",
        f"      the field report (seed map, per-row quality, rate, alarms; opens offline): "
        f"{sowgate} report --config {_shown(state / CONFIG_FILE)} --state-dir {_shown(state)} "
        f"--output demo-report.html",
    ]
    if channels:
        lines.append(
            f"      the channels' as-applied log: {sowgate} export --what as-applied "
            f"--state-dir {_shown(state)} --output demo-applied.csv"
        )
    return "\n".join(lines)


def status_line(state: MachineState) -> str:
    """One line of the daemon's state for ``--no-tui`` (the live view's essentials)."""
    speed, source = state.speed_kmh, state.speed_source
    parts = [
        state.work_state,
        "no speed" if speed is None else f"{speed:.2f} km/h" + (f" [{source}]" if source else ""),
        f"motor {state.motor_duty_pct:.1f} % fan {state.fan_duty_pct:.1f} %",
        f"{state.area_ha:.4f} ha",
    ]
    if state.seeds is not None:
        parts.append(f"{state.seeds.records_stored} seeds recorded")
    if state.hopper is not None:
        h = state.hopper
        se = h.correction_standard_error
        parts.append(
            f"hopper {'--' if h.mass_kg is None else f'{h.mass_kg:.0f}'} kg, correction "
            f"x{h.discharge_correction:.3f}" + ("" if se is None else f" (SE {se * 100:.1f} %)")
        )
    codes = [a.code for a in state.alarms]
    parts.append("alarms: " + (", ".join(codes) or "none"))
    return ", ".join(parts)


async def _log_status(daemon: Daemon, on_stdout: bool = False) -> None:
    while True:
        await asyncio.sleep(STATUS_EVERY_S)
        line = status_line(daemon.state())
        if on_stdout:
            print(f"{time.strftime('%H:%M:%S')} {line}", flush=True)
        else:
            log.info("%s", line)


async def _start_controllers(stack: contextlib.AsyncExitStack, can_channel: str) -> dict[str, Any]:
    """Paper B's PID controllers + hydraulic motors answering on the virtual CAN bus."""
    from drivers.can_bus import CanBus
    from simulator.can_pid import MeteringControllerSim, MeterPlant

    bus = await stack.enter_async_context(CanBus("virtual", can_channel))
    plants = {
        name: MeterPlant(grams_per_rev=g_per_rev, outlets=PAPER_B_OUTLETS)
        for name, _product, _rate, g_per_rev in PAPER_B_CHANNELS
    }
    sim = MeteringControllerSim(
        bus, {node: plants[name] for node, (name, *_) in enumerate(PAPER_B_CHANNELS, start=1)}
    )
    task = asyncio.create_task(sim.run(), name="demo-can-controllers")

    async def stop() -> None:
        await cancel_and_wait(task)

    stack.push_async_callback(stop)
    return plants


def cmd_demo(args: argparse.Namespace) -> int:
    # the live view redraws a terminal; into a pipe (`make demo | tee`) it would show nothing
    # until the end, so there the demo prints plain status lines instead
    live = not args.no_tui and sys.stdout.isatty()
    setup_logging(args.verbose, quiet=not args.no_tui)
    return asyncio.run(
        run_demo(
            duration_s=args.duration,
            tui=live,
            status_on_stdout=not args.no_tui and not live,
            crop=args.crop,
            channels=args.channels,
            state=args.state_dir,
            hopper_scale=args.hopper_scale,
            dashboard=args.dashboard,
        )
    )


def add_demo_command(sub: Any) -> None:
    """``sowgate demo``, registered by entry point (``sowgate.commands`` in pyproject.toml)."""
    d = sub.add_parser("demo", help="run the daemon against the built-in simulated machine")
    d.add_argument("--duration", type=float, default=None, help="seconds (default: until ^C)")
    d.add_argument(
        "--no-tui",
        action="store_true",
        help="log a status line every few seconds instead of the live view",
    )
    d.add_argument(
        "--state-dir",
        type=Path,
        default=None,
        help="where the demo keeps its record store and config (default: ./sowgate-demo); "
        "never the real state directory",
    )
    d.add_argument("--crop", choices=["rapeseed", "wheat"], default="rapeseed")
    d.add_argument(
        "--channels",
        action="store_true",
        help="add paper B's three CAN metering channels (simulated PID controllers on a "
        "virtual CAN bus)",
    )
    d.add_argument(
        "--hopper-scale",
        action="store_true",
        help="add a hopper scale on the RS485 bus (σ 2 kg vibration, a refill at 10 min) "
        "and make the simulated drill discharge 8 %% more than its model, to watch the "
        "correction find it",
    )
    d.add_argument(
        "--dashboard",
        action="store_true",
        help="also serve the web dashboard (make demo does): on the broker SOWGATE_MQTT__* "
        "names, else on a private mosquitto when one is installed; prints its URL",
    )
    d.set_defaults(func=cmd_demo)
