"""Async access to a CAN bus with python-can, plus the two users sowgate has for it.

``CanBus`` owns one ``can.Bus`` and a ``can.Notifier`` bound to the running event loop. If the
bus fails (socketcan interface down, USB adapter unplugged) it is torn down and reopened with
the shared capped ``Backoff``, so a brown-out on the implement harness costs a few frames, not
the daemon. ``MeteringCanLink`` speaks the metering controllers' DBC; ``IsobusListener``
keeps the tractor's latest speed and hitch messages with the time each arrived (which of them
the machine acts on, and for how long, is ``gateway.metering.isobus``'s to decide).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import can

from drivers.backoff import Backoff
from drivers.errors import DeviceUnavailable, DriverError
from protocol import can_metering, isobus
from protocol.errors import ProtocolError

log = logging.getLogger(__name__)

RX_BUFFER_MAX = 1024  # frames held between the notifier and the consumer; oldest dropped
NOTIFIER_POLL_S = 0.1  # notifier thread wake-up; bounds how long close() blocks the loop

Clock = Callable[[], float]


class _BoundedReader(can.AsyncBufferedReader):
    """AsyncBufferedReader with a capped buffer and a wake-up on notifier errors."""

    def __init__(self, maxsize: int) -> None:
        super().__init__()
        self.buffer = asyncio.Queue(maxsize=maxsize)
        self.error: BaseException | None = None
        self.dropped = 0

    def on_message_received(self, msg: can.Message) -> None:
        if self._is_stopped:
            return
        if self.buffer.full():
            self.buffer.get_nowait()
            self.dropped += 1
        self.buffer.put_nowait(msg)

    def on_error(self, exc: Exception) -> None:
        self.error = exc
        # wake a consumer blocked in get(); the marker is recognised by identity
        if self.buffer.full():
            self.buffer.get_nowait()
        self.buffer.put_nowait(_ERROR_MARKER)


_ERROR_MARKER = can.Message(arbitration_id=0, is_error_frame=True)


class _QuietNotifier(can.Notifier):
    """Notifier whose reader thread ends quietly after a bus error.

    In loop mode python-can hands the error to the listeners (our reader wakes the consumer,
    which reconnects) and then re-raises it in the thread, which would only print a
    traceback from threading.excepthook.
    """

    def _rx_thread(self, bus: can.BusABC) -> None:
        try:
            super()._rx_thread(bus)
        except Exception as exc:  # already delivered to _BoundedReader.on_error
            log.debug("CAN notifier thread ended: %s", exc)


@dataclass
class BusStats:
    received: int = 0
    sent: int = 0
    reconnects: int = 0
    bad_frames: int = 0
    dropped: int = 0
    last_error: str | None = None


class CanBus:
    """One CAN interface, reopened with backoff when it fails. Use as ``async with``.

    ``open_interface`` opens the python-can interface (``can.Bus`` by default, called with
    ``interface=``, ``channel=`` and the ``bus_kwargs``); a test passes a wrapper to get hold of
    each interface opened and fail it the way an unplugged adapter does.
    """

    def __init__(
        self,
        interface: str,
        channel: str,
        bitrate: int | None = None,
        *,
        backoff: Backoff | None = None,
        rx_buffer: int = RX_BUFFER_MAX,
        bus_kwargs: dict[str, Any] | None = None,
        open_interface: Callable[..., can.BusABC] | None = None,
    ) -> None:
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self._backoff = backoff or Backoff(initial_s=0.1, cap_s=5.0)
        self._rx_buffer = rx_buffer
        self._bus_kwargs = bus_kwargs or {}
        self._open_interface = open_interface or can.Bus
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._reader: _BoundedReader | None = None
        self._lock = asyncio.Lock()
        self._closed = False
        self.stats = BusStats()

    @property
    def connected(self) -> bool:
        return self._bus is not None

    async def __aenter__(self) -> CanBus:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def _open_now(self) -> None:
        kwargs = dict(self._bus_kwargs)
        if self.bitrate is not None and self.interface != "virtual":
            kwargs["bitrate"] = self.bitrate
        try:
            bus = self._open_interface(interface=self.interface, channel=self.channel, **kwargs)
        except can.CanInterfaceNotImplementedError as exc:
            raise DriverError(
                f"CAN interface {self.interface!r} is not available on this system: {exc}"
            ) from exc
        reader = _BoundedReader(self._rx_buffer)
        try:
            notifier = _QuietNotifier(
                bus, [reader], timeout=NOTIFIER_POLL_S, loop=asyncio.get_running_loop()
            )
        except BaseException:
            bus.shutdown()
            raise
        self._bus, self._reader, self._notifier = bus, reader, notifier

    def _close_now(self) -> None:
        notifier, bus, reader = self._notifier, self._bus, self._reader
        self._notifier = self._bus = self._reader = None
        if reader is not None:
            reader.stop()
            self.stats.dropped += reader.dropped
        if notifier is not None:
            notifier.stop(timeout=NOTIFIER_POLL_S * 5)
        if bus is not None:
            with contextlib.suppress(can.CanError, OSError):
                bus.shutdown()

    async def open(self) -> None:
        """Open now; retries with backoff until it works (DriverError if it never can)."""
        self._closed = False
        await self._ensure_open()

    async def _ensure_open(self) -> None:
        async with self._lock:
            while self._bus is None:
                if self._closed:
                    raise DeviceUnavailable(f"CAN bus {self.channel} is closed")
                try:
                    self._open_now()
                except (can.CanError, OSError) as exc:
                    self.stats.last_error = str(exc)
                    delay = self._backoff.next_delay()
                    log.warning("CAN %s: cannot open (%s); retry in %.1fs", self.channel, exc,
                                delay)
                    await asyncio.sleep(delay)
                else:
                    self._backoff.reset()

    async def _reconnect(self, exc: BaseException) -> None:
        self.stats.last_error = str(exc)
        self.stats.reconnects += 1
        log.warning("CAN %s failed (%s); reopening", self.channel, exc)
        self._close_now()
        await asyncio.sleep(self._backoff.next_delay())
        await self._ensure_open()

    def close(self) -> None:
        """Stop the notifier thread and release the interface. Safe to call twice."""
        self._closed = True
        self._close_now()

    async def send(self, arbitration_id: int, data: bytes, *, extended: bool = False) -> None:
        """Send one frame; DeviceUnavailable if the bus is down (a reconnect is started)."""
        if self._bus is None:
            await self._ensure_open()
        bus = self._bus
        assert bus is not None
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=extended)
        try:
            bus.send(msg, timeout=0.05)
        except (can.CanError, OSError) as exc:
            if not self._closed:
                await self._reconnect(exc)
            raise DeviceUnavailable(f"CAN {self.channel}: send failed: {exc}") from exc
        self.stats.sent += 1

    async def recv(self, max_wait_s: float | None = None) -> can.Message | None:
        """Next received data frame, or None after ``max_wait_s``. Reconnects on bus errors."""
        loop = asyncio.get_running_loop()
        deadline = None if max_wait_s is None else loop.time() + max_wait_s
        while True:
            if self._bus is None:
                await self._ensure_open()
            reader = self._reader
            assert reader is not None
            remaining = None if deadline is None else deadline - loop.time()
            if remaining is not None and remaining <= 0:
                return None
            try:
                msg = await asyncio.wait_for(reader.get_message(), remaining)
            except TimeoutError:
                return None
            if msg is _ERROR_MARKER:
                await self._reconnect(reader.error or DriverError("notifier error"))
                continue
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            self.stats.received += 1
            return msg


@dataclass
class _NodeState:
    target_rpm: float = 0.0
    enable: bool = False
    sequence: int = 0
    status: can_metering.MeterStatus | None = None
    status_at: float | None = None


StatusCallback = Callable[[can_metering.MeterStatus, float], None]


class MeteringCanLink:
    """Sends each node's target speed at ``command_hz`` and tracks their status frames.

    ``node_ids`` come from the config, which refuses two channels on one node id; a repeated
    id here is just the one node.
    """

    def __init__(
        self,
        bus: CanBus,
        node_ids: Sequence[int],
        *,
        command_hz: float = 10.0,
        clock: Clock = time.monotonic,
    ) -> None:
        for node in node_ids:
            can_metering.command_id(node)  # FieldError for a node outside 1..15
        self.bus = bus
        self.command_period_s = 1.0 / command_hz
        self._clock = clock
        self._nodes = {n: _NodeState() for n in node_ids}

    @property
    def node_ids(self) -> list[int]:
        return list(self._nodes)

    def set_target(self, node_id: int, rpm: float, enable: bool = True) -> None:
        """Takes effect with the next command frame (at most one command period later)."""
        state = self._nodes[node_id]
        state.target_rpm = max(0.0, min(rpm, can_metering.SPEED_MAX_RPM))
        state.enable = enable and state.target_rpm > 0

    def stop_all(self) -> None:
        for node in self._nodes:
            self.set_target(node, 0.0, enable=False)

    def target(self, node_id: int) -> float:
        return self._nodes[node_id].target_rpm

    def status(self, node_id: int) -> tuple[can_metering.MeterStatus, float] | None:
        """Latest status and the local time it arrived, or None if none yet."""
        st = self._nodes[node_id]
        if st.status is None or st.status_at is None:
            return None
        return st.status, st.status_at

    async def send_commands(self) -> None:
        for node, st in self._nodes.items():
            frame_id, data = can_metering.encode_command(
                can_metering.SpeedCommand(node, st.target_rpm, st.enable, st.sequence)
            )
            st.sequence = (st.sequence + 1) % can_metering.SEQUENCE_MODULO
            await self.bus.send(frame_id, data)

    def feed(self, msg: can.Message) -> can_metering.MeterStatus | None:
        """Take one received frame; returns the decoded status if it is one of our nodes'."""
        if msg.is_extended_id:
            return None
        kind = can_metering.frame_kind(msg.arbitration_id)
        if kind is None or kind[0] != "status" or kind[1] not in self._nodes:
            return None
        try:
            status = can_metering.decode_status(msg.arbitration_id, bytes(msg.data))
        except ProtocolError as exc:
            self.bus.stats.bad_frames += 1
            log.debug("bad metering frame 0x%03X: %s", msg.arbitration_id, exc)
            return None
        st = self._nodes[status.node_id]
        st.status, st.status_at = status, self._clock()
        return status

    async def _tx_loop(self) -> None:
        loop = asyncio.get_running_loop()
        next_at = loop.time()
        while True:
            with contextlib.suppress(DeviceUnavailable):
                await self.send_commands()
            next_at += self.command_period_s
            delay = next_at - loop.time()
            if delay < 0:  # fell behind (bus reconnect): don't burst to catch up
                next_at, delay = loop.time(), 0.0
            await asyncio.sleep(delay)

    async def _rx_loop(self, on_status: StatusCallback | None) -> None:
        while True:
            msg = await self.bus.recv()
            if msg is None:
                continue
            status = self.feed(msg)
            if status is not None and on_status is not None:
                on_status(status, self._clock())

    async def run(self, on_status: StatusCallback | None = None) -> None:
        """Command and receive until cancelled; the bus must be open (``async with bus``)."""
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._tx_loop(), name="metering-can-tx")
            tg.create_task(self._rx_loop(on_status), name="metering-can-rx")


M = TypeVar("M")


@dataclass(frozen=True)
class Heard(Generic[M]):
    """A decoded ISOBUS message and the local monotonic time its frame arrived."""

    message: M
    at: float


@dataclass
class IsobusListener:
    """The tractor's latest ISOBUS speed message per PGN and rear hitch status, each with the
    time its frame arrived.

    Decoding only: which speed source the machine follows, how old a reading may be and when
    the hitch means "in work" are the machine's decisions (``gateway.metering.isobus``).
    """

    bus: CanBus | None = None
    clock: Clock = time.monotonic
    _speeds: dict[int, Heard[isobus.SpeedMessage]] = field(default_factory=dict)
    _hitch: Heard[isobus.HitchStatus] | None = None
    bad_frames: int = 0

    def feed(self, msg: can.Message, now: float | None = None) -> None:
        if not msg.is_extended_id:
            return
        t = self.clock() if now is None else now
        try:
            decoded = isobus.decode(msg.arbitration_id, bytes(msg.data))
        except ProtocolError as exc:
            self.bad_frames += 1
            log.debug("bad ISOBUS frame 0x%08X: %s", msg.arbitration_id, exc)
            return
        if isinstance(decoded, isobus.SpeedMessage):
            self._speeds[decoded.pgn] = Heard(decoded, t)
        elif isinstance(decoded, isobus.HitchStatus):
            self._hitch = Heard(decoded, t)

    def latest_speed(self, pgn: int) -> Heard[isobus.SpeedMessage] | None:
        """The latest speed message of ``pgn`` (``protocol.isobus.PGN_*_SPEED``), however old;
        None if none came yet."""
        return self._speeds.get(pgn)

    def latest_hitch(self) -> Heard[isobus.HitchStatus] | None:
        """The latest rear hitch status, however old; None if none came yet."""
        return self._hitch

    async def run(self) -> None:
        """Consume frames until cancelled; the bus must be open (``async with bus``)."""
        if self.bus is None:
            raise DriverError("IsobusListener.run needs a bus")
        while True:
            msg = await self.bus.recv()
            if msg is not None:
                self.feed(msg)
