"""sd_notify datagrams reach a real AF_UNIX socket; watchdog pings stop when the loop stalls."""

from __future__ import annotations

import asyncio
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.link.sdnotify import Notifier, Watchdog, watchdog_interval


@pytest.fixture
def path_socket(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify")
    sock.bind(path)
    sock.settimeout(2)
    yield path, sock
    sock.close()


@pytest.fixture
def abstract_socket() -> Iterator[tuple[str, socket.socket]]:
    name = f"sowgate-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(2)
    yield "@" + name, sock
    sock.close()


def test_ready_status_and_stopping_arrive_on_a_path_socket(
    path_socket: tuple[str, socket.socket],
) -> None:
    addr, sock = path_socket
    with Notifier({"NOTIFY_SOCKET": addr}) as n:
        assert n.ready("running\nfine")
        assert sock.recv(1024) == b"READY=1\nSTATUS=running fine"
        assert n.stopping()
        assert sock.recv(1024) == b"STOPPING=1"


def test_abstract_socket_names_start_with_at(abstract_socket: tuple[str, socket.socket]) -> None:
    addr, sock = abstract_socket
    with Notifier({"NOTIFY_SOCKET": addr}) as n:
        assert n.watchdog()
        assert sock.recv(1024) == b"WATCHDOG=1"


def test_without_notify_socket_everything_is_a_no_op() -> None:
    n = Notifier({})
    assert not n.enabled
    assert not n.ready()
    assert not n.watchdog()


def test_a_vanished_socket_is_logged_not_raised(tmp_path: Path) -> None:
    with Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone")}) as n:
        assert n.ready() is False


def test_watchdog_interval_is_half_of_watchdog_usec() -> None:
    assert watchdog_interval({"WATCHDOG_USEC": "10000000"}) == 5.0
    assert watchdog_interval({}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "junk"}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}) is None
    mine = {"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": str(os.getpid())}
    assert watchdog_interval(mine) == 2.0


def test_pings_only_while_the_control_loop_kicks(
    path_socket: tuple[str, socket.socket],
) -> None:
    """A stalled control loop must let systemd's watchdog fire: no kick, no ping."""
    addr, sock = path_socket
    now = [100.0]
    with Notifier({"NOTIFY_SOCKET": addr}) as n:
        wd = Watchdog(n, 1.0, clock=lambda: now[0])
        assert not wd.ping_if_alive()  # never kicked
        wd.kick()
        now[0] += 0.5
        assert wd.ping_if_alive()
        assert sock.recv(1024) == b"WATCHDOG=1"
        now[0] += 1.5  # loop stalled longer than the interval
        assert not wd.ping_if_alive()
        assert (wd.pings, wd.skipped) == (1, 2)


async def test_run_pings_periodically_and_stops_when_kicks_stop(
    path_socket: tuple[str, socket.socket],
) -> None:
    addr, sock = path_socket
    sock.setblocking(False)
    with Notifier({"NOTIFY_SOCKET": addr}) as n:
        wd = Watchdog(n, 0.05)
        task = asyncio.create_task(wd.run(), name="watchdog")
        try:
            for _ in range(10):
                wd.kick()
                await asyncio.sleep(0.02)
            pings_while_alive = wd.pings
            await asyncio.sleep(0.3)  # control loop "stalls"
            assert pings_while_alive >= 1
            assert wd.pings <= pings_while_alive + 1
            assert wd.skipped >= 2
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task


async def test_run_returns_at_once_without_a_watchdog() -> None:
    await asyncio.wait_for(Watchdog(Notifier({}), None).run(), 1)
