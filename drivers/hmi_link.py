"""The UART link to the TJC touchscreen: commands in, display instructions out.

The screen is a convenience, not a safety device: losing it must never stop seeding or crash the
daemon. So ``run()`` keeps (re)opening the port with capped backoff, swallows every I/O error
(logging it with the port name and counting it), and ``show()`` drops text instead of waiting
when the screen is gone -- the next periodic update repaints everything anyway.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import serial
import serial_asyncio_fast

from drivers.backoff import Backoff
from drivers.log_limit import RateLimitedLog
from protocol.hmi import (
    HmiDecoder,
    HmiEvent,
    Rejected,
    ScreenError,
    ScreenReply,
    set_text,
    set_value,
)

log = logging.getLogger(__name__)

READ_CHUNK = 256
# A real TJC sends a frame in one burst (8 bytes ≈ 8 ms at 9600 baud); bytes left over after
# this much silence are a truncated frame or noise and are reported rather than held forever.
IDLE_FLUSH_S = 0.25
# Unsent instructions allowed to queue while the screen does not read (e.g. its UART is hung
# while the port stays open). Beyond this, updates are dropped: stale text is worthless.
MAX_WRITE_BACKLOG = 4096
CLOSE_TIMEOUT_S = 2.0
LOG_EVERY_S = 10.0  # at most one warning per kind per this interval under a storm of errors


@dataclass
class HmiLinkStats:
    frames_ok: int = 0  # valid commands delivered
    rejected: int = 0  # garbage runs and invalid frames
    # the same, per kind (protocol.hmi KIND_*: garbage, bad_trailer, unknown_function, ...)
    rejected_by_reason: dict[str, int] = field(default_factory=dict)
    screen_errors: int = 0  # Nextion error replies to our instructions
    connects: int = 0  # successful port opens
    reconnects: int = 0  # attempts to reopen after a failure or a loss
    open_failures: int = 0
    disconnects: int = 0  # the open port failed or vanished
    writes: int = 0  # instructions written
    dropped_writes: int = 0  # instructions dropped (disconnected, backlog, timeout)
    callback_errors: int = 0  # on_event raised; logged and ignored


class HmiLink:
    """One TJC screen on one serial port (9600 8N1 by default).

    ``on_event`` is called from the read loop for every decoded command and every ``Rejected``
    (so the gateway can show why on the screen). Nextion error replies are counted and logged
    but not passed on: showing them on the screen could trigger the same error again.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 9600,
        encoding: str = "ascii",
        *,
        on_event: Callable[[HmiEvent], None],
        write_timeout_s: float = 0.5,
        reconnect_max_s: float = 5.0,
        idle_flush_s: float = IDLE_FLUSH_S,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        "".encode(encoding)  # an unknown codec should fail here, at start-up, not per update
        self.port = port
        self.baudrate = baudrate
        self.encoding = encoding
        self._on_event = on_event
        self._write_timeout_s = write_timeout_s
        self._idle_flush_s = idle_flush_s
        self._backoff = backoff or Backoff(initial_s=0.1, cap_s=reconnect_max_s)
        self._writer: asyncio.StreamWriter | None = None
        self._ever_connected = False
        self._log = RateLimitedLog(log, LOG_EVERY_S, clock=clock)
        self.stats = HmiLinkStats()
        self.last_screen_error: ScreenError | None = None

    @property
    def available(self) -> bool:
        """True while the port is open; says nothing about whether a screen is plugged in."""
        return self._writer is not None and not self._writer.is_closing()

    @property
    def write_backlog(self) -> int:
        """Bytes written to the port that the screen has not taken yet (0 while closed); above
        ``MAX_WRITE_BACKLOG`` further updates are dropped instead of queued."""
        writer = self._writer
        return 0 if writer is None else writer.transport.get_write_buffer_size()

    # -- reading ------------------------------------------------------------------------------

    async def run(self) -> None:
        """Read forever, reopening the port after any failure. Only cancellation ends it."""
        while True:
            try:
                reader, writer = await serial_asyncio_fast.open_serial_connection(
                    url=self.port,
                    baudrate=self.baudrate,
                    bytesize=serial.EIGHTBITS,
                    parity=serial.PARITY_NONE,
                    stopbits=serial.STOPBITS_ONE,
                    exclusive=True,
                )
            except (serial.SerialException, OSError, ValueError) as exc:
                self.stats.open_failures += 1
                self._log.warning("open", "HMI port %s cannot be opened: %s", self.port, exc)
            else:
                await self._serve(reader, writer)
            self.stats.reconnects += 1
            await asyncio.sleep(self._backoff.next_delay())

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.stats.connects += 1
        self._log.reset("open")
        log.info(
            "HMI port %s %s at %d baud",
            self.port,
            "reopened" if self._ever_connected else "opened",
            self.baudrate,
        )
        self._ever_connected = True
        self._writer = writer
        decoder = HmiDecoder()
        try:
            while True:
                try:
                    async with asyncio.timeout(self._idle_flush_s if decoder.pending else None):
                        data = await reader.read(READ_CHUNK)
                except TimeoutError:
                    self._dispatch(decoder.flush())
                    continue
                if not data:
                    raise ConnectionResetError("port closed")
                self._backoff.reset()  # the link has proved itself
                self._dispatch(decoder.feed(data))
        except (serial.SerialException, OSError) as exc:
            self.stats.disconnects += 1
            self._log.warning("lost", "HMI port %s lost: %s", self.port, exc)
        finally:
            self._writer = None
            if not writer.is_closing():
                # abort, not close: unsent display text is worthless and must not hold the fd
                writer.transport.abort()
            with contextlib.suppress(Exception):
                # waits for the transport to close the fd (done in an executor thread)
                await asyncio.wait_for(writer.wait_closed(), CLOSE_TIMEOUT_S)

    def _dispatch(self, events: list[HmiEvent]) -> None:
        for event in events:
            if isinstance(event, ScreenError):
                self.stats.screen_errors += 1
                self.last_screen_error = event
                self._log.warning(
                    "screen", "HMI on %s reports %s (0x%02X)", self.port, event.meaning, event.code
                )
                continue
            if isinstance(event, ScreenReply):
                log.debug("HMI on %s replied 0x%02X %s", self.port, event.code, event.data.hex())
                continue
            if isinstance(event, Rejected):
                self.stats.rejected += 1
                by_reason = self.stats.rejected_by_reason
                by_reason[event.kind] = by_reason.get(event.kind, 0) + 1
                self._log.warning(
                    f"rejected:{event.kind}",
                    "HMI on %s sent bad input: %s (%s)",
                    self.port,
                    event.reason,
                    event.raw[:32].hex(" "),
                )
            else:
                self.stats.frames_ok += 1
                log.info("HMI on %s: %s", self.port, event)
            try:
                self._on_event(event)
            except Exception:
                self.stats.callback_errors += 1
                log.exception("HMI event handler failed on %r", event)

    # -- writing ------------------------------------------------------------------------------

    async def show(self, obj: str, text: str) -> bool:
        """Set a text object; False if the update was dropped (the screen is unavailable)."""
        return await self._write(set_text(obj, text, self.encoding), 1)

    async def show_many(self, texts: Mapping[str, str]) -> bool:
        """Set several text objects in one write, so a page repaints together."""
        if not texts:
            return True
        payload = b"".join(set_text(obj, text, self.encoding) for obj, text in texts.items())
        return await self._write(payload, len(texts))

    async def set_number(self, obj: str, value: int) -> bool:
        """Set a number object (``obj.val``)."""
        return await self._write(set_value(obj, value), 1)

    async def _write(self, payload: bytes, count: int) -> bool:
        writer = self._writer
        if writer is None or writer.is_closing():
            return self._drop(count, "port not open")
        if self.write_backlog > MAX_WRITE_BACKLOG:
            return self._drop(count, "screen is not reading")
        writer.write(payload)
        self.stats.writes += count
        try:
            await asyncio.wait_for(writer.drain(), self._write_timeout_s)
        except TimeoutError:
            log.debug(
                "HMI port %s: write still pending after %.1f s", self.port, self._write_timeout_s
            )
        except (serial.SerialException, OSError, RuntimeError) as exc:
            # The read loop sees the same failure and reconnects.
            log.debug("HMI port %s: write failed: %s", self.port, exc)
            return False
        return True

    def _drop(self, count: int, why: str) -> bool:
        self.stats.dropped_writes += count
        log.debug("HMI port %s: update dropped, %s", self.port, why)
        return False
