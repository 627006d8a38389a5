"""What the daemon says and checks at start, and ``sowgate check-config`` with it.

Nothing may be off or missing without a word: one line lists which parts are on
(``parts_summary``), and every file or directory the config names is checked before anything
runs (``input_file_problems``, ``output_location_problems``, ``prepare_state_dir``), so a
missing CA certificate or a state directory that is really a file is a config error naming
the key and the path (exit 78, which systemd does not restart in a loop), not a traceback or
an ``[Errno 2]`` retried for ever.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path
from typing import IO, TYPE_CHECKING

from gateway.core.errors import ConfigError
from gateway.core.files import regular_file_problem

if TYPE_CHECKING:
    from gateway.config import ChannelSection, Settings

DEFAULT_STATE_DIR = "sowgate-state"


def _part_details(settings: Settings) -> dict[str, str]:
    """How each part is reached, shown after "on" so a wrong port or broker stands out."""
    s = settings
    seeds = s.seed_sensors
    mqtt = f"{s.mqtt.host}:{s.mqtt.port}" + (" TLS" if s.mqtt.tls is not None else "")
    return {
        "rs485": s.rs485.port,
        "hmi": s.hmi.port,
        "gnss": s.gnss.port,
        "seed_sensors": seeds.port if seeds.source == "serial" else f"gpio {seeds.gpio_chip}",
        "mqtt": mqtt,
        "can": f"{s.can.interface} {s.can.channel}",
        "isobus": f"{s.isobus.interface} {s.isobus.channel}",
        "agopengps": f"{s.agopengps.listen}, AgIO {s.agopengps.agio or 'first seen'}",
        "prescription": s.prescription.path or "no path",
        "hopper_scale": f"RS485 id {s.hopper_scale.device_id}",
    }


def parts_summary(settings: Settings) -> str:
    """One line: every optional part on or off, then every metering channel.

    The daemon logs it at start and ``check-config`` prints it after "ok", e.g.
    ``parts: rs485 on (/dev/ttyUSB0), hmi on (/dev/ttyS1), gnss off, ..., mqtt on
    (broker.example:8883 TLS), can off, ...``. A channel whose drive is off says so.
    """
    from gateway.config import optional_parts

    details = _part_details(settings)
    words = []
    for name in optional_parts():
        if name == "row_monitor" and settings.row_monitor.enabled and not (
            settings.seed_sensors.enabled
        ):
            words.append("row_monitor off (no seed_sensors)")
        elif getattr(settings, name).enabled:
            detail = details.get(name)
            words.append(f"{name} on ({detail})" if detail else f"{name} on")
        else:
            words.append(f"{name} off")
    undriven = undriven_channels(settings)
    for ch in settings.channel:
        if ch.drive == "pwm_modbus":
            words.append(f"channel {ch.name} on (pwm_modbus)")
        elif ch in undriven:
            words.append(f"channel {ch.name} off (can_pid, but can is off)")
        else:
            words.append(f"channel {ch.name} on (can_pid node {ch.node_id})")
    return "parts: " + ", ".join(words)


def undriven_channels(settings: Settings) -> list[ChannelSection]:
    """The ``can_pid`` channels nothing drives because the CAN bus is off.

    Not a config error (a fitter may switch the bus off for a day), but never silent: the
    parts line says ``off``, ``check-config`` warns and the daemon raises
    ``channel.can_disabled``, all from this one list.
    """
    if settings.can.enabled:
        return []
    return [c for c in settings.channel if c.drive == "can_pid"]


# ---- files the config names --------------------------------------------------------------------


def file_problem(path: str | os.PathLike[str]) -> str | None:
    """Why the file at ``path`` cannot be read, or None if it can.

    Opened for real: as root (the tests, many field boxes) ``os.access`` says yes to anything.
    """
    # without blocking: a FIFO's open waits for a writer (check-config hung on one)
    return regular_file_problem(path)


CREDENTIALS_ROOT = "/run/credentials/"


def credential_elsewhere(path: str | os.PathLike[str]) -> str | None:
    """The unit whose systemd credential ``path`` is (``/run/credentials/<unit>/<name>``, put
    there by ``LoadCredential=`` while that unit runs), when this process is not that unit;
    None for any other path, or inside the unit (``$CREDENTIALS_DIRECTORY``), where the file
    is checked like any other. ``check-config`` run by the fitter or install.sh cannot see a
    credential: it names it instead of calling it missing."""
    text = os.fspath(path)
    if not text.startswith(CREDENTIALS_ROOT):
        return None
    folder = os.path.dirname(text)
    if os.environ.get("CREDENTIALS_DIRECTORY", "").rstrip("/") == folder:
        return None
    return folder.removeprefix(CREDENTIALS_ROOT) or None


def credential_notes(settings: Settings) -> list[str]:
    """``check-config``'s notes on the files that are systemd credentials of a unit."""
    named = [("mqtt.password_file", settings.mqtt.password_file),
             ("dashboard.password_file", settings.dashboard.password_file)]
    return [f"{key}: {path} is a systemd credential of {unit} (LoadCredential=): it exists "
            f"only inside that service, which checks it when it starts (exit 78 if missing)"
            for key, path in named
            if path is not None and (unit := credential_elsewhere(path)) is not None]


def input_file_problems(settings: Settings) -> list[str]:
    """``key: problem (got path)`` for every file an enabled part reads and cannot read.

    A part that is off needs none of its files. Device nodes (serial ports, the GPIO chip,
    CAN interfaces) are not files the config provides: they may appear later (a USB adapter
    plugged in) and their drivers reconnect and alarm.
    """
    files: list[tuple[str, str | None]] = []
    mqtt = settings.mqtt
    if mqtt.enabled:
        files.append(("mqtt.password_file", mqtt.password_file))
        if mqtt.tls is not None:
            files += [
                ("mqtt.tls.ca_file", mqtt.tls.ca_file),
                ("mqtt.tls.cert_file", mqtt.tls.cert_file),
                ("mqtt.tls.key_file", mqtt.tls.key_file),
            ]
    problems = []
    rx = settings.prescription.path
    if settings.prescription.enabled:
        if rx is not None and Path(rx).is_dir():  # an ISO-XML TaskData folder
            if not os.access(rx, os.R_OK | os.X_OK):
                problems.append(f"prescription.path: the folder is not readable (got {rx!r})")
        else:
            files.append(("prescription.path", rx))
    for key, path in files:
        if path is None or credential_elsewhere(path) is not None:
            continue
        problem = file_problem(path)
        if problem is not None:
            problems.append(f"{key}: {problem} (got {path!r})")
    return problems


def dashboard_problems(settings: Settings) -> list[str]:
    """What stops ``sowgate dashboard`` from starting (exit 78), each naming its key.

    ``check-config`` says them too: the fitter who sets ``listen = "0.0.0.0:8080"`` to open
    the page from the office should hear that the password file is missing before the
    dashboard's unit fails at boot. The listen address's form is the schema's.
    """
    from gateway.config.farm import DASHBOARD_COMMANDS

    d = settings.dashboard
    controls = [c for c in DASHBOARD_COMMANDS if c in settings.commands.enabled]
    problems: list[str] = []
    if d.password_file is not None and credential_elsewhere(d.password_file) is not None:
        pass  # inside its unit only: checked there at start (credential_notes)
    elif d.password_file is not None:
        problem = file_problem(d.password_file)
        if problem is None and not Path(d.password_file).read_text(
                encoding="utf-8", errors="replace").strip():
            problem = "the file is empty (it holds the page's password on one line)"
        if problem is not None:
            problems.append(f"dashboard.password_file: {problem} (got {d.password_file!r})")
    elif controls and not d.local_only:
        problems.append(
            f"dashboard.password_file: needed when dashboard.listen ({d.listen}) is not "
            f"localhost (127.0.0.1, ::1, localhost) and the page offers commands ([commands] "
            f"enabled: {', '.join(controls)}); set it, listen on 127.0.0.1, or disable those "
            "commands"
        )
    return problems


# ---- directories the daemon writes to ------------------------------------------------------------


def _nearest_existing(path: Path) -> Path:
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return Path(path.anchor or ".")


def directory_problem(path: Path, *, create: bool) -> str | None:
    """Why the daemon cannot keep files in directory ``path``, or None.

    ``create``: make it and write a scratch file in it, as the daemon does at start.
    Otherwise (``check-config``, which must change nothing) look only: the nearest existing
    ancestor must be a writable directory.
    """
    if path.exists() and not path.is_dir():
        return "a file, not a directory"
    existing = _nearest_existing(path)
    if not existing.is_dir():
        return f"cannot create the directory: {existing} is a file"
    if not create:
        if not os.access(existing, os.W_OK | os.X_OK):
            return f"not writable: {existing}"
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot create the directory: {exc.strerror or exc}"
    try:
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        return f"not writable: {exc.strerror or exc}"
    return None


def output_location_problems(settings: Settings, *, create: bool) -> list[str]:
    """``key: problem (got path)`` for files the daemon writes outside the state directory:
    the record store (``store.path``) and the as-applied log (``prescription.as_applied_path``).
    """
    files: list[tuple[str, str | None]] = []
    if settings.mqtt.enabled or settings.seed_sensors.enabled:
        files.append(("store.path", settings.store.path))
    if settings.channel:
        files.append(("prescription.as_applied_path", settings.prescription.as_applied_path))
    problems = []
    for key, path in files:
        if path is None:
            continue
        p = Path(path)
        if p.is_dir():
            problem: str | None = "a directory, not a file"
        elif p.parent.exists() and not p.parent.is_dir():
            problem = f"cannot create the directory: {p.parent} is a file"
        else:
            problem = directory_problem(p.parent, create=create)
        if problem is not None:
            problems.append(f"{key}: {problem} (got {path!r})")
    return problems


def resolve_state_dir() -> tuple[Path, str]:
    """The state directory and where it came from, for messages: ``$SOWGATE_STATE_DIR``, else
    systemd's ``$STATE_DIRECTORY`` (its first entry), else ``./sowgate-state``."""
    explicit = os.environ.get("SOWGATE_STATE_DIR")
    if explicit:
        return Path(explicit), "$SOWGATE_STATE_DIR"
    systemd_dir = os.environ.get("STATE_DIRECTORY")
    if systemd_dir:
        return Path(systemd_dir.split(":")[0]), "$STATE_DIRECTORY"
    return Path(DEFAULT_STATE_DIR), "state directory (default; set $SOWGATE_STATE_DIR)"


def prepare_state_dir() -> Path:
    """Create the state directory and prove it writable, or raise ConfigError naming the
    variable it came from and the path (``$SOWGATE_STATE_DIR: a file, not a directory ...``).
    """
    path, source = resolve_state_dir()
    problem = directory_problem(path, create=True)
    if problem is not None:
        raise ConfigError([f"{source}: {problem} (got {str(path)!r})"])
    return path


STATE_LOCK_FILE = "sowgate.lock"


def lock_state_dir(path: Path) -> IO[str]:
    """Hold the state directory for this process (``fcntl.flock`` on ``sowgate.lock``), or
    raise ConfigError naming the directory and the pid of the daemon that holds it.

    Two daemons on one state directory mixed two machines' records in one store with no
    warning. The lock is the kernel's: it goes with the process (a crash or a power cut leaves
    no stale lock behind); the pid written in the file only names the holder. Keep the returned
    file open for as long as the daemon runs.
    """
    lock_path = path / STATE_LOCK_FILE
    try:
        handle = lock_path.open("a+", encoding="utf-8")
    except OSError as exc:
        raise ConfigError([f"state directory: cannot open its lock file {str(lock_path)!r}: "
                           f"{exc.strerror or exc}"]) from None
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        holder = handle.read(32).strip() or "unknown"
        handle.close()
        raise ConfigError([
            f"state directory: {str(path)!r} is in use by another sowgate daemon (pid "
            f"{holder}, holding {STATE_LOCK_FILE}); two daemons on one directory would mix "
            "their records: stop that one, or give this one its own SOWGATE_STATE_DIR"
        ]) from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle


def start_problems(settings: Settings, state_dir: Path) -> list[str]:
    """Everything the daemon checks before it builds its parts (``Daemon.__init__``)."""
    problems = []
    state = directory_problem(state_dir, create=True)
    if state is not None:
        problems.append(f"state directory: {state} (got {str(state_dir)!r})")
    return problems + input_file_problems(settings) + output_location_problems(
        settings, create=True
    )
