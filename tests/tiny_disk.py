"""A real, tiny filesystem that fills up, for the "disk full" tests.

A tmpfs mounted with ``size=2m`` is a disk that really runs out of space: SQLite gets
``SQLITE_FULL`` from the kernel exactly as it would on a full SD card, and ``grow`` (a
``remount`` with a larger size) gives the space back without touching the files, as an
operator deleting old exports would. Mounting needs CAP_SYS_ADMIN: CI runs as root; anyone
else runs the test again inside a user and mount namespace (``unshare -rm``), where they are
root over their own mounts, and the outer test passes only if that run passed.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

SMALL = "2m"
LARGE = "64m"
_INSIDE = "SOWGATE_TEST_IN_MOUNT_NAMESPACE"


def may_mount() -> bool:
    return os.geteuid() == 0


def run_in_mount_namespace(request: pytest.FixtureRequest) -> None:
    """Run this one test again under ``unshare -rm`` and fail if it fails there."""
    if os.environ.get(_INSIDE):
        raise RuntimeError("no permission to mount a tmpfs even inside a mount namespace")
    env = {**os.environ, _INSIDE: "1"}
    done = subprocess.run(
        ["unshare", "-rm", sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         request.node.nodeid],
        cwd=request.config.rootpath, env=env, capture_output=True, text=True, check=False,
    )
    assert done.returncode == 0, f"in a mount namespace:\n{done.stdout}\n{done.stderr}"


@contextlib.contextmanager
def tiny_tmpfs(path: Path, size: str = SMALL) -> Iterator[Path]:
    """Mount a tmpfs of ``size`` on ``path`` (created) for the duration of the block."""
    path.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                   check=True)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def grow(path: Path, size: str = LARGE) -> None:
    """Give the full tmpfs room again, keeping its files (the operator freed space)."""
    subprocess.run(["mount", "-o", f"remount,size={size}", str(path)], check=True)


def fill(path: Path) -> None:
    """Take the last free bytes with a ballast file, so the next write hits ENOSPC."""
    with contextlib.suppress(OSError), (path / "ballast").open("wb") as f:
        while True:
            f.write(b"\0" * 65536)
            f.flush()
