"""Seed-tube sensors: one edge per seed per row, stamped on the host's monotonic clock.

One interface (:class:`SeedSensorSource`), two sources, chosen by ``seed_sensors.source``:

* ``serial`` — an edge-capture module on a UART sends ``D,<row>\\r\\n`` per seed
  (``protocol.seed_line``). The line carries no time, so each is stamped when its bytes reach
  us; all lines completed by one read share that read's stamp (they arrived together).
* ``gpio`` — one GPIO line per row through libgpiod v2 (``pip install sowgate[gpio]``),
  falling edges with the KERNEL's timestamp. The kernel stamps the interrupt, so the time is
  free of Python scheduling delay; libgpiod's default event clock is CLOCK_MONOTONIC, the
  clock ``time.monotonic()`` reads on Linux, so the stamp is directly comparable with GNSS
  arrival stamps. Debounce is done here on those raw stamps rather than by the kernel:
  kernel (software-emulated) debounce reports an edge only after the line has been stable
  for the debounce period and stamps it then, which would shift every seed by that period
  (2 ms is 7 mm at 12 km/h).

Both deliver :class:`SeedEdgeEvent` to ``on_edge`` inside the event loop and keep going on any
bad input; a vanished port (``drivers.serial_line``) or chip is retried with
``drivers.backoff.Backoff``.

Cancelling ``run`` is the daemon's graceful stop, and a seed the module has already reported
is a seed that fell: before honouring the cancel, both sources hand over what has already
arrived (serial: read on until the port is quiet, bounded by ``DRAIN_TIMEOUT_S``; gpio: the
events the kernel has queued), so the recorder's final flush, which runs after them, sees it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import select
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

from drivers.backoff import Backoff
from drivers.errors import DeviceUnavailable
from drivers.log_limit import RateLimitedLog
from drivers.serial_line import Drain, SerialLine
from drivers.ticks import next_tick
from protocol.seed_line import Rejected, SeedLineDecoder

log = logging.getLogger(__name__)

READ_CHUNK_BYTES = 1024
GPIO_CONSUMER = "sowgate-seed-sensors"
NS_PER_S = 1_000_000_000
# On a stop, the serial port is read on until no byte has come for DRAIN_QUIET_S (a line
# already sent may still be in the USB adapter, whose latency timer is 16 ms by default), but
# never longer than DRAIN_TIMEOUT_S: a planter still moving would never go quiet.
DRAIN_QUIET_S = 0.05
# The GPIO lines are read at most this often, on the shared tick grid (drivers.ticks). The
# kernel stamps every edge, so reading them in batches loses no timing, while waking per edge
# (up to 2 000 a second on a 48-row planter) would cost the daemon more CPU than everything it
# does with the seeds: on the bench machine each wake-up cost about 0.25 ms of CPU, and reading
# every 50 ms instead of every 10 ms took a quarter off the daemon's CPU at 2 100 seeds/s.
# Meanwhile the kernel queues the edges (GPIO_EVENT_BUFFER), and 50 ms is also well under the
# ~100 ms a seed takes to fall, so an edge still reaches the positioner before the GNSS epoch
# that brackets its landing.
GPIO_READ_INTERVAL_S = 0.05
# When something else reads the lines (``GpioSeedSensors.read_pending``: the daemon does ahead
# of each GNSS epoch, in the wake-up the epoch brought), the driver's own next read waits this
# long: more than the 0.1 s between epochs, so while the receiver talks the lines cost no
# wake-up of their own (each one costs ~0.25 ms of CPU on the bench machine, bare).
GPIO_MAX_WAIT_S = 0.15
# Edge events the kernel keeps for us between reads: its maximum (GPIO_V2_LINES_MAX x 16; a
# larger request is clamped). 0.5 s of edges at 2 100 seeds/s, ten read intervals. The default
# would be 16 per requested line. Edges lost to an overflow show as gaps in the kernel's
# sequence numbers and are counted (SeedSensorStats.lost) and logged.
GPIO_EVENT_BUFFER = 1024
DRAIN_TIMEOUT_S = 0.3
LOG_EVERY_S = 10.0  # at most one warning per rejection kind per this interval
# the rejection kind of a GPIO event on a line no row was configured for
KIND_UNKNOWN_LINE = "unknown_line"


class SeedEdgeEvent(NamedTuple):
    """A seed passed the sensor of ``row`` (1-based) at host monotonic time ``t_mono``.

    A NamedTuple, not a frozen dataclass: one is made per seed (~2 000 a second), and a
    frozen dataclass costs several times as much to build."""

    row: int
    t_mono: float


@dataclass
class SeedSensorStats:
    edges: int = 0
    rejected: int = 0  # lines that did not decode (serial) / events for unknown lines (gpio)
    # the same per kind: protocol.seed_line KIND_* (serial), KIND_UNKNOWN_LINE (gpio)
    rejected_by_reason: dict[str, int] = field(default_factory=dict)
    debounced: int = 0  # edges dropped as bounce
    lost: int = 0  # edges the kernel dropped because its queue was full (gpio)
    connects: int = 0
    last_error: str | None = None
    last_rejected: str | None = None

    @property
    def reconnects(self) -> int:
        return max(0, self.connects - 1)


class SeedSensorSource(Protocol):
    """What the daemon needs from either source."""

    @property
    def available(self) -> bool:
        """The port/chip is open and being read."""
        ...

    @property
    def stats(self) -> SeedSensorStats: ...

    async def run(self) -> None:
        """Read forever (reconnecting); ends only by cancellation, after delivering the edges
        that had already arrived when it came."""
        ...


EdgeCallback = Callable[[SeedEdgeEvent], None]


def _deliver(on_edge: EdgeCallback, event: SeedEdgeEvent) -> None:
    try:
        on_edge(event)
    except Exception:  # a consumer bug must not stop the sensors being read
        log.exception("seed edge callback failed")


# ---------------------------------------------------------------- serial


class SerialSeedSensors:
    """The edge-capture module on a UART (the simulator's ``SeedTubeEmulator`` speaks it)."""

    def __init__(
        self,
        port: str,
        baudrate: int,
        rows: int,
        on_edge: EdgeCallback,
        *,
        clock: Callable[[], float] = time.monotonic,
        backoff: Backoff | None = None,
    ) -> None:
        self.port = port
        self.baudrate = baudrate
        self.rows = rows
        self._decoder = SeedLineDecoder(rows)  # validates the row count now, not at first connect
        self._on_edge = on_edge
        self._stats = SeedSensorStats()
        self._log = RateLimitedLog(log, LOG_EVERY_S, clock=clock)
        self._line = SerialLine(
            port,
            baudrate,
            label="seed sensors",
            logger=log,
            on_data=self._feed,
            on_open=self._opened,
            drain=Drain(quiet_s=DRAIN_QUIET_S, timeout_s=DRAIN_TIMEOUT_S),
            read_chunk_bytes=READ_CHUNK_BYTES,
            backoff=backoff,  # None: SerialLine's default, 0.1 s doubling to 5 s
            clock=clock,
        )

    @property
    def available(self) -> bool:
        return self._line.connected

    @property
    def stats(self) -> SeedSensorStats:
        # the connection's counters are the line's; shown here under the sources' common names
        line = self._line.stats
        self._stats.connects, self._stats.last_error = line.connects, line.last_error
        return self._stats

    async def run(self) -> None:
        await self._line.run()

    def _opened(self, _writer: asyncio.StreamWriter) -> None:
        self._decoder = SeedLineDecoder(self.rows)  # a fresh connection starts a fresh line

    def _feed(self, data: bytes, t_arrival: float) -> None:
        """Decode one chunk; every line it completes is stamped with its arrival time."""
        for item in self._decoder.feed(data):
            if isinstance(item, Rejected):
                self._reject(item)
                continue
            self._stats.edges += 1
            _deliver(self._on_edge, SeedEdgeEvent(item.row, t_arrival))

    def _reject(self, item: Rejected) -> None:
        stats = self._stats
        stats.rejected += 1
        stats.rejected_by_reason[item.kind] = stats.rejected_by_reason.get(item.kind, 0) + 1
        stats.last_rejected = f"{item.reason}: {item.line!r}"
        self._log.warning(
            item.kind, "seed sensor line on %s rejected (%s): %r", self.port, item.reason,
            item.line,
        )


# ---------------------------------------------------------------- gpio


class EdgeEventLike(Protocol):
    """The part of ``gpiod.EdgeEvent`` used here."""

    @property
    def event_type(self) -> Any: ...
    @property
    def timestamp_ns(self) -> int: ...
    @property
    def line_offset(self) -> int: ...
    @property
    def global_seqno(self) -> int: ...


class LineRequestLike(Protocol):
    """The part of ``gpiod.LineRequest`` used here."""

    @property
    def fd(self) -> int: ...

    def read_edge_events(self) -> Iterable[EdgeEventLike]: ...

    def release(self) -> None: ...


RequestFactory = Callable[[str, Sequence[int], str], LineRequestLike]


def gpiod_request(chip: str, offsets: Sequence[int], bias: str) -> LineRequestLike:
    """Request falling-edge events on ``offsets`` with libgpiod v2 (imported only here)."""
    try:
        import gpiod
        from gpiod.line import Bias, Clock, Edge
    except ImportError:
        raise DeviceUnavailable(
            "seed_sensors.source = 'gpio' needs libgpiod v2 bindings: pip install 'sowgate[gpio]'"
        ) from None
    bias_value = {
        "pull_up": Bias.PULL_UP,
        "pull_down": Bias.PULL_DOWN,
        "disabled": Bias.DISABLED,
        "as_is": Bias.AS_IS,
    }[bias]
    settings = gpiod.LineSettings(
        edge_detection=Edge.FALLING, bias=bias_value, event_clock=Clock.MONOTONIC
    )
    request: LineRequestLike = gpiod.request_lines(
        chip, consumer=GPIO_CONSUMER, config={tuple(offsets): settings},
        event_buffer_size=GPIO_EVENT_BUFFER,
    )
    return request


class GpioSeedSensors:
    """One GPIO line per row (``lines[row-1]``), falling edges with kernel timestamps."""

    def __init__(
        self,
        chip: str,
        lines: Sequence[int],
        debounce_ms: float,
        on_edge: EdgeCallback,
        *,
        bias: str = "pull_up",
        request_factory: RequestFactory = gpiod_request,
        backoff: Backoff | None = None,
    ) -> None:
        if not lines:
            raise ValueError("seed_sensors.gpio_lines: need one GPIO line per row")
        if len(set(lines)) != len(lines):
            raise ValueError(f"seed_sensors.gpio_lines: a line is used twice in {list(lines)}")
        if debounce_ms < 0:
            raise ValueError(f"seed_sensors.debounce_ms must be >= 0, got {debounce_ms}")
        self.chip = chip
        self.lines = list(lines)
        self._row_of = {offset: i + 1 for i, offset in enumerate(self.lines)}
        self._debounce_ns = round(debounce_ms * 1e6)
        self._on_edge = on_edge
        self._bias = bias
        self._factory = request_factory
        self._backoff = backoff if backoff is not None else Backoff(initial_s=0.5, cap_s=10.0)
        self._last_ns: dict[int, int] = {}
        self._last_seqno: int | None = None  # the kernel numbers a request's events 1, 2, ...
        self._falling: dict[Any, bool] = {}  # event type → is it a falling edge
        self._connected = False
        self._pause: asyncio.TimerHandle | None = None  # the reader's rest between reads
        # the open request and the future that ends its reading, while one is open
        self._reading: tuple[LineRequestLike, asyncio.Future[str]] | None = None
        self._stats = SeedSensorStats()
        self._log = RateLimitedLog(log, LOG_EVERY_S)

    @property
    def available(self) -> bool:
        return self._connected

    @property
    def stats(self) -> SeedSensorStats:
        return self._stats

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                request = self._factory(self.chip, self.lines, self._bias)
            except OSError as exc:
                self._failed(f"cannot request lines {self.lines} on {self.chip}: {exc}")
                await asyncio.sleep(self._backoff.next_delay())
                continue
            broken: asyncio.Future[str] = loop.create_future()
            fd = request.fd
            loop.add_reader(fd, self._readable, request, broken)
            self._pause = None
            self._reading = (request, broken)
            self._last_seqno = None  # a new request numbers its events from 1 again
            self._connected = True
            self._stats.connects += 1
            self._backoff.reset()
            try:
                self._failed(await broken)
            except asyncio.CancelledError:
                self._read_queued(request)
                raise
            finally:
                self._connected = False
                self._reading = None
                if self._pause is not None:
                    self._pause.cancel()
                    self._pause = None
                loop.remove_reader(fd)
                with contextlib.suppress(OSError):
                    request.release()
            await asyncio.sleep(self._backoff.next_delay())

    def _read_queued(self, request: LineRequestLike) -> None:
        """After a cancel: edges the kernel has queued but the loop has not yet seen. They
        carry the kernel's stamps, so reading them late costs nothing; bounded anyway."""
        deadline = time.monotonic() + DRAIN_TIMEOUT_S
        with contextlib.suppress(OSError, ValueError):  # a failing or closed fd: nothing more
            while time.monotonic() < deadline and select.select([request.fd], [], [], 0)[0]:
                self.handle_events(request.read_edge_events())

    def read_pending(self) -> None:
        """Read what the kernel has queued now, from a wake-up the loop had anyway, and put
        the driver's own next read off by ``GPIO_MAX_WAIT_S``.

        The daemon calls this ahead of each GNSS epoch: the edges reach the recorder before
        the epoch that follows them, as they would with reads of their own, and with the
        receiver sending 10 epochs a second the lines never need a wake-up of their own.
        """
        reading, pause = self._reading, self._pause
        if reading is None or pause is None:
            return  # not open, or the reader is armed: the next edge wakes it anyway
        request, broken = reading
        try:
            queued = bool(select.select([request.fd], [], [], 0)[0])
        except (OSError, ValueError) as exc:
            if not broken.done():
                broken.set_result(f"reading {self.chip} failed: {exc}")
            return
        if queued and not self._read(request, broken):
            return
        loop = asyncio.get_running_loop()
        pause.cancel()
        self._pause = loop.call_at(
            loop.time() + GPIO_MAX_WAIT_S, self._resume, request, broken
        )

    def _readable(self, request: LineRequestLike, broken: asyncio.Future[str]) -> None:
        if not self._read(request, broken):
            return
        # let edges gather in the kernel until the next tick of the grid (see drivers.ticks)
        loop = asyncio.get_running_loop()
        loop.remove_reader(request.fd)
        self._pause = loop.call_at(
            next_tick(loop.time(), GPIO_READ_INTERVAL_S), self._resume, request, broken
        )

    def _resume(self, request: LineRequestLike, broken: asyncio.Future[str]) -> None:
        self._pause = None
        asyncio.get_running_loop().add_reader(request.fd, self._readable, request, broken)

    def _read(self, request: LineRequestLike, broken: asyncio.Future[str]) -> bool:
        """Hand every queued event on; False (and ``broken`` resolved) if the read failed."""
        try:
            events = list(request.read_edge_events())
        except OSError as exc:
            if not broken.done():
                broken.set_result(f"reading {self.chip} failed: {exc}")
            return False
        self.handle_events(events)
        return True

    def handle_event(self, event: EdgeEventLike) -> None:
        """One kernel edge event → a seed edge (or a counted bounce / stray)."""
        self.handle_events((event,))

    def handle_events(self, events: Iterable[EdgeEventLike]) -> None:
        """Kernel edge events, in order → seed edges (bounces and strays counted).

        One loop over a read's events with the driver's state in locals: at 2 000 edges a
        second the per-event method call and attribute look-ups were a fifth of the cost."""
        stats, on_edge = self._stats, self._on_edge
        falling_of, row_of, last_ns = self._falling, self._row_of, self._last_ns
        debounce_ns, last_seqno = self._debounce_ns, self._last_seqno
        # the NamedTuple's own constructor is a Python function; tuple.__new__ builds the
        # same SeedEdgeEvent in C
        new_edge = tuple.__new__
        try:
            for event in events:
                seqno = event.global_seqno
                if last_seqno is not None and seqno > last_seqno + 1:
                    self._lost(seqno - last_seqno - 1)
                last_seqno = seqno
                kind = event.event_type
                falling = falling_of.get(kind)
                if falling is None:  # once per event type, not per event
                    falling = falling_of[kind] = (
                        getattr(kind, "name", str(kind)) == "FALLING_EDGE"
                    )
                if not falling:
                    continue
                row = row_of.get(event.line_offset)
                if row is None:
                    self._stray(event.line_offset)
                    continue
                t_ns = event.timestamp_ns
                last = last_ns.get(row)
                if last is not None and t_ns - last < debounce_ns:
                    stats.debounced += 1  # bounce: keep the first edge's time, the true one
                    continue
                last_ns[row] = t_ns
                stats.edges += 1
                try:
                    on_edge(new_edge(SeedEdgeEvent, (row, t_ns / NS_PER_S)))
                except Exception:  # a consumer bug must not stop the sensors being read
                    log.exception("seed edge callback failed")
        finally:
            self._last_seqno = last_seqno

    def _stray(self, offset: int) -> None:
        stats = self._stats
        stats.rejected += 1
        by_reason = stats.rejected_by_reason
        by_reason[KIND_UNKNOWN_LINE] = by_reason.get(KIND_UNKNOWN_LINE, 0) + 1
        stats.last_rejected = f"event on unrequested line {offset}"
        self._log.warning(
            KIND_UNKNOWN_LINE, "GPIO seed sensors: event on line %d of %s, which is no row's",
            offset, self.chip,
        )

    def _lost(self, lost: int) -> None:
        self._stats.lost += lost
        log.error(
            "GPIO seed sensors: the kernel's event queue overflowed, %d edges lost (%d in "
            "all): the event loop did not read %s for too long", lost, self._stats.lost,
            self.chip,
        )

    def _failed(self, message: str) -> None:
        if message != self._stats.last_error:
            log.warning("seed sensors: %s", message)
        self._stats.last_error = message
