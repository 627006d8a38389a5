"""One serial port kept open: the open / read / reopen-with-backoff loop every UART driver needs.

The GNSS receiver, the seed-tube module and the touchscreen each hang on a UART that can
vanish at any time (USB adapter unplugged, connector shaken loose, receiver rebooting).
``SerialLine.run`` opens the port with pyserial-asyncio-fast and hands every chunk it reads
to the driver, stamped with its arrival time. When the port fails, reaches end of file or
(if asked) stays silent too long, the line closes it and opens it again after a capped,
jittered ``drivers.backoff.Backoff`` delay -- forever, until cancelled. The backoff starts
over once bytes arrive: a port that delivers data has proved itself.

The driver keeps what is its own: decoding, stamping, delivering. It hears about the line
through callbacks (all run in the event loop, and must not block):

* ``on_data(data, t_arrival)`` for every chunk read;
* ``on_open(writer)`` after each successful open (the writer is for drivers that also send);
* ``on_idle(now)`` when nothing arrived for ``idle_after_s`` (flush a half-read frame,
  emit what is complete); ``idle_after_s`` may be a callable, asked before each read, so a
  driver waits with a timeout only while it holds something to flush;
* ``on_close()`` after the port closed for any reason, a cancel included.

The connection's health is kept in one place, :class:`SerialLineStats` (open or not, how often
it opened, failed to open or was lost, and why it last failed), which each driver presents
under its own stats' names.

Cancel-safe: a cancel at any await closes the port (and calls ``on_close``) before it
propagates. With ``drain`` set, a cancel that comes while the line is reading first reads on
until the port is quiet (bounded), so bytes already sent are still handed to ``on_data``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from serial import SerialException
from serial_asyncio_fast import open_serial_connection

from drivers.backoff import Backoff

log = logging.getLogger(__name__)

# pyserial raises ValueError for a setting the port refuses (an unsupported baud rate): the
# line retries it like a missing port and says why in ``last_error``; it never crashes.
OPEN_ERRORS: Final = (SerialException, OSError, ValueError)
READ_ERRORS: Final = (SerialException, OSError)
CLOSE_TIMEOUT_S: Final = 2.0  # the transport closes the fd in an executor thread


@dataclass(frozen=True)
class Drain:
    """How long to read on after a cancel: until no byte came for ``quiet_s`` (bytes already
    sent may still sit in a USB adapter, whose latency timer is 16 ms by default), but never
    longer than ``timeout_s`` in all (a sender that keeps talking never goes quiet)."""

    quiet_s: float
    timeout_s: float


@dataclass
class SerialLineStats:
    connected: bool = False  # the port is open and being read
    connects: int = 0  # successful opens
    open_failures: int = 0  # opens that failed (port missing, busy, refused a setting)
    disconnects: int = 0  # an open port failed, reached end of file or went silent
    last_error: str | None = None  # why the port last failed or was lost (kept after reopening)

    @property
    def reconnects(self) -> int:
        """Times the port was opened again after its first open."""
        return max(0, self.connects - 1)


class SerialLine:
    """One serial port, read forever by ``run()`` and reopened after every failure.

    ``label`` names the device in log messages ("GNSS", "HMI"); ``logger`` is the driver's, so
    its messages stay under the driver's name.
    """

    def __init__(
        self,
        port: str,
        baudrate: int,
        *,
        on_data: Callable[[bytes, float], None],
        label: str,
        logger: logging.Logger = log,
        on_open: Callable[[asyncio.StreamWriter], None] | None = None,
        on_idle: Callable[[float], None] | None = None,
        on_close: Callable[[], None] | None = None,
        idle_after_s: float | Callable[[], float | None] | None = None,
        silence_reconnect_s: float | None = None,
        drain: Drain | None = None,
        read_chunk_bytes: int = 4096,
        exclusive: bool = False,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if silence_reconnect_s is not None and idle_after_s is None:
            idle_after_s = silence_reconnect_s  # silence is only noticed by a read timing out
        self.port = port
        self.baudrate = baudrate
        self.label = label
        self._on_data = on_data
        self._on_open = on_open
        self._on_idle = on_idle
        self._on_close = on_close
        self._idle_after_s = idle_after_s
        self._silence_reconnect_s = silence_reconnect_s
        self._drain = drain
        self._read_chunk_bytes = read_chunk_bytes
        # True: an advisory lock (flock), so a second program cannot use the same port; None
        # leaves pyserial's default (no lock, none taken away)
        self._exclusive: bool | None = True if exclusive else None
        self._backoff = backoff if backoff is not None else Backoff(initial_s=0.1, cap_s=5.0)
        self._clock = clock
        self._log = logger
        self._writer: asyncio.StreamWriter | None = None
        self.stats = SerialLineStats()

    @property
    def connected(self) -> bool:
        return self.stats.connected

    @property
    def writer(self) -> asyncio.StreamWriter | None:
        """The open port's writer, None while it is closed."""
        return self._writer

    async def run(self) -> None:
        """Open, read, reopen after any failure; only cancellation ends it."""
        while True:
            try:
                reader, writer = await open_serial_connection(
                    url=self.port, baudrate=self.baudrate, exclusive=self._exclusive
                )
            except OPEN_ERRORS as exc:
                self.stats.open_failures += 1
                self._failed(f"cannot open {self.port}: {exc}")
            else:
                await self._serve(reader, writer)
            await asyncio.sleep(self._backoff.next_delay())

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        guard_write_ready(writer.transport)
        stats = self.stats
        stats.connected = True
        stats.connects += 1
        self._writer = writer
        self._log.info(
            "%s port %s open at %d baud (connection %d)",
            self.label, self.port, self.baudrate, stats.connects,
        )
        try:
            if self._on_open is not None:
                self._on_open(writer)
            try:
                why = await self._read_until_lost(reader)
            except READ_ERRORS as exc:
                why = f"{self.port}: {exc}"
            stats.disconnects += 1
            self._failed(why)
        finally:
            stats.connected = False
            self._writer = None
            try:
                if self._on_close is not None:
                    self._on_close()
            finally:
                await _close(writer)

    async def _read_until_lost(self, reader: asyncio.StreamReader) -> str:
        """Read until the port is lost; returns why (a read error raises instead)."""
        chunk, clock, on_data = self._read_chunk_bytes, self._clock, self._on_data
        silence_s = self._silence_reconnect_s
        last_data = clock()
        while True:
            idle_after_s = self._idle_after_s
            if callable(idle_after_s):
                idle_after_s = idle_after_s()
            try:
                if idle_after_s is None:
                    data = await reader.read(chunk)
                else:
                    async with asyncio.timeout(idle_after_s):
                        data = await reader.read(chunk)
            except TimeoutError:
                now = clock()
                if self._on_idle is not None:
                    self._on_idle(now)
                if silence_s is not None and now - last_data > silence_s:
                    return f"{self.port}: no data for {silence_s:.1f} s"
                continue
            except asyncio.CancelledError:
                if self._drain is not None:
                    await self._read_what_was_sent(reader, self._drain)
                raise
            if not data:
                return f"{self.port}: port closed"
            last_data = clock()  # the arrival stamp of everything in this chunk
            self._backoff.reset()
            on_data(data, last_data)

    async def _read_what_was_sent(self, reader: asyncio.StreamReader, drain: Drain) -> None:
        """After a cancel: hand on what arrives until the port is quiet or the time is up."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + drain.timeout_s
        with contextlib.suppress(*READ_ERRORS):  # a dead port has no more to give
            while (left := deadline - loop.time()) > 0:
                try:
                    data = await asyncio.wait_for(
                        reader.read(self._read_chunk_bytes), min(drain.quiet_s, left)
                    )
                except TimeoutError:
                    return
                if not data:
                    return
                self._on_data(data, self._clock())

    def _failed(self, message: str) -> None:
        if message != self.stats.last_error:  # a port that stays away is reported once
            self._log.warning("%s: %s", self.label, message)
        self.stats.last_error = message


def guard_write_ready(transport: asyncio.BaseTransport) -> None:
    """Work around pyserial-asyncio-fast 0.16: after a partial write (the peer not reading,
    its pty buffer full) the transport registers a writer callback, and when that callback
    then writes the rest it never removes itself; the next time the fd is writable it asserts
    on the empty buffer ("Write buffer should not be empty"), logged by asyncio on every turn
    of the loop (a busy loop: 17 000 tracebacks in a minute on a loaded host). The guard
    removes the callback when there is nothing left to write, which is what the library's own
    ``_write_data`` means to do."""
    write_ready = getattr(transport, "_write_ready", None)
    remove_writer = getattr(transport, "_remove_writer", None)
    buffer = getattr(transport, "_write_buffer", None)
    if write_ready is None or remove_writer is None or not isinstance(buffer, list):
        return  # another transport (or a fixed library): nothing to guard

    def guarded() -> None:
        if not buffer:
            remove_writer()
            return
        write_ready()

    transport._write_ready = guarded  # type: ignore[attr-defined]


async def _close(writer: asyncio.StreamWriter) -> None:
    """Abort, not close: nothing is left worth sending on a lost port, and unsent bytes
    must not hold the fd open. Then wait (bounded) for the transport to release it."""
    if not writer.is_closing():
        writer.transport.abort()
    with contextlib.suppress(Exception):
        await asyncio.wait_for(writer.wait_closed(), CLOSE_TIMEOUT_S)
