"""Fixtures that run the real daemon against the simulated machine over pty pairs."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from gateway.app.daemon import Daemon
from gateway.control.work_state import WorkState
from simulator.machine import SimulatedMachine
from simulator.modbus_devices import Rs485Simulator
from simulator.plant import Drive, Leg
from tests.helpers import eventually


def steady_drive(speed_kmh: float = 5.0, standing_s: float = 1.0, total_s: float = 600.0) -> Drive:
    return Drive(legs=[Leg(standing_s, 0.0), Leg(total_s, speed_kmh)], dt=0.02)


@dataclass
class Rig:
    machine: SimulatedMachine
    daemon: Daemon
    task: asyncio.Task[None]

    def state(self) -> WorkState | None:
        return None if self.daemon.outputs is None else self.daemon.outputs.state

    async def until(
        self, predicate: Callable[[], bool], timeout: float = 8.0, what: str = "condition"
    ) -> None:
        await eventually(
            predicate, timeout, what, unless=self.task,
            detail=lambda: f"state: {self.daemon.state()}",
        )

    async def stop(self) -> None:
        self.daemon.request_stop()
        await asyncio.wait_for(self.task, 5.0)


@contextlib.asynccontextmanager
async def running(
    tmp_path: Path, machine: SimulatedMachine, **overrides: Any
) -> AsyncIterator[Rig]:
    async with machine:
        daemon = Daemon(machine.settings(**overrides), tmp_path / "state")
        async with daemon_task(daemon) as task:
            yield Rig(machine, daemon, task)


@contextlib.asynccontextmanager
async def daemon_task(daemon: Daemon) -> AsyncIterator[asyncio.Task[None]]:
    """``daemon.run()`` as a task for the block; on leaving it the daemon is asked to stop
    (5 s), then cancelled (5 s more), so no test leaves a daemon behind."""
    task = asyncio.create_task(daemon.run(), name="daemon")
    try:
        yield task
    finally:
        if not task.done():
            daemon.request_stop()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(task, 5.0)
        if not task.done():
            task.cancel()
            # bounded: a daemon that ignores cancellation fails the leak check, not CI
            await asyncio.wait({task}, timeout=5.0)


@contextlib.asynccontextmanager
async def metering(
    tmp_path: Path, machine: SimulatedMachine, **overrides: Any
) -> AsyncIterator[tuple[Rig, Rs485Simulator]]:
    """The daemon in work mode with the metering motor already turning."""
    async with running(tmp_path, machine, control={"start_working": True}, **overrides) as rig:
        sim = rig.machine.rs485
        assert sim is not None
        await rig.until(lambda: sim.duty_pct["motor"] > 0, what="metering")
        yield rig, sim


@pytest.fixture
def make_machine() -> Callable[..., SimulatedMachine]:
    def make(**kw: Any) -> SimulatedMachine:
        kw.setdefault("drive", steady_drive())
        return SimulatedMachine(**kw)

    return make
