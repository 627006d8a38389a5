"""The UM982 on its UART: sentences stamped on arrival, assembled into one epoch per UTC instant.

Why epochs: RMC (speed, date), GGA (fix quality, height) and #HEADINGA (dual-antenna heading)
each describe the same instant but arrive as separate lines. The position model needs them
together, with *when they arrived on this host* — that arrival time, not the receiver's UTC,
is what a seed-tube edge (stamped on the same monotonic clock) can be compared with.

An epoch is emitted as soon as every sentence kind in ``required`` has been seen for its UTC
time, or, if one never comes (heading lost, line corrupted), when another UTC time begins or
the line goes quiet; it then carries what it had. A sentence for an epoch already emitted (up
to ``LATE_WINDOW_MS`` behind the newest) is counted as ``late`` and dropped. A stamp further
from the newest is not judged here: it is a new time line (a bad stamp, the receiver's time
stepping), assembled like any other, and the position model decides whether to believe it
(``gateway.recording.positioning.gnss_time``). So one epoch stamped hours ahead cannot make
every later, correct one "late".

A UTC leap second (``235960.xx``) is an epoch of its own, after 23:59:59.9 and before
00:00:00.0 (``GnssEpoch.leap_second``), and a heading log of that instant is matched to it
(``protocol.unicore.place_in_leap_second``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from datetime import UTC, date, datetime, timedelta
from datetime import time as dtime
from typing import Final, Literal

from drivers.backoff import Backoff
from drivers.log_limit import RateLimitedLog
from drivers.serial_line import SerialLine
from drivers.tasks import StartClose, cancel_and_wait
from protocol.gnss import REASON_UNKNOWN, GnssEvent, GnssLineDecoder, Rejected
from protocol.nmea import MS_PER_DAY, Gga, Hdt, Rmc, Ths, Vtg, utc_ms_of_day
from protocol.unicore import GPS_UTC_LEAP_S, Heading, place_in_leap_second

log = logging.getLogger(__name__)

Fix = Literal["rtk_fixed", "rtk_float", "dgps", "single", "none"]

READ_CHUNK_BYTES: Final = 4096
DAY_MS: Final = MS_PER_DAY
# the keys of a day: its milliseconds, and the second 60 of a leap second after them
KEY_SPAN_MS: Final = DAY_MS + 1000
# A sentence at most this far behind the newest epoch is a straggler of an epoch already
# emitted (late); further back it starts a new time line.
LATE_WINDOW_MS: Final = 2000
DEFAULT_REQUIRED: Final = frozenset({"RMC", "GGA", "HEADING"})
EPOCH_MAX_WAIT_S: Final = 0.3  # an open epoch older than this is emitted when the line is quiet
SILENCE_RECONNECT_S: Final = 5.0  # no byte for this long: reopen the port (adapter wedged)
LOG_EVERY_S: Final = 10.0  # at most one warning per rejection reason per this interval

# GGA quality indicator -> fix. 3 (PPS) counts as single; 6 (dead reckoning), 7 (manual) and
# 8 (simulator) are not measurements of where we are; 9 is SBAS on some firmwares.
GGA_QUALITY_FIX: Final[dict[int, Fix]] = {
    0: "none", 1: "single", 2: "dgps", 3: "single", 4: "rtk_fixed", 5: "rtk_float",
    6: "none", 7: "none", 8: "none", 9: "dgps",
}
# RMC mode indicator (NMEA 2.3+) -> fix, used when the epoch has no GGA.
RMC_MODE_FIX: Final[dict[str, Fix]] = {
    "R": "rtk_fixed", "F": "rtk_float", "D": "dgps", "P": "dgps", "A": "single",
    "E": "none", "M": "none", "S": "none", "N": "none",
}


@dataclass(frozen=True)
class GnssEpoch:
    """Everything the receiver said about one UTC instant, and when it reached us."""

    utc: datetime
    t_mono: float  # host monotonic time when the first sentence of this epoch arrived
    lat: float
    lon: float
    alt_m: float | None  # above mean sea level (GGA)
    fix: Fix
    speed_kmh: float | None
    course_deg: float | None
    heading_deg: float | None  # None when the receiver had no heading solution at all
    heading_valid: bool  # ambiguity-fixed dual-antenna heading (see protocol.unicore)
    num_sv: int | None
    # #HEADINGA's "pitch": the elevation of the antenna baseline (primary -> secondary),
    # positive when the secondary is higher; None without a Unicore heading solution. The
    # machine's roll or pitch depending on how the antennas sit (gnss.heading_offset_deg).
    baseline_pitch_deg: float | None = None
    # second 60 of 23:59 (a UTC leap second): ``utc`` then holds 23:59:59 + the fraction
    leap_second: bool = False


def fix_from_gga_quality(quality: int) -> Fix:
    return GGA_QUALITY_FIX.get(quality, "none")


def fix_from_rmc(rmc: Rmc) -> Fix:
    if not rmc.valid:
        return "none"
    if rmc.mode is None:  # pre-2.3 receivers: A means "some fix"
        return "single"
    return RMC_MODE_FIX.get(rmc.mode, "none")


@dataclass
class _Partial:
    ms_of_day: int
    t_first: float
    day: date | None = None
    kinds: set[str] = field(default_factory=set)
    rmc: Rmc | None = None
    gga: Gga | None = None
    vtg: Vtg | None = None
    heading: Heading | Hdt | Ths | None = None


def _behind(a: int, b: int) -> bool:
    """``a`` is ``b`` or up to ``LATE_WINDOW_MS`` before it on the daily clock (midnight and
    a leap second allowed for)."""
    return (b - a) % KEY_SPAN_MS <= LATE_WINDOW_MS


class EpochAssembler:
    """Groups timed sentences by UTC instant. Pure: arrival times are passed in."""

    def __init__(
        self,
        required: Iterable[str] = DEFAULT_REQUIRED,
        *,
        leap_s: int = GPS_UTC_LEAP_S,
        today: Callable[[], date] = lambda: datetime.now(UTC).date(),
        heading_offset_deg: float = 0.0,
    ) -> None:
        self.required = frozenset(required)
        self.leap_s = leap_s
        # machine heading = receiver heading + offset: the receiver reports the direction of
        # its antenna baseline (primary -> secondary), which is the direction of travel only
        # when the secondary antenna sits straight ahead of the primary one
        self.heading_offset_deg = heading_offset_deg
        self._today = today
        self._open: dict[int, _Partial] = {}
        self._last_key: int | None = None
        self._last_utc: datetime | None = None
        self._leap_midnight: datetime | None = None  # the end of a leap second in progress
        self.counts: Counter[str] = Counter()  # epochs, late, untimed, no_position

    def add(self, event: GnssEvent, t_mono: float) -> list[GnssEpoch]:
        """Take one decoded sentence that arrived at ``t_mono``; return epochs now complete."""
        if isinstance(event, Hdt | Ths | Vtg):
            return self._add_untimed(event)
        if isinstance(event, Heading):
            utc = event.utc(event.leap_s if event.leap_s is not None else self.leap_s)
            utc, leap = place_in_leap_second(utc, self._leap_midnight)
            key = utc_ms_of_day(utc.time(), leap)
            day: date | None = utc.date()
        else:
            if event.utc is None:
                self.counts["untimed"] += 1  # no fix yet: receiver leaves the time empty
                return []
            key = utc_ms_of_day(event.utc, event.leap_second)
            day = event.date if isinstance(event, Rmc) else None
            self._note_leap_second(event, day)
        if self._last_key is not None and _behind(key, self._last_key):
            self.counts["late"] += 1
            return []
        # what is open for another instant is complete unless it is just after this one
        out = [self._emit(k) for k in sorted(self._open, key=lambda k: self._open[k].t_first)
               if k != key and not _behind(key, k)]
        partial = self._open.get(key)
        if partial is None:
            partial = self._open[key] = _Partial(key, t_mono)
        if day is not None:
            partial.day = day
        if isinstance(event, Rmc):
            partial.rmc, kind = event, "RMC"
        elif isinstance(event, Gga):
            partial.gga, kind = event, "GGA"
        else:
            partial.heading, kind = event, "HEADING"
        partial.kinds.add(kind)
        if partial.kinds >= self.required:
            out.append(self._emit(key))
        return [e for e in out if e is not None]

    def _note_leap_second(self, event: Rmc | Gga, day: date | None) -> None:
        """Second 60 begins: headings of it are matched to it; once it is over, a heading
        without its own leap count is converted with one more (``leap_s``)."""
        if event.leap_second:
            if self._leap_midnight is None:
                on = day or (self._last_utc.date() if self._last_utc else self._today())
                self._leap_midnight = datetime.combine(on, dtime(), UTC) + timedelta(days=1)
        elif self._leap_midnight is not None:
            self._leap_midnight = None
            self.leap_s += 1

    def _add_untimed(self, event: Hdt | Ths | Vtg) -> list[GnssEpoch]:
        """HDT/THS/VTG carry no time: they belong to the epoch whose burst is in progress."""
        if not self._open:
            self.counts["untimed"] += 1
            return []
        key = max(self._open, key=lambda k: self._open[k].t_first)
        partial = self._open[key]
        if isinstance(event, Vtg):
            partial.vtg = event
            partial.kinds.add("VTG")
        else:
            partial.heading = event
            partial.kinds.add("HEADING")
        if partial.kinds >= self.required:
            epoch = self._emit(key)
            return [] if epoch is None else [epoch]
        return []

    def expire(self, older_than_mono: float) -> list[GnssEpoch]:
        """Emit open epochs whose first sentence arrived before ``older_than_mono``."""
        keys = [k for k, p in self._open.items() if p.t_first < older_than_mono]
        return self._emit_keys(keys)

    def flush(self) -> list[GnssEpoch]:
        """Emit everything open (end of stream)."""
        return self._emit_keys(list(self._open))

    def _emit_keys(self, keys: list[int]) -> list[GnssEpoch]:
        keys.sort(key=lambda k: self._open[k].t_first)
        return [e for e in (self._emit(k) for k in keys) if e is not None]

    def _utc(self, p: _Partial) -> datetime:
        # second 60 is carried as 23:59:59 + fraction (GnssEpoch.leap_second)
        tod = timedelta(milliseconds=p.ms_of_day - (1000 if p.ms_of_day >= DAY_MS else 0))
        if p.day is not None:
            return datetime.combine(p.day, dtime(), UTC) + tod
        if self._last_utc is not None:
            guess = datetime.combine(self._last_utc.date(), dtime(), UTC) + tod
            if guess < self._last_utc - timedelta(hours=12):
                guess += timedelta(days=1)  # GGA just after midnight, before the next RMC
            return guess
        return datetime.combine(self._today(), dtime(), UTC) + tod

    def _emit(self, key: int) -> GnssEpoch | None:
        p = self._open.pop(key)
        if self._last_key is None or not _behind(key, self._last_key):
            self._last_key = key
        utc = self._utc(p)
        self._last_utc = utc
        epoch = _build_epoch(p, utc, self.heading_offset_deg)
        if epoch is not None and key >= DAY_MS:
            epoch = replace(epoch, leap_second=True)
        self.counts["epochs" if epoch is not None else "no_position"] += 1
        return epoch


def _build_epoch(p: _Partial, utc: datetime, heading_offset_deg: float = 0.0) -> GnssEpoch | None:
    gga, rmc = p.gga, p.rmc
    if gga is not None and gga.lat is not None and gga.lon is not None:
        lat, lon = gga.lat, gga.lon
    elif rmc is not None and rmc.lat is not None and rmc.lon is not None:
        lat, lon = rmc.lat, rmc.lon
    else:
        return None
    if gga is not None:
        fix = fix_from_gga_quality(gga.quality)
    else:
        assert rmc is not None
        fix = fix_from_rmc(rmc)
    speed = rmc.speed_kmh if rmc is not None else None
    course = rmc.course_deg if rmc is not None else None
    if speed is None and p.vtg is not None:
        speed = p.vtg.speed_kmh
    if course is None and p.vtg is not None:
        course = p.vtg.course_deg
    heading_deg: float | None = None
    baseline_pitch: float | None = None
    valid = False
    h = p.heading
    if isinstance(h, Heading):
        if h.quality != "none":
            heading_deg, valid = h.heading_deg, h.valid
            baseline_pitch = h.pitch_deg
    elif isinstance(h, Ths):
        heading_deg, valid = h.heading_deg, h.valid
    elif isinstance(h, Hdt):
        heading_deg, valid = h.heading_deg, h.heading_deg is not None
    if heading_deg is not None and heading_offset_deg:
        heading_deg = (heading_deg + heading_offset_deg) % 360.0
        if heading_deg >= 360.0:  # float rounding of a tiny negative sum
            heading_deg = 0.0
    return GnssEpoch(
        utc=utc,
        t_mono=p.t_first,
        lat=lat,
        lon=lon,
        alt_m=gga.alt_m if gga is not None else None,
        fix=fix,
        speed_kmh=speed,
        course_deg=course,
        heading_deg=heading_deg,
        heading_valid=valid,
        num_sv=gga.num_sv if gga is not None else None,
        baseline_pitch_deg=baseline_pitch,
    )


@dataclass(frozen=True)
class GnssStats:
    sentences_ok: int
    rejected: dict[str, int]  # lines per reason, see protocol.gnss REASON_*
    epochs: int
    late: int
    reconnects: int
    connected: bool
    last_error: str | None
    # bytes dropped from lines longer than protocol.gnss.MAX_LINE_BYTES (binary output on the
    # port); each such line is also one "overlong" in ``rejected``
    discarded_bytes: int = 0


class GnssReader(StartClose):
    """Reads the receiver's port forever (reopened by ``drivers.serial_line.SerialLine``) and
    hands complete epochs to a callback.

    ``on_epoch`` runs in the event loop; keep it short (append to a buffer, set an event).
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        *,
        on_epoch: Callable[[GnssEpoch], None],
        stale_after_s: float = 0.5,
        required: Iterable[str] = DEFAULT_REQUIRED,
        epoch_max_wait_s: float = EPOCH_MAX_WAIT_S,
        silence_reconnect_s: float = SILENCE_RECONNECT_S,
        clock: Callable[[], float] = time.monotonic,
        backoff: Backoff | None = None,
        heading_offset_deg: float = 0.0,
    ) -> None:
        self.port = port
        self.baudrate = baudrate
        self._on_epoch = on_epoch
        self.stale_after_s = stale_after_s
        self._epoch_max_wait_s = epoch_max_wait_s
        self._clock = clock
        self._decoder = GnssLineDecoder()
        self._assembler = EpochAssembler(required, heading_offset_deg=heading_offset_deg)
        self._task: asyncio.Task[None] | None = None
        # the receiver talks 10+ times a second: a port silent for ``silence_reconnect_s`` is
        # a wedged adapter or a receiver that rebooted, and is reopened
        self._line = SerialLine(
            port,
            baudrate,
            label="GNSS",
            logger=log,
            on_data=self._received,
            on_idle=self._quiet,
            on_close=self._closed,
            idle_after_s=epoch_max_wait_s,
            silence_reconnect_s=silence_reconnect_s,
            read_chunk_bytes=READ_CHUNK_BYTES,
            backoff=backoff,  # None: SerialLine's default, 0.1 s doubling to 5 s
            clock=clock,
        )
        self.latest: GnssEpoch | None = None
        self.last_rejected: Rejected | None = None
        self._log = RateLimitedLog(log, LOG_EVERY_S, clock=clock)

    # -- state for the rest of the daemon ----------------------------------------------------

    @property
    def available(self) -> bool:
        """A fresh epoch with a fix: usable as a position and as a speed source."""
        e = self.latest
        return (
            e is not None
            and e.fix != "none"
            and self._clock() - e.t_mono <= self.stale_after_s
        )

    def speed_kmh(self) -> float | None:
        """GNSS ground speed for the control loop, or None when not available."""
        e = self.latest
        return e.speed_kmh if self.available and e is not None else None

    @property
    def stats(self) -> GnssStats:
        counts, line = self._decoder.counts, self._line.stats
        return GnssStats(
            sentences_ok=counts["ok"],
            rejected={k: v for k, v in counts.items() if k != "ok"},
            epochs=self._assembler.counts["epochs"],
            late=self._assembler.counts["late"],
            reconnects=line.reconnects,
            connected=line.connected,
            last_error=line.last_error,
            discarded_bytes=self._decoder.discarded_bytes,
        )

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        if self._task is not None:
            raise RuntimeError("GnssReader already started")
        self._task = asyncio.create_task(self._line.run(), name=f"gnss-reader:{self.port}")

    async def close(self) -> None:
        """Stop reading and close the port (what was half-read is delivered first)."""
        await cancel_and_wait(self._task)
        self._task = None

    # -- I/O ---------------------------------------------------------------------------------

    def _received(self, data: bytes, t_arrival: float) -> None:
        """One chunk from the port; ``t_arrival`` stamps every line it completes."""
        self._dispatch(self._decoder.feed(data), t_arrival)
        self._deliver(self._assembler.expire(t_arrival - self._epoch_max_wait_s))

    def _quiet(self, now: float) -> None:
        """Nothing arrived for ``epoch_max_wait_s``: emit the epochs that waited long enough."""
        self._deliver(self._assembler.expire(now - self._epoch_max_wait_s))

    def _closed(self) -> None:
        """The port closed: what was half-read is all there will be of it."""
        self._dispatch(self._decoder.flush(), self._clock())
        self._deliver(self._assembler.flush())

    def _dispatch(self, items: list[GnssEvent | Rejected], t_mono: float) -> None:
        for item in items:
            if isinstance(item, Rejected):
                self.last_rejected = item
                if item.reason == REASON_UNKNOWN:  # sentences we do not use: normal traffic
                    log.debug("GNSS line skipped (%s): %s", item.reason, item.detail)
                else:  # counted per reason in ``stats``, summarised by the daemon
                    self._log.warning(
                        item.reason, "GNSS line on %s rejected (%s): %s: %r",
                        self.port, item.reason, item.detail, item.line,
                    )
                continue
            self._deliver(self._assembler.add(item, t_mono))

    def _deliver(self, epochs: list[GnssEpoch]) -> None:
        for epoch in epochs:
            self.latest = epoch
            try:
                self._on_epoch(epoch)
            except Exception:  # a consumer bug must not stop the receiver being read
                log.exception("GNSS on_epoch callback failed")
