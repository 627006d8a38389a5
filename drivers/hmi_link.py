"""The UART link to the TJC touchscreen: commands in, display instructions out.

The screen is a convenience, not a safety device: losing it must never stop seeding or crash the
daemon. So ``run()`` keeps (re)opening the port with capped backoff, swallows every I/O error
(logging it with the port name and counting it), and ``show()`` drops text instead of waiting
when the screen is gone -- the next periodic update repaints everything anyway.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import serial

from drivers.backoff import Backoff
from drivers.log_limit import RateLimitedLog
from drivers.serial_line import SerialLine
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
        self._writer: asyncio.StreamWriter | None = None
        self._decoder = HmiDecoder()
        self._log = RateLimitedLog(log, LOG_EVERY_S, clock=clock)
        self._stats = HmiLinkStats()
        self.last_screen_error: ScreenError | None = None
        self._line = SerialLine(
            port,
            baudrate,
            label="HMI",
            logger=log,
            on_data=self._received,
            on_open=self._opened,
            on_idle=self._quiet,
            on_close=self._closed,
            idle_after_s=self._flush_after_s,
            read_chunk_bytes=READ_CHUNK,
            exclusive=True,
            backoff=backoff or Backoff(initial_s=0.1, cap_s=reconnect_max_s),
            clock=clock,
        )

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

    @property
    def stats(self) -> HmiLinkStats:
        # the connection's counters are the line's; shown here under the link's own names
        line, stats = self._line.stats, self._stats
        stats.connects, stats.open_failures = line.connects, line.open_failures
        stats.disconnects = line.disconnects
        stats.reconnects = line.open_failures + line.disconnects
        return stats

    # -- reading ------------------------------------------------------------------------------

    async def run(self) -> None:
        """Read forever, reopening the port after any failure. Only cancellation ends it."""
        await self._line.run()

    def _opened(self, writer: asyncio.StreamWriter) -> None:
        self._writer = writer
        self._decoder = HmiDecoder()  # a fresh connection starts a fresh frame

    def _closed(self) -> None:
        self._writer = None

    def _flush_after_s(self) -> float | None:
        """Wait with a timeout only while part of a frame is held."""
        return self._idle_flush_s if self._decoder.pending else None

    def _received(self, data: bytes, _t_arrival: float) -> None:
        self._dispatch(self._decoder.feed(data))

    def _quiet(self, _now: float) -> None:
        self._dispatch(self._decoder.flush())

    def _dispatch(self, events: list[HmiEvent]) -> None:
        for event in events:
            if isinstance(event, ScreenError):
                self._stats.screen_errors += 1
                self.last_screen_error = event
                self._log.warning(
                    "screen", "HMI on %s reports %s (0x%02X)", self.port, event.meaning, event.code
                )
                continue
            if isinstance(event, ScreenReply):
                log.debug("HMI on %s replied 0x%02X %s", self.port, event.code, event.data.hex())
                continue
            if isinstance(event, Rejected):
                self._stats.rejected += 1
                by_reason = self._stats.rejected_by_reason
                by_reason[event.kind] = by_reason.get(event.kind, 0) + 1
                self._log.warning(
                    f"rejected:{event.kind}",
                    "HMI on %s sent bad input: %s (%s)",
                    self.port,
                    event.reason,
                    event.raw[:32].hex(" "),
                )
            else:
                self._stats.frames_ok += 1
                log.info("HMI on %s: %s", self.port, event)
            try:
                self._on_event(event)
            except Exception:
                self._stats.callback_errors += 1
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
        self._stats.writes += count
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
        self._stats.dropped_writes += count
        log.debug("HMI port %s: update dropped, %s", self.port, why)
        return False
