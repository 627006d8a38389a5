"""``<state_dir>/daemon.json``: the running daemon and the calibration file it has applied.

The CLI and the daemon share nothing but the state directory. The daemon writes this file at
start and after each (re)load of ``calibration.json``: its pid and the signature (inode,
size, mtime) of the calibration file it applied, with what it made of it. It removes the file
when it stops. So ``sowgate calibrate`` can say after a save whether a running daemon picked
the calibration up or it applies at the next start, and refuses to drive the meter's bus
while a daemon owns it. A file left by a daemon that was killed names a pid that no longer
runs (or runs something else) and is ignored.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any

from gateway.calibration.fits import CALIBRATION_FILE, atomic_write_json

PRESENCE_FILE = "daemon.json"
WATCH_S = 2.0  # how often a running daemon looks at calibration.json's signature


def calibration_signature(state_dir: Path) -> list[int] | None:
    """What identifies one version of ``calibration.json`` (None: there is none).

    The store writes a new file and renames it over the old one, so the inode changes with
    every save even when two saves fall within the file system's mtime resolution."""
    try:
        st = (state_dir / CALIBRATION_FILE).stat()
    except OSError:
        return None
    return [st.st_ino, st.st_size, st.st_mtime_ns]


def write_presence(state_dir: Path, doc: dict[str, Any]) -> None:
    atomic_write_json(state_dir / PRESENCE_FILE, {"pid": os.getpid(), **doc})


def remove_presence(state_dir: Path) -> None:
    path = state_dir / PRESENCE_FILE
    with contextlib.suppress(OSError, ValueError):
        if json.loads(path.read_text(encoding="utf-8")).get("pid") == os.getpid():
            path.unlink()


def _is_sowgate(pid: int) -> bool:
    if pid == os.getpid():
        return True  # a daemon run in this very process (tests, the demo)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # runs, as another user
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return True  # no /proc: trust the pid
    return b"sowgate" in cmdline or b"gateway.app" in cmdline


def running_daemon(state_dir: Path) -> dict[str, Any] | None:
    """The presence record of a daemon running on ``state_dir``, or None."""
    try:
        doc = json.loads((state_dir / PRESENCE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    pid = doc.get("pid") if isinstance(doc, dict) else None
    if not isinstance(pid, int) or pid <= 0 or not _is_sowgate(pid):
        return None
    return dict(doc)
