"""AgOpenGPS over UDP: AgIO's broadcast in (port 8888), replies and screen texts out (9999).

What this endpoint obeys (docs/agopengps.md, "What the source trusts"):

* one sender only: the configured ``agio`` host, or else the first host whose well-formed,
  correctly summed frame comes from AgIO (``src`` 0x7F). Another host is adopted only after
  the trusted one has been silent for ``stale_after_s`` (AgIO restarted with a new address);
  frames from every other host are dropped ("untrusted sender"), hellos included, so a
  stranger can neither move the machine nor make it send;
* only frames with the ``80 81`` header, a length that matches and a right checksum;
* at most ``max_frames_per_s`` frames a second from the trusted host (a token bucket): a
  flood beyond it is dropped ("over rate") before it is decoded or handed on;
* values the codec refuses (a speed above 100 km/h, a lift state that does not exist) are
  dropped ("out of range"); the controller then applies ``speed.max_plausible_kmh``.

Every dropped frame is counted by reason (``rejected``) and logged rate-limited. The clock
is injected so tests step time.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter
from collections.abc import Callable
from typing import cast

from drivers.log_limit import RateLimitedLog
from protocol import agopengps as aog
from protocol.errors import ChecksumError, FieldError, ProtocolError

log = logging.getLogger(__name__)

AGIO_PORT = 9999
REASONS = ("untrusted_sender", "not_from_agio", "bad_frame", "bad_checksum", "out_of_range",
           "over_rate")


class AgOpenGpsEndpoint(asyncio.DatagramProtocol):
    """Receives AgIO's frames, hands the trusted ones on, answers the hello, sends texts."""

    def __init__(
        self,
        on_message: Callable[[aog.Message, float], None],
        *,
        agio: tuple[str, int] | None = None,
        stale_after_s: float = 4.0,
        max_frames_per_s: float = 100.0,
        hello_sections: Callable[[], tuple[bool, ...]] = tuple,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._on_message = on_message
        self._configured = agio
        self.trusted_host: str | None = agio[0] if agio else None
        self.stale_after_s = stale_after_s
        self._rate = max_frames_per_s
        self._tokens = max_frames_per_s
        self._tokens_t: float | None = None
        self._hello_sections = hello_sections
        self._clock = clock
        self._last_trusted_t: float | None = None
        self.transport: asyncio.DatagramTransport | None = None
        self.accepted = 0
        self.hellos_answered = 0
        self.texts_sent = 0
        self.rejected: Counter[str] = Counter()
        self._log = RateLimitedLog(log, clock=clock)

    # ---- lifecycle ------------------------------------------------------------------------
    async def open(self, host: str, port: int) -> None:
        loop = asyncio.get_running_loop()
        # no SO_REUSEPORT: a second process on the port would silently take half the frames
        await loop.create_datagram_endpoint(
            lambda: self, local_addr=(host, port), allow_broadcast=True
        )

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    @property
    def local_port(self) -> int | None:
        if self.transport is None:
            return None
        return int(self.transport.get_extra_info("sockname")[1])

    @property
    def agio_address(self) -> tuple[str, int] | None:
        """Where replies and texts go: the configured ``agio``, else the trusted host, 9999."""
        if self._configured is not None:
            return self._configured
        return None if self.trusted_host is None else (self.trusted_host, AGIO_PORT)

    # ---- in ------------------------------------------------------------------------------
    def _reject(self, reason: str, host: str, detail: str) -> None:
        self.rejected[reason] += 1
        self._log.warning(f"aog.{reason}", "AgOpenGPS frame from %s ignored (%s): %s",
                          host, reason.replace("_", " "), detail)

    def _trust(self, host: str, now: float) -> bool:
        if host == self.trusted_host:
            return True
        if self._configured is not None:
            return False
        silent = self._last_trusted_t is None or now - self._last_trusted_t > self.stale_after_s
        return silent  # adopt a new AgIO only when the trusted one has gone quiet

    def _within_rate(self, now: float) -> bool:
        if self._tokens_t is not None:
            self._tokens = min(self._rate, self._tokens + (now - self._tokens_t) * self._rate)
        self._tokens_t = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True

    def datagram_received(self, data: bytes, addr: tuple[str | object, ...]) -> None:
        host = str(addr[0])
        now = self._clock()
        if not self._trust(host, now):
            self._reject("untrusted_sender", host, f"AgIO is {self.trusted_host}")
            return
        if not self._within_rate(now):
            self._reject("over_rate", host, f"more than {self._rate:g} frames/s")
            return
        try:
            frame = aog.decode_frame(data)
            msg = aog.decode(data)
        except ChecksumError as exc:
            self._reject("bad_checksum", host, str(exc))
            return
        except FieldError as exc:
            self._reject("out_of_range", host, str(exc))
            return
        except ProtocolError as exc:
            self._reject("bad_frame", host, str(exc))
            return
        if frame.src != aog.AGIO_SOURCE:
            self._reject("not_from_agio", host, f"source 0x{frame.src:02X}, AgIO's is 0x7F")
            return
        if host != self.trusted_host:
            log.info("AgOpenGPS: obeying AgIO at %s", host)
            self.trusted_host = host
        self._last_trusted_t = now
        self.accepted += 1
        if isinstance(msg, aog.Hello):
            self._send(aog.hello_reply(self._hello_sections()))
            self.hellos_answered += 1
        self._on_message(msg, now)

    def error_received(self, exc: Exception) -> None:
        self._log.warning("aog.socket", "AgOpenGPS UDP error: %s", exc)

    # ---- out -----------------------------------------------------------------------------
    def _send(self, frame: bytes) -> bool:
        where = self.agio_address
        if self.transport is None or where is None:
            return False
        self.transport.sendto(frame, where)
        return True

    def send_text(self, text: str, seconds: int = 5) -> bool:
        """Show ``text`` on the AgOpenGPS screen (PGN 221); False if AgIO is not known yet."""
        sent = self._send(aog.display_text(text, seconds))
        self.texts_sent += sent
        return sent
