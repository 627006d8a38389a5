"""Pseudo-terminal pairs that stand in for serial cables in the simulator and the tests.

A pty is a real tty: the daemon opens ``device_path`` with pyserial exactly as it would open
``/dev/ttyUSB0``, so the tests exercise the same termios, framing and error paths as the cab.

Two details make ptys behave like a cable rather than like a terminal:

* raw mode on the device side, so nothing is echoed, translated or line-buffered;
* the device-side fd is held open here for the pair's whole life. Otherwise, whenever the
  daemon closes the port (e.g. to reconnect), reads on the master fail with EIO and a reader
  registered on it spins. Holding it open keeps the master quiet until the daemon returns.

``link_path`` gives the pair a stable name (a symlink to ``/dev/pts/N``). A simulator that
makes the port vanish and come back creates a fresh pair on the same ``link_path``, so the
daemon's config keeps pointing at the same file, as a udev symlink would on the real box.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from pathlib import Path
from types import TracebackType

from drivers.tasks import cancel_and_wait


class PtyPair:
    """One pty pair: ``master_fd`` for the simulator, ``device_path`` for the daemon."""

    def __init__(self, link_path: str | os.PathLike[str] | None = None) -> None:
        self._master_fd, self._slave_fd = os.openpty()
        try:
            tty.setraw(self._slave_fd)
            os.set_blocking(self._master_fd, False)
            self.slave_path = os.ttyname(self._slave_fd)
            self._link: Path | None = None
            if link_path is not None:
                link = Path(link_path)
                with contextlib.suppress(FileNotFoundError):
                    link.unlink()
                link.symlink_to(self.slave_path)
                self._link = link
        except BaseException:
            os.close(self._master_fd)
            os.close(self._slave_fd)
            raise
        self._closed = False

    @property
    def master_fd(self) -> int:
        """Non-blocking fd of the simulator's end."""
        if self._closed:
            raise OSError(f"pty pair for {self.device_path} is closed")
        return self._master_fd

    @property
    def device_path(self) -> str:
        """Path the daemon (or a pyserial peer) opens: the symlink if any, else /dev/pts/N."""
        return str(self._link) if self._link is not None else self.slave_path

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Close both ends (the peer then reads EIO, like an unplugged adapter) and remove the
        symlink if it still points at this pair. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._link is not None:
            with contextlib.suppress(OSError):
                if os.readlink(self._link) == self.slave_path:
                    self._link.unlink()
        for fd in (self._master_fd, self._slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> PtyPair:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"PtyPair({self.device_path!r} -> {self.slave_path!r}, {state})"


async def unplug(task: asyncio.Task[None] | None, pair: PtyPair | None) -> None:
    """Stop the task that plays a device on ``pair``, then close the pair: in that order, so
    the task never writes to a closed fd. Either may be None (never started)."""
    await cancel_and_wait(task)
    if pair is not None:
        pair.close()
