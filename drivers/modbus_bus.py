"""The one RS485 Modbus-RTU bus: a pymodbus async master, one request at a time, with every
failure turned into a named, counted, rate-limited DriverError instead of a crash.

Why the extra layer over ``AsyncModbusSerialClient``:

* RS485 is half duplex with one master: two overlapping requests corrupt each other, so an
  ``asyncio.Lock`` serialises every request of every device on the bus.
* pymodbus reports a CRC error, line noise and a silent device all the same way (the framer
  drops a bad frame silently, the request then times out with ``ModbusIOException``). A
  ``trace_packet`` hook notes whether any byte came back during the request, which is enough
  to tell "nothing answered" (timeout) from "something answered but garbled" (CRC / noise);
  an operator needs that difference to choose between a dead sensor and a bad cable.
* pymodbus's own reconnect loop is turned off (``reconnect_delay=0``) and replaced by one
  driven by :class:`drivers.backoff.Backoff` capped at ``reconnect_max_s``, so all sowgate
  drivers retry the same way; while the port is down requests fail fast instead of each
  waiting for a timeout, which keeps the control loop's timing intact.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from pymodbus.client import AsyncModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType

from drivers.backoff import Backoff
from drivers.errors import DeviceRejected, DeviceUnavailable, DriverError
from drivers.tasks import StartClose, cancel_and_wait

log = logging.getLogger(__name__)

LOG_EVERY_S = 30.0  # a device that keeps failing is reported at most this often
RX_SNIPPET_MAX = 32  # bytes of a garbled reply kept for the log message
MAX_READ_COUNT = 125  # Modbus limit for function 3
RECONNECT_INITIAL_S = 0.05
# Backstops against a pymodbus call that never returns (seen once when a pty vanished in the
# middle of a reconnect): no await under the bus lock may outlive these.
CONNECT_TIMEOUT_S = 3.0
REQUEST_GRACE_S = 1.0
CLOSE_TIMEOUT_S = 3.0

_EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "device failure",
    5: "acknowledge",
    6: "device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target failed to respond",
}

# pymodbus logs every timeout / failed connect at WARNING/ERROR itself; this driver reports
# the same events once, with the device name, rate-limited. Drop the duplicates.
_PYMODBUS_DUPLICATES = (
    "No response received",
    "Failed to connect",
    "Not connected, trying to connect",
    "Cancel send, because not connected",
    # its own marker for a message it just logged again (dropped above): noise under load
    "Repeating....",
)


class _DropPymodbusDuplicates(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        return not any(text in msg for text in _PYMODBUS_DUPLICATES)


def _install_pymodbus_log_filter() -> None:
    pm_log = logging.getLogger("pymodbus.logging")
    if not any(isinstance(f, _DropPymodbusDuplicates) for f in pm_log.filters):
        pm_log.addFilter(_DropPymodbusDuplicates())


@dataclass
class DeviceStats:
    """Counters for one named device; ``available`` is "the last request succeeded"."""

    name: str
    device_id: int
    ok: int = 0
    timeouts: int = 0  # nothing came back
    garbled: int = 0  # bytes came back but no valid frame: CRC error or line noise
    exceptions: int = 0  # the device answered with a Modbus exception
    port_errors: int = 0  # the serial port was missing or vanished
    consecutive_failures: int = 0
    available: bool = False
    last_error: str | None = None
    last_ok_monotonic: float | None = None
    _last_logged: float = field(default=-1e18, repr=False)
    _last_kind: str | None = field(default=None, repr=False)
    _streak_logged: bool = field(default=False, repr=False)

    @property
    def failures(self) -> int:
        return self.timeouts + self.garbled + self.exceptions + self.port_errors


class ModbusBus(StartClose):
    """The RS485 master shared by the radar, inclinometer and PWM module."""

    def __init__(
        self,
        port: str,
        baudrate: int = 9600,
        parity: str = "N",
        stopbits: int = 1,
        timeout_s: float = 0.3,
        retries: int = 0,
        reconnect_max_s: float = 5.0,
        *,
        name: str = "rs485",
        log_every_s: float = LOG_EVERY_S,
    ) -> None:
        if parity not in ("N", "E", "O"):
            raise ValueError(f"parity must be N, E or O (got {parity!r})")
        if stopbits not in (1, 2):
            raise ValueError(f"stopbits must be 1 or 2 (got {stopbits})")
        if timeout_s <= 0 or reconnect_max_s <= 0 or retries < 0:
            raise ValueError("timeout_s and reconnect_max_s must be > 0, retries >= 0")
        self.port = port
        self.name = name
        self.timeout_s = timeout_s
        self.retries = retries
        self.reconnect_max_s = reconnect_max_s
        self.log_every_s = log_every_s
        self._client_args: dict[str, Any] = {
            "framer": FramerType.RTU,
            "baudrate": baudrate,
            "parity": parity,
            "stopbits": stopbits,
            "timeout": timeout_s,
            "retries": retries,
            "reconnect_delay": 0,  # reconnects are ours (Backoff), not pymodbus's
            "name": name,
        }
        self._client: AsyncModbusSerialClient | None = None
        self._lock = asyncio.Lock()
        self._stats: dict[str, DeviceStats] = {}
        self._reconnect_task: asyncio.Task[None] | None = None
        self._backoff = Backoff(
            initial_s=min(RECONNECT_INITIAL_S, reconnect_max_s), cap_s=reconnect_max_s
        )
        self._connected_event = asyncio.Event()
        self._closing = False
        self._started = False
        self._rx_bytes = bytearray()
        self._port_error: str = "not opened yet"
        self._port_down_logged_at = -1e18
        self.reconnects = 0  # successful re-opens after a loss
        _install_pymodbus_log_filter()

    @classmethod
    def from_config(cls, section: Any, *, log_every_s: float = LOG_EVERY_S) -> ModbusBus:
        """Build from ``gateway.config.Rs485Section`` (duck-typed to keep drivers below
        gateway in the layer order)."""
        return cls(
            section.port,
            baudrate=section.baudrate,
            parity=section.parity,
            stopbits=section.stopbits,
            timeout_s=section.timeout_s,
            retries=section.retries,
            reconnect_max_s=section.reconnect_max_s,
            log_every_s=log_every_s,
        )

    # -------------------------------------------------------------------------------------
    # lifecycle

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.connected

    @property
    def port_error(self) -> str | None:
        """Why the port is down (``"/dev/x does not exist"``), None while it is open."""
        return None if self.connected else self._port_error

    async def start(self) -> None:
        """Open the port. A missing port is not an error here: the bus keeps trying in the
        background and requests fail with DeviceUnavailable until it appears."""
        if self._started:
            return
        self._started = True
        self._closing = False
        if not await self._open():
            self._port_went_down(self._port_error)

    async def close(self) -> None:
        """Stop reconnecting and close the port. Idempotent."""
        self._closing = True
        task, self._reconnect_task = self._reconnect_task, None
        try:
            async with asyncio.timeout(CLOSE_TIMEOUT_S):
                await cancel_and_wait(task)
                await self._lock.acquire()
                self._lock.release()
        except TimeoutError:
            log.error("RS485 port %s: a request or reconnect hung; closing regardless", self.port)
        if self._client is not None:
            self._client.close()
            self._client = None
        self._connected_event.clear()
        self._started = False
        self._port_error = "bus closed"

    async def wait_connected(self, timeout_s: float) -> bool:
        """True once the port is open (for start-up sequencing and tests)."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._connected_event.wait(), timeout_s)
        return self.connected

    # -------------------------------------------------------------------------------------
    # statistics

    @property
    def stats(self) -> dict[str, DeviceStats]:
        """Per-device counters, keyed by device name."""
        return self._stats

    def device_stats(self, device: str) -> DeviceStats:
        try:
            return self._stats[device]
        except KeyError:
            raise KeyError(f"no request has been made to a device named {device!r}") from None

    def available(self, device: str) -> bool:
        stats = self._stats.get(device)
        return bool(stats and stats.available)

    # -------------------------------------------------------------------------------------
    # requests

    async def read_holding(
        self, device: str, device_id: int, address: int, count: int
    ) -> list[int]:
        """Read ``count`` holding registers (function 3) from ``device``."""
        _check_target(device, device_id, address)
        if not 1 <= count <= MAX_READ_COUNT:
            raise ValueError(f"{device}: count must be 1..{MAX_READ_COUNT} (got {count})")
        what = f"read {count} register(s) at {address}"

        def call(client: AsyncModbusSerialClient) -> Awaitable[Any]:
            return client.read_holding_registers(address, count=count, device_id=device_id)

        response = await self._request(device, device_id, what, call)
        registers = list(response.registers)
        if len(registers) != count:
            error = DeviceRejected(
                f"{device} (id {device_id}) answered {len(registers)} register(s) "
                f"to a {what} request"
            )
            self._failed(self._stats_for(device, device_id), "exceptions", error)
            raise error
        return registers

    async def write_register(
        self, device: str, device_id: int, address: int, value: int
    ) -> None:
        """Write one holding register (function 6) on ``device``."""
        _check_target(device, device_id, address)
        if not 0 <= value <= 0xFFFF:
            raise ValueError(f"{device}: register value must be 0..65535 (got {value})")
        what = f"write {value} to register {address}"

        def call(client: AsyncModbusSerialClient) -> Awaitable[Any]:
            return client.write_register(address, value, device_id=device_id)

        await self._request(device, device_id, what, call)

    async def _request(
        self,
        device: str,
        device_id: int,
        what: str,
        call: Callable[[AsyncModbusSerialClient], Awaitable[Any]],
    ) -> Any:
        stats = self._stats_for(device, device_id)
        label = f"{device} (id {device_id})"
        async with self._lock:
            client = self._client
            if client is None or not client.connected:
                error: DriverError = DeviceUnavailable(
                    f"{label}: cannot {what}: RS485 port {self.port} is down "
                    f"({self._port_error})"
                )
                # counted, not logged per device: the port's own line says it once, with
                # what is retried (a line per device and register said "reconnecting" 4 times)
                self._failed(stats, "port_errors", error, log_it=False)
                if self._started and not self._closing:
                    self._ensure_reconnecting()
                raise error
            self._rx_bytes.clear()
            try:
                response = await self._finish_even_if_cancelled(call(client))
            except TimeoutError as exc:
                error = DeviceUnavailable(f"{label}: {what} hung in the Modbus client; reset")
                self._failed(stats, "timeouts", error)
                client.close()
                if self._client is client:
                    self._client = None
                self._port_went_down("Modbus client hung")
                raise error from exc
            except (ModbusIOException, ConnectionException, OSError) as exc:
                if not client.connected:
                    kind = "port_errors"
                    error = DeviceUnavailable(
                        f"{label}: {what} failed, RS485 port {self.port} vanished ({exc})"
                    )
                elif self._rx_bytes:
                    kind = "garbled"
                    error = DeviceUnavailable(
                        f"{label}: garbled reply to {what} (CRC error or line noise): "
                        f"{bytes(self._rx_bytes[:RX_SNIPPET_MAX]).hex(' ')}"
                    )
                else:
                    kind = "timeouts"
                    error = DeviceUnavailable(
                        f"{label}: no reply to {what} within {self.timeout_s:g} s "
                        f"({self.retries} retries)"
                    )
                self._failed(stats, kind, error)
                raise error from exc
            except ModbusException as exc:  # anything else pymodbus may raise
                error = DeviceUnavailable(f"{label}: {what} failed: {exc}")
                self._failed(stats, "garbled", error)
                raise error from exc
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            error = DeviceRejected(
                f"{label} rejected {what}: Modbus exception {code} "
                f"({_EXCEPTION_NAMES.get(code, 'unknown')})"
            )
            self._failed(stats, "exceptions", error)
            raise error
        self._succeeded(stats)
        return response

    async def _finish_even_if_cancelled(self, request: Awaitable[Any]) -> Any:
        """Await ``request`` (already sent, or about to be) to its end, even if the caller is
        cancelled meanwhile; then re-raise the cancellation.

        Why: a request cancelled between sending and the reply leaves that reply on its way.
        The next request (the daemon's final motor/fan-to-0 write after a stop cancelled a
        poll) then met it: pymodbus logged "request ask for id=3 but got id=1, Skipping" or
        "received pdu without a corresponding request". Waiting out the request, bounded by
        the Modbus timeout, keeps the bus lock until the line is quiet again; the caller
        still ends as cancelled (and acts on nothing it read).
        """
        bound_s = self.timeout_s * (self.retries + 1) + REQUEST_GRACE_S

        async def bounded() -> Any:
            async with asyncio.timeout(bound_s):
                return await request

        inner = asyncio.ensure_future(bounded())
        try:
            return await asyncio.shield(inner)
        except asyncio.CancelledError:
            if inner.done():
                raise
            # drivers.tasks.cancel_all cancels again every 0.5 s: keep waiting, the request
            # ends by itself within bound_s
            while not inner.done():
                with contextlib.suppress(asyncio.CancelledError):
                    await asyncio.wait({inner})
            if not inner.cancelled():
                inner.exception()  # retrieved: the caller is cancelled, not failed
            raise

    def _stats_for(self, device: str, device_id: int) -> DeviceStats:
        stats = self._stats.get(device)
        if stats is None:
            stats = self._stats[device] = DeviceStats(device, device_id)
        stats.device_id = device_id
        return stats

    def _succeeded(self, stats: DeviceStats) -> None:
        if stats._streak_logged:
            log.info(
                "%s (id %d) answering again after %d failed request(s)",
                stats.name, stats.device_id, stats.consecutive_failures,
            )
        stats.ok += 1
        stats.available = True
        stats.consecutive_failures = 0
        stats.last_ok_monotonic = time.monotonic()
        stats._streak_logged = False

    def _failed(
        self, stats: DeviceStats, kind: str, error: DriverError, *, log_it: bool = True
    ) -> None:
        """Count the failure; log it unless the same kind was logged for this device less
        than ``log_every_s`` ago (a dead or flapping device must not flood the journal)."""
        setattr(stats, kind, getattr(stats, kind) + 1)
        stats.available = False
        stats.consecutive_failures += 1
        stats.last_error = str(error)
        now = time.monotonic()
        if not log_it:
            log.debug("%s", error)
        elif kind != stats._last_kind or now - stats._last_logged >= self.log_every_s:
            suffix = (
                f" ({stats.consecutive_failures} consecutive failures)"
                if stats.consecutive_failures > 1
                else ""
            )
            log.warning("%s%s", error, suffix)
            stats._last_logged = now
            stats._last_kind = kind
            stats._streak_logged = True

    # -------------------------------------------------------------------------------------
    # port management

    def _make_client(self) -> AsyncModbusSerialClient:
        return AsyncModbusSerialClient(
            self.port,
            **self._client_args,
            trace_packet=self._trace_packet,
            trace_connect=self._trace_connect,
        )

    async def _open(self) -> bool:
        """One attempt to open the port; True on success."""
        if self._client is None:
            self._client = self._make_client()
        try:
            async with asyncio.timeout(CONNECT_TIMEOUT_S):
                ok = bool(await self._client.connect())
        except (OSError, ModbusException, TimeoutError):
            ok = False
        if ok:
            self._connected_event.set()
            self._backoff.reset()
            return True
        self._client.close()
        self._client = None
        self._port_error = _open_failure_reason(self.port)
        return False

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending and data:  # pymodbus passes its whole receive buffer so far
            self._rx_bytes[:] = data[:RX_SNIPPET_MAX]
        return data

    def _trace_connect(self, connected: bool) -> None:
        if connected:
            self._connected_event.set()
            return
        self._connected_event.clear()
        if self._closing:
            return
        self._port_went_down("port closed or vanished (I/O error)")

    def _port_went_down(self, reason: str) -> None:
        self._port_error = reason
        self._connected_event.clear()
        now = time.monotonic()
        if now - self._port_down_logged_at >= self.log_every_s:
            log.warning(
                "RS485 port %s is down (%s): sowgate retries opening it (every %g s at most); "
                "until it opens, the devices on it do not answer",
                self.port, reason, self._backoff.cap_s,
            )
            self._port_down_logged_at = now
        self._ensure_reconnecting()

    def _ensure_reconnecting(self) -> None:
        if self._closing or (self._reconnect_task and not self._reconnect_task.done()):
            return
        self._reconnect_task = asyncio.get_running_loop().create_task(
            self._reconnect_loop(), name=f"{self.name}-reconnect"
        )

    async def _reconnect_loop(self) -> None:
        while not self._closing:
            await asyncio.sleep(self._backoff.next_delay())
            async with self._lock:
                if self._closing:
                    return
                if self._client is not None and self._client.connected:
                    return
                if self._client is not None:  # a dead client from before the loss
                    self._client.close()
                    self._client = None
                if await self._open():
                    self.reconnects += 1
                    log.info("RS485 port %s is open again", self.port)
                    self._port_down_logged_at = -1e18
                    return


def _open_failure_reason(port: str) -> str:
    """Why an open failed, as far as can be told cheaply (pymodbus swallows the OSError)."""
    if not os.path.exists(port):  # also false for a symlink to a vanished pty
        return f"{port} does not exist"
    return f"cannot open {port} (busy, or no permission)"


def _check_target(device: str, device_id: int, address: int) -> None:
    if not device:
        raise ValueError("device name must not be empty (it names the device in errors)")
    if not 1 <= device_id <= 247:
        raise ValueError(f"{device}: device_id must be 1..247 (got {device_id})")
    if not 0 <= address <= 0xFFFF:
        raise ValueError(f"{device}: address must be 0..65535 (got {address})")
