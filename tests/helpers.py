"""Helpers every kind of test shares, kept once here.

- ``eventually``: wait until a condition holds, failing with what was awaited (no test writes
  its own deadline loop);
- ``sowgate_argv`` / ``sowgate_env`` / ``run_sowgate`` / ``spawn_sowgate`` / ``sowgate_process``:
  the daemon (``python -m gateway.app.cli …``, what systemd starts) as a separate process;
- ``wheat_drill`` / ``calibration_cli``: a one-channel CAN drill's settings, and
  ``sowgate calibrate …`` run in-process (no questions may be asked) with its output on one line;
- ``Plant``: the values the simulated RS485 devices report, which a test changes between
  requests (the ``plant`` and ``sim`` fixtures in ``tests/conftest.py`` build on it).

The real mosquitto broker and the dashboard subscriber live in ``tests/mosquitto.py``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Callable, Mapping
from pathlib import Path
from typing import IO, Any

import pytest
from rich.console import Console

from gateway.calibration.cli import add_calibration_commands, run_calibration
from gateway.config import Settings, parse_config

WAIT_S = 15.0  # generous (two cores shared by many test runs): only a failing test waits it out
POLL_S = 0.05


# ---- waiting ------------------------------------------------------------------------------------


async def eventually(
    check: Callable[[], object],
    timeout: float = WAIT_S,
    what: str = "",
    *,
    interval: float = POLL_S,
    unless: asyncio.Task[Any] | None = None,
    detail: Callable[[], object] | None = None,
) -> float:
    """Wait until ``check()`` is true; the seconds it took.

    AssertionError naming ``what`` (and ``detail()``, if given) after ``timeout`` seconds. With
    ``unless``, a task that must keep running meanwhile (the daemon): if it ends, its exception
    is raised, or an AssertionError saying it exited.
    """
    loop = asyncio.get_running_loop()
    start = loop.time()
    while not check():
        if unless is not None and unless.done():
            unless.result()
            raise AssertionError(f"{unless.get_name()} exited while waiting for {what or check}")
        if loop.time() - start > timeout:
            extra = f"; {detail()}" if detail is not None else ""
            raise AssertionError(
                f"timed out after {timeout:g} s waiting for {what or check}{extra}"
            )
        await asyncio.sleep(interval)
    return loop.time() - start


# ---- calibration --------------------------------------------------------------------------------


def wheat_drill() -> Settings:
    """A 3 m, 24-row drill sowing wheat from one CAN-metered channel ``seed`` (no touchscreen)."""
    return parse_config({
        "hmi": {"enabled": False},
        "machine": {"working_width_m": 3.0, "rows": 24},
        "channel": [{"name": "seed", "product": "wheat", "target_rate_kg_ha": 225.0,
                     "node_id": 3, "outlets": 24, "grams_per_rev": 11.2}],
    })


def calibration_cli(argv: list[str]) -> tuple[int, str]:
    """``sowgate <argv>`` for the calibration commands, in-process: its exit code and its
    output with white space folded (rich wraps); a question asked fails the test."""
    root = argparse.ArgumentParser(prog="sowgate")
    add_calibration_commands(root.add_subparsers(dest="command"))
    out = io.StringIO()
    code = run_calibration(root.parse_args(argv), console=Console(file=out, width=200),
                           ask=lambda q: pytest.fail(f"asked {q!r}"))
    return code, " ".join(out.getvalue().split())


# ---- the daemon as its own process --------------------------------------------------------------


def sowgate_argv(*args: str, console_script: bool = False) -> list[str]:
    """The command line of ``sowgate ARGS``: ``python -m gateway.app.cli ARGS``, or with
    ``console_script`` the installed ``sowgate`` script itself (what the systemd unit starts)."""
    if console_script:
        return [str(Path(sys.executable).with_name("sowgate")), *args]
    return [sys.executable, "-m", "gateway.app.cli", *args]


def sowgate_env(
    state_dir: Path | None = None, env: Mapping[str, str] | None = None, *, clean: bool = False
) -> dict[str, str]:
    """This process's environment for a daemon: its store in ``state_dir``, plus ``env``.

    ``clean`` drops every ``SOWGATE_*`` variable (and systemd's ``STATE_DIRECTORY``) first, so
    the developer's own settings cannot leak into a test.
    """
    base = dict(os.environ)
    if clean:
        base = {k: v for k, v in base.items()
                if k != "STATE_DIRECTORY" and not k.startswith("SOWGATE_")}
    if state_dir is not None:
        base["SOWGATE_STATE_DIR"] = str(state_dir)
    return {**base, **(env or {})}


def run_sowgate(
    *args: str,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
    timeout: float = 60.0,
    console_script: bool = False,
) -> subprocess.CompletedProcess[str]:
    """``sowgate ARGS`` to its end (it must end within ``timeout``), its output as text.
    ``env`` is the whole environment (see ``sowgate_env``); None inherits this process's."""
    return subprocess.run(
        sowgate_argv(*args, console_script=console_script),
        capture_output=True, text=True, timeout=timeout, cwd=cwd,
        env=None if env is None else dict(env),
    )


Output = int | IO[Any] | None


async def spawn_sowgate(
    *args: str,
    env: Mapping[str, str] | None = None,
    stdout: Output = asyncio.subprocess.PIPE,
    stderr: Output = asyncio.subprocess.PIPE,
) -> asyncio.subprocess.Process:
    """``sowgate ARGS`` started in its own process (stdin closed); the caller reaps it.
    ``env`` is the whole environment (see ``sowgate_env``); None inherits this process's."""
    return await asyncio.create_subprocess_exec(
        *sowgate_argv(*args),
        env=None if env is None else dict(env),
        stdin=asyncio.subprocess.DEVNULL, stdout=stdout, stderr=stderr,
    )


@contextlib.asynccontextmanager
async def sowgate_process(
    *args: str,
    env: Mapping[str, str] | None = None,
    stdout: Output = asyncio.subprocess.PIPE,
    stderr: Output = asyncio.subprocess.PIPE,
) -> AsyncIterator[asyncio.subprocess.Process]:
    """``spawn_sowgate`` for the block; a daemon still running when it ends is killed, whatever
    the test did, so none is left behind."""
    proc = await spawn_sowgate(*args, env=env, stdout=stdout, stderr=stderr)
    try:
        yield proc
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


# ---- the RS485 plant ----------------------------------------------------------------------------


class Plant:
    """What the simulated radar and inclinometer report (tests change it between requests), and
    every duty the simulated PWM module was told, in order."""

    def __init__(self, kmh: float = 5.0, tilt: float = 0.0) -> None:
        self.kmh = kmh
        self.tilt = tilt
        self.duties: list[tuple[str, float]] = []

    def on_duty(self, channel: str, pct: float) -> None:
        self.duties.append((channel, pct))
