"""systemd notification protocol, spoken directly: READY, WATCHDOG, STATUS, STOPPING.

It is one datagram per message to ``$NOTIFY_SOCKET``, so no library is worth a dependency.
Outside systemd (no ``NOTIFY_SOCKET``) everything is a no-op, so the daemon runs the same in
a terminal, in docker and under ``Type=notify``.

The watchdog is the point: systemd restarts the service when pings stop, and pings must stop
when the *control loop* stalls, not merely when the process dies. So the control loop
``kick()``s the ``Watchdog`` every tick, and the ping task only pings if a kick happened within
the last ping interval.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

STATUS_MAX_CHARS = 200  # STATUS= is shown by `systemctl status`; keep it one line


def _socket_address(value: str) -> str | bytes:
    """A leading ``@`` names a Linux abstract socket (NUL byte first on the wire)."""
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    return value


class Notifier:
    """Sends sd_notify datagrams; never raises (a dead supervisor must not kill the daemon)."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        raw = env.get("NOTIFY_SOCKET", "")
        self._address: str | bytes | None = _socket_address(raw) if raw else None
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def send(self, *fields: str) -> bool:
        if self._address is None:
            return False
        message = "\n".join(fields).encode()
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(message, self._address)
        except OSError as exc:
            log.warning("sd_notify to %r failed: %s", self._address, exc)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.send("READY=1", *([_status(status)] if status else []))

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.send(_status(text))

    def stopping(self) -> bool:
        return self.send("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _status(text: str) -> str:
    return "STATUS=" + " ".join(text.split())[:STATUS_MAX_CHARS]


def watchdog_interval(environ: Mapping[str, str] | None = None) -> float | None:
    """Seconds between pings: half of ``WATCHDOG_USEC``, or None when no watchdog is set.

    ``WATCHDOG_PID``, when present, must be our pid (systemd sets it so children that inherit
    the environment do not ping for the parent).
    """
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and pid.strip() != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("ignoring WATCHDOG_USEC=%r (not an integer)", usec)
        return None
    return value / 2e6 if value > 0 else None


class Watchdog:
    """Pings systemd only while the control loop keeps kicking."""

    def __init__(
        self,
        notifier: Notifier,
        interval_s: float | None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.notifier = notifier
        self.interval_s = interval_s
        self._clock = clock
        self._last_kick: float | None = None
        self.pings = 0
        self.skipped = 0

    @classmethod
    def from_environment(cls, notifier: Notifier) -> Watchdog:
        return cls(notifier, watchdog_interval())

    def kick(self) -> None:
        """Call from every control-loop tick: cheap, never blocks."""
        self._last_kick = self._clock()

    def loop_alive(self) -> bool:
        if self._last_kick is None or self.interval_s is None:
            return False
        return self._clock() - self._last_kick <= self.interval_s

    def ping_if_alive(self) -> bool:
        if self.loop_alive() and self.notifier.watchdog():
            self.pings += 1
            return True
        self.skipped += 1
        return False

    async def run(self) -> None:
        """Ping every interval while the loop is alive; returns at once with no watchdog."""
        if self.interval_s is None or not self.notifier.enabled:
            return
        while True:
            await asyncio.sleep(self.interval_s)
            if not self.ping_if_alive():
                log.error("control loop has not ticked for %.1f s: withholding watchdog ping",
                          self.interval_s)
