"""Suite-wide guards (a test that leaks tasks, threads or file descriptors fails) and the
fixtures several folders share: the simulated RS485 bus and the plant behind it."""

from __future__ import annotations

import asyncio
import gc
import os
import threading
import time
from collections.abc import AsyncIterator, Iterator

import pytest
from hypothesis import HealthCheck, settings

from simulator.modbus_devices import Rs485Simulator
from tests.helpers import Plant

LEAK_GRACE_S = 2.0

# Property tests judge what the code does, not how fast: hypothesis's default 200 ms deadline
# per example (and its too-slow health check) failed them on a loaded machine as "flaky".
settings.register_profile(
    "suite", deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("suite")
# pytest-xdist distributions that keep a test file on one worker (make test: loadfile)
WHOLE_FILE_DISTRIBUTIONS = ("loadfile", "loadscope")


def pytest_configure(config: pytest.Config) -> None:
    """Parallel workers must get whole files: the fault matrix runs its campaign in a session
    fixture (split over workers, every worker ran all of it, four at once on two cores) and
    module fixtures (a daemon's sowing run) are shared by the tests of their file."""
    workers = getattr(config.option, "numprocesses", None)
    dist = getattr(config.option, "dist", "no")
    if workers and dist not in WHOLE_FILE_DISTRIBUTIONS:
        raise pytest.UsageError(
            f"-n {workers} needs --dist loadfile (got --dist {dist}): the fault matrix and "
            "module fixtures expect each test file on one worker"
        )


def _fd_targets() -> dict[int, str]:
    """Open sockets, ptys and serial devices of this process (fd -> target)."""
    out: dict[int, str] = {}
    for name in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{name}")
        except OSError:
            continue
        if target.startswith(("socket:", "/dev/pts/", "/dev/ptmx", "/dev/tty")):
            out[int(name)] = target
    return out


def _threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.is_alive()}


def _new_threads_and_fds(
    threads_before: set[threading.Thread], fds_before: dict[int, str]
) -> tuple[list[threading.Thread], dict[int, str]]:
    new_threads = list(_threads() - threads_before)
    fds_now = _fd_targets()
    return new_threads, {fd: t for fd, t in fds_now.items() if fds_before.get(fd) != t}


def _leak_problems(threads_before: set[threading.Thread], fds_before: dict[int, str]) -> list[str]:
    """Threads and fds the test left behind, after LEAK_GRACE_S for them to end. A full
    collection (sockets in reference cycles close when collected) runs only when something
    looks leaked: once the suite's heap is large ``gc.collect()`` takes 0.1-0.4 s, and run
    after each of ~2100 tests it was over a third of the suite's time. The verdict is the
    same: a collection closes fds and never opens one, and cannot end a thread."""
    deadline = time.monotonic() + LEAK_GRACE_S
    while True:
        new_threads, new_fds = _new_threads_and_fds(threads_before, fds_before)
        if not new_threads and not new_fds:
            break
        gc.collect()
        new_threads, new_fds = _new_threads_and_fds(threads_before, fds_before)
        if (not new_threads and not new_fds) or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    problems = []
    if new_threads:
        problems.append("threads: " + ", ".join(t.name for t in new_threads))
    if new_fds:
        problems.append("fds: " + ", ".join(f"{fd}->{t}" for fd, t in sorted(new_fds.items())))
    return problems


@pytest.fixture
async def _no_leaked_tasks() -> AsyncIterator[None]:
    """For async tests: checked inside the test's own loop, whose own fds are the baseline."""
    threads_before = _threads()
    fds_before = _fd_targets()
    yield
    me = asyncio.current_task()
    deadline = time.monotonic() + LEAK_GRACE_S
    while True:
        pending = [t for t in asyncio.all_tasks() if t is not me and not t.done()]
        if not pending or time.monotonic() > deadline:
            break
        await asyncio.sleep(0.05)
    if pending:
        names = ", ".join(sorted(t.get_name() for t in pending))
        for t in pending:
            t.cancel()
        pytest.fail(f"test leaked asyncio tasks: {names}")
    # executor threads (e.g. DNS look-ups) belong to the loop and end with it
    await asyncio.get_running_loop().shutdown_default_executor()
    problems = _leak_problems(threads_before, fds_before)
    if problems:
        pytest.fail("test leaked " + "; ".join(problems))


@pytest.fixture(autouse=True)
def _no_leaks(request: pytest.FixtureRequest) -> Iterator[None]:
    if request.node.get_closest_marker("asyncio") is not None:
        request.getfixturevalue("_no_leaked_tasks")
        yield
        return
    threads_before = _threads()
    fds_before = _fd_targets()
    yield
    problems = _leak_problems(threads_before, fds_before)
    if problems:
        pytest.fail("test leaked " + "; ".join(problems))


@pytest.fixture
def plant() -> Plant:
    """What the simulated RS485 devices report; a test file overrides it for its own values."""
    return Plant()


@pytest.fixture
async def sim(plant: Plant) -> AsyncIterator[Rs485Simulator]:
    """The simulated RS485 bus (radar, inclinometer, PWM module) on a pty, reporting ``plant``."""
    async with Rs485Simulator(
        radar_kmh=lambda: plant.kmh, tilt_deg=lambda: plant.tilt, on_duty=plant.on_duty
    ) as simulator:
        yield simulator
