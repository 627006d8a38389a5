"""``sowgate``: the daemon, config checking, the simulated demo and field tools."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from gateway.config import (
    EXIT_CONFIG,
    ConfigError,
    Settings,
    dashboard_problems,
    input_file_problems,
    load_config,
    lock_state_dir,
    output_location_problems,
    parts_summary,
    prepare_state_dir,
    undriven_channels,
)
from gateway.core.journal_logging import use_journal_priorities

log = logging.getLogger("sowgate")

# ``sowgate run`` stopped but could not set motor and fan to 0 (the PWM module did not answer)
EXIT_NOT_SAFE = 1

DESCRIPTION = """\
sowgate: the seeder daemon, config checking, a demo on a simulated machine,
and field tools (export, field report, calibration, GNSS decoding)."""
EPILOG = """\
Try it:       sowgate demo                  (Ctrl-C to stop)
On a tractor: sowgate check-config FILE, then sowgate run --config FILE
              (installing it as a service: systemd/README.md)"""


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sowgate")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def setup_logging(verbose: bool, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )
    use_journal_priorities()
    # pymodbus logs every server start ("Server listening."), frame dumps, its own view of
    # each failed connect or request and a repeat marker ("Repeating....", at WARNING):
    # noise next to sowgate's own device messages, which say the same once, naming the
    # device and the port. Only -v lets it through.
    logging.getLogger("pymodbus").setLevel(logging.DEBUG if verbose else logging.CRITICAL)


def check_settings(settings: Settings) -> tuple[list[str], list[str]]:
    """What the schema cannot see: files the config names, the prescription map's content,
    unused tables.

    Returns (problems, warnings). A missing or unreadable file, or a store the daemon could not
    create, stops the daemon at start (exit 78) as well; it survives the rest (a bad map means
    default rates and an alarm), but a fitter checking a config wants to hear about them now.
    """
    problems: list[str] = input_file_problems(settings)
    problems += output_location_problems(settings, create=False)
    problems += dashboard_problems(settings)
    from gateway.config.startup import credential_notes

    warnings: list[str] = settings.deprecation_notes() + credential_notes(settings)
    p = settings.prescription
    undriven = [c.name for c in undriven_channels(settings)]
    if undriven:
        warnings.append(
            f"channel: {', '.join(undriven)} use drive = 'can_pid' but can is off (no [can] "
            "table, or [can] enabled = false); they will not be driven"
        )
    attrs = [c.prescription_attribute for c in settings.channel if c.prescription_attribute]
    if p.enabled:
        from gateway.metering.prescription import PrescriptionError, load_prescription

        # a missing or unreadable file is said above already, once
        if not any(line.startswith("prescription.path:") for line in problems):
            try:
                rx = load_prescription(settings)
            except PrescriptionError as exc:
                problems.append(str(exc))
            else:
                if rx is not None:
                    from gateway.metering.prescription import WIDE_MAP_KM

                    # where the map lies, so a fitter sees a map of another field now; the
                    # daemon compares it with the machine's position (far_from_field)
                    warnings.append(f"prescription map {p.path}: {len(rx.zones)} zones, rates "
                                    f"{attrs} ok; {rx.extent_note()}")
                    if max(rx.size_km()) > WIDE_MAP_KM:
                        warnings.append(
                            f"prescription map {p.path} spans {max(rx.size_km()):.0f} km: more "
                            "than a field (several farms' zones, or a stray polygon?)")
    elif attrs:
        warnings.append("channel: prescription_attribute set but prescription.enabled = false")
    return problems, warnings


def config_problems(problems: list[str]) -> int:
    """Print each config problem on its own line to stderr; the exit status for them.

    78 (EX_CONFIG) wherever the CLI meets a bad config, before or while starting the daemon:
    systemd's ``RestartPreventExitStatus=78`` then stops instead of restarting in a loop.
    """
    for line in problems:
        print(line, file=sys.stderr)
    return EXIT_CONFIG


def cmd_check_config(args: argparse.Namespace) -> int:
    try:
        settings = load_config(args.file)
    except ConfigError as exc:
        return config_problems(exc.problems)
    problems, warnings = check_settings(settings)
    for line in warnings:
        print(f"note: {line}", file=sys.stderr)
    if problems:
        return config_problems(problems)
    if args.systemd_device_allow:
        from gateway.app.systemd_devices import device_allow_dropin

        # stdout is the drop-in only (install.sh writes it to sowgate.service.d/devices.conf)
        print(f"{args.file}: ok", file=sys.stderr)
        sys.stdout.write(device_allow_dropin(settings, args.file))
        return 0
    print(f"{args.file}: ok (machine {settings.machine.id}, {settings.machine.rows} rows)")
    print(parts_summary(settings))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    try:
        settings = load_config(args.config)
        state = prepare_state_dir()
        # held until this process ends: a second daemon on this directory stops here (78)
        state_lock = lock_state_dir(state)
    except ConfigError as exc:
        return config_problems(exc.problems)
    try:
        return _run_daemon(args, settings, state)
    finally:
        state_lock.close()


def _run_daemon(args: argparse.Namespace, settings: Settings, state: Path) -> int:
    setup_logging(args.verbose)
    from gateway.app.daemon import Daemon, settle_gc
    from gateway.ui.terminal import run_with_live_view

    async def main() -> str | None:
        daemon = Daemon(settings, state)
        settle_gc()
        if args.tui:
            await run_with_live_view(daemon.state, daemon.run())
        else:
            await daemon.run()
        return daemon.safe_off_failure

    try:
        not_safe = asyncio.run(main())
    except ConfigError as exc:
        # found while building the daemon (a check only possible with its parts): still a
        # config problem, so 78 as well
        return config_problems(exc.problems)
    if not_safe is not None:
        # logged already; the last line again, after a live view that may have hidden it
        print(f"sowgate: {not_safe}", file=sys.stderr)
        return EXIT_NOT_SAFE
    return 0


# Subcommands that live outside gateway/: the simulator's ``demo`` registers itself here by entry
# point (pyproject.toml), so the product never imports the simulated machine.
PLUGIN_COMMANDS = "sowgate.commands"


def _add_plugin_commands(sub: Any) -> None:
    """Each entry point of ``PLUGIN_COMMANDS`` is ``add(subparsers)``: it adds its parser and
    sets ``func`` (and ``verbose`` comes from the main parser)."""
    for ep in sorted(entry_points(group=PLUGIN_COMMANDS), key=lambda e: e.name):
        ep.load()(sub)


def cmd_decode_gnss(args: argparse.Namespace) -> int:
    from gateway.recording.gnss_diagnostics import main_decode_gnss

    return main_decode_gnss(args.file, sys.stdout)


def cmd_export(args: argparse.Namespace) -> int:
    from gateway.app.export import main_export

    return int(main_export(args) or 0)


def cmd_report(args: argparse.Namespace) -> int:
    from gateway.report.command import main_report

    return main_report(args)


def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.calibrate_command == "positions":  # joins the record store: an app command
        from gateway.app.position_calibration import main_calibrate_positions

        return main_calibrate_positions(args)
    from gateway.calibration.cli import run_calibration
    from gateway.calibration.drive import abandoned_prompt

    code = run_calibration(args)
    if abandoned_prompt():  # Ctrl-C at a prompt: the meter is off, end without the shutdown
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="sowgate",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--version", action="version", version=f"sowgate {_version()}")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run the daemon")
    r.add_argument("--config", required=True, type=Path, help="TOML config file")
    r.add_argument("--tui", action="store_true", help="show the live terminal view")
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("check-config", help="validate a config file (exit 78 if invalid)")
    c.add_argument("file", type=Path)
    c.add_argument(
        "--systemd-device-allow",
        action="store_true",
        help="if the config passes, print the systemd drop-in that lets sowgate.service open "
        "exactly the configured ports (install.sh writes it to "
        "/etc/systemd/system/sowgate.service.d/devices.conf)",
    )
    c.set_defaults(func=cmd_check_config)

    _add_plugin_commands(sub)

    g = sub.add_parser("decode-gnss", help="decode receiver output, one JSON object per line")
    g.add_argument("file", help="capture file, or - for standard input")
    g.set_defaults(func=cmd_decode_gnss)

    e = sub.add_parser("export", help="export seed records (or the as-applied log)")
    e.add_argument(
        "--what",
        choices=["seeds", "as-applied", "alarms"],
        default="seeds",
        help="seed records with spacing quality (default), the metering as-applied log, or "
        "the alarm periods (CSV: raised, ended, and whether cleared or ended by a stop)",
    )
    e.add_argument(
        "--format",
        choices=["geojson", "csv", "isoxml"],
        default=None,
        help="default: from the --output extension (.csv -> csv; .geojson or .json -> "
        "geojson; geojson for -); isoxml: an ISO 11783-10 TaskData folder "
        "OUTPUT/TASKDATA with the seeds and the as-applied log as a task time log "
        "(docs/isoxml.md)",
    )
    e.add_argument(
        "--zip",
        action="store_true",
        help="with --format isoxml: write the TASKDATA folder into the zip file OUTPUT",
    )
    e.add_argument(
        "--output",
        required=True,
        help="file to write, or - for standard output; a seeds CSV also writes the per-row "
        "spacing quality to FILE.quality.csv",
    )
    e.add_argument("--since", default=None, help="ISO 8601 UTC start time")
    e.add_argument("--until", default=None, help="ISO 8601 UTC end time")
    e.add_argument("--rows", default=None, help="comma-separated row numbers")
    e.add_argument(
        "--reposition",
        action="store_true",
        help="seeds where the current position model says they landed (config + the saved "
        "'calibrate positions'), not as stored; records stored before they kept raw data "
        "are written as stored (counted)",
    )
    e.add_argument("--config", type=Path, default=None, help="config file (for the store path)")
    e.add_argument(
        "--state-dir",
        type=Path,
        default=None,
        help="read the store here (e.g. sowgate-demo), not in $SOWGATE_STATE_DIR",
    )
    from gateway.report.command import add_database_options, add_report_command

    add_database_options(e)
    e.set_defaults(func=cmd_export)

    add_report_command(sub)
    sub.choices["report"].set_defaults(func=cmd_report)

    try:
        from gateway.calibration.cli import add_calibration_commands
    except ImportError:  # pragma: no cover - calibration module is part of the package
        pass
    else:
        add_calibration_commands(sub).set_defaults(func=cmd_calibrate)
    return p


def take_ctrl_c() -> None:
    """Let Ctrl-C (SIGINT) raise KeyboardInterrupt even if it was ignored when we were started.

    A shell starts a background job (``make test &``, ``cmd &`` in a script) with SIGINT
    ignored, and the ignore is inherited through exec: Python then leaves it ignored, and
    asyncio.run only turns SIGINT into a cancel when the handler is Python's default. A
    calibration that cannot be stopped by the signal meant to stop it leaves a meter running,
    so every sowgate command takes SIGINT back (``run`` installs its own handlers on top).
    """
    signal.signal(signal.SIGINT, signal.default_int_handler)


def main(argv: list[str] | None = None) -> int:
    take_ctrl_c()
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # output piped into `head` and closed early: not an error of ours
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
