"""A UM982 dual-antenna RTK receiver in software: sentences on a pty, ground truth on the side.

Two layers:

* ``um982_sentences`` — a pure generator (``simulator.gnss_sentences``, sharing no code with
  ``protocol/``): one epoch's ``$GNRMC``, ``$GNGGA`` and ``#HEADINGA``
  with correct checksums/CRC and the field widths the real receiver uses. Tests build their
  inputs with it, so the parsers are never tested against hand-typed strings.
* ``Um982Emulator`` — samples a true trajectory at ``rate_hz`` on the UTC grid, adds RTK and
  heading noise, converts local ENU metres to WGS84 with pymap3d, waits the receiver's output
  latency and writes the lines to a pty. For every epoch it keeps the *true* pose and the
  instant it describes, which is what every accuracy check compares against.

Faults a field receiver produces can be injected: corrupted checksums, line noise, a heading
solution that drops out, and the port vanishing (USB adapter unplugged) and coming back; and
its time going wrong: stamps shifted for a few epochs or for good (``shift_stamps``), dates
1024 weeks early (``week_rollover``), a UTC leap second (``insert_leap_second``).
"""

from __future__ import annotations

import asyncio
import math
import os
import random
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Final, Protocol

import pymap3d

from drivers.tasks import StartClose
from simulator.gnss_sentences import GEOID_SEP_M, GPS_MINUS_UTC_S, Fix, epoch_sentences
from simulator.pty_link import PtyPair, unplug

__all__ = ["GEOID_SEP_M", "Fix", "TruthEpoch", "Um982Emulator", "corrupt_checksum",
           "um982_sentences"]

TRUTH_CAPACITY: Final = 200_000  # epochs of ground truth kept (5.5 h at 10 Hz)
SPEED_SIGMA_KMH: Final = 0.03  # Doppler speed noise of an RTK receiver

# horizontal noise scale for each fix type
_SIGMA_FACTOR: Final[dict[str, float]] = {  # multiples of rtk_sigma_m (1 cm -> 20 cm float...)
    "rtk_fixed": 1.0, "rtk_float": 20.0, "dgps": 50.0, "single": 150.0, "none": 150.0,
}


class PoseLike(Protocol):
    """What the emulator needs from a true pose (simulator.plant.Pose satisfies it)."""

    @property
    def east(self) -> float: ...
    @property
    def north(self) -> float: ...
    @property
    def heading_deg(self) -> float: ...
    @property
    def speed_kmh(self) -> float: ...


@dataclass(frozen=True)
class TruthEpoch:
    """Ground truth for one output epoch: what the receiver should ideally have reported."""

    utc: datetime
    t_mono: float  # the epoch instant on the monotonic clock the daemon stamps arrivals with
    t_sim: float  # the same instant in the trajectory's time (argument given to pose_at)
    pose: PoseLike
    lat: float  # true position of the antenna (before noise)
    lon: float


# One epoch's RMC, GGA and #HEADINGA, encoded by the simulator's own ``simulator.gnss_sentences``
# (no code shared with the decoders in protocol/ it feeds).
um982_sentences = epoch_sentences


# An epoch written later than this after its due time counts as late (see late_epochs)
LATE_EPOCH_S = 0.05

# binary bytes that would end a line or start a sentence become 0x00 (see binary_output)
_NO_LINE_OR_START = bytes(0 if b in b"\n$#" else b for b in range(256))


def corrupt_checksum(line: str) -> str:
    """The same line with its last checksum digit changed, so it must be rejected."""
    last = line[-1]
    swapped = "0" if last not in "0" else "1"
    return line[:-1] + swapped


class Um982Emulator(StartClose):
    """Writes a noisy view of ``pose_at`` as UM982 output to a pty, 10 times a second.

    ``pose_at`` is called with the trajectory time ``t_sim = t_mono - t0_mono``: pass the same
    ``t0_mono`` to every simulator of a run so seeds, radar and GNSS share one time line.
    The UTC of epoch k is ``utc_start + k / rate_hz`` and it is written at
    ``t0_mono + k / rate_hz + output_latency_s`` (the receiver's real delay, which the position
    model must account for).
    """

    def __init__(
        self,
        pose_at: Callable[[float], PoseLike],
        *,
        origin_lat: float,
        origin_lon: float,
        origin_alt_m: float = 100.0,
        rate_hz: float = 10.0,
        rtk_sigma_m: float = 0.01,
        heading_sigma_deg: float = 0.1,
        output_latency_s: float = 0.02,
        seed: int = 0,
        fix: Fix = "rtk_fixed",
        utc_start: datetime | None = None,
        t0_mono: float | None = None,
        link_path: str | os.PathLike[str] | None = None,
        clock: Callable[[], float] = time.monotonic,
        antenna_height_m: float = 0.0,
        roll_deg: float = 0.0,
        heading_offset_deg: float = 0.0,
    ) -> None:
        if not 0 < rate_hz <= 50:
            raise ValueError(f"rate_hz must be in (0, 50], got {rate_hz}")
        if not 0 <= output_latency_s < 1.0 / rate_hz:
            raise ValueError("output_latency_s must be >= 0 and shorter than one epoch")
        self._pose_at = pose_at
        self.origin = (origin_lat, origin_lon, origin_alt_m)
        self.rate_hz = rate_hz
        self.rtk_sigma_m = rtk_sigma_m
        self.heading_sigma_deg = heading_sigma_deg
        self.output_latency_s = output_latency_s
        self.fix: Fix = fix
        # Terrain: the pose is the ground point below the antenna; on a side slope of
        # ``roll_deg`` (positive = right side down) the antenna, ``antenna_height_m`` up,
        # leans H·sin(roll) to the right of it. The antennas sit as ``heading_offset_deg``
        # says (the daemon's gnss.heading_offset_deg): #HEADINGA reports the baseline's
        # heading (machine heading − offset) and its elevation (roll·sin(offset)).
        self.antenna_height_m = antenna_height_m
        self.roll_deg = roll_deg
        self.heading_offset_deg = heading_offset_deg
        self._rng = random.Random(seed)
        self._clock = clock
        self._utc_start = utc_start
        self._t0_mono = t0_mono
        self._link_path = link_path
        self._pair: PtyPair | None = None
        self._task: asyncio.Task[None] | None = None
        self._corrupt_left = 0
        self._garbage = bytearray()
        self._drop_heading = False
        self._interleave = b""
        # time faults: (shift, epochs left or None for good), rollover, leap second midnight
        self._stamp_shift = timedelta(0)
        self._shift_epochs: int | None = None
        self._rollover = False
        self._leap_midnight: datetime | None = None
        self.truth: deque[TruthEpoch] = deque(maxlen=TRUTH_CAPACITY)
        self.epochs_written = 0
        # (epoch instant, seconds written after its due time) for writes > 50 ms late or
        # skipped (starved): the fault matrix tells the simulator's lateness from the daemon's
        self.late_epochs: deque[tuple[float, float]] = deque(maxlen=10_000)
        self.lines_corrupted = 0
        self.bytes_dropped = 0  # written while nobody read and the pty buffer was full

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        if self._task is not None:
            raise RuntimeError("emulator already started")
        self._pair = PtyPair(self._link_path)
        if self._t0_mono is None:
            self._t0_mono = self._clock()
        if self._utc_start is None:
            self._utc_start = datetime.now(UTC).replace(microsecond=0)
        self._task = asyncio.create_task(self._run(), name="um982-emulator")

    async def close(self) -> None:
        await unplug(self._task, self._pair)
        self._task, self._pair = None, None

    @property
    def device_path(self) -> str:
        """The path the daemon opens (the symlink when ``link_path`` was given)."""
        if self._pair is None:
            if self._link_path is not None:
                return os.fspath(self._link_path)
            raise RuntimeError("emulator not started")
        return self._pair.device_path

    @property
    def t0_mono(self) -> float:
        if self._t0_mono is None:
            raise RuntimeError("emulator not started")
        return self._t0_mono

    # -- fault injection ---------------------------------------------------------------------

    def corrupt_next(self, n: int = 1) -> None:
        """Give the next ``n`` lines a wrong checksum/CRC."""
        self._corrupt_left += n

    def garbage(self, n_bytes: int) -> None:
        """Write ``n_bytes`` of random line noise before the next epoch's lines."""
        self._garbage += self._rng.randbytes(n_bytes)

    def binary_output(self, n_bytes: int) -> None:
        """Write ``n_bytes`` of a binary log (no LF, '$' or '#' in it) right before the next
        epoch's lines, as a receiver with binary logs enabled on the same port does."""
        noise = self._rng.randbytes(n_bytes).translate(_NO_LINE_OR_START)
        self._garbage += noise

    def drop_heading(self, on: bool = True) -> None:
        """Stop (or resume) sending #HEADINGA, as when the secondary antenna loses lock."""
        self._drop_heading = on

    def interleave(self, data: bytes | None) -> None:
        """Write ``data`` before every line from now on (None: stop), as a receiver with
        binary logs switched on mixes them with its NMEA sentences on the one port."""
        self._interleave = data or b""

    def shift_stamps(self, by: timedelta, epochs: int | None = None) -> None:
        """Stamp the next ``epochs`` epochs (None: every one from now on) ``by`` off the true
        time, sentences and heading log alike (a glitch, or the receiver's clock stepping)."""
        self._stamp_shift, self._shift_epochs = by, epochs

    def week_rollover(self, on: bool = True) -> None:
        """Stamp dates 1024 weeks early, as a receiver with the GPS week rollover bug does."""
        self._rollover = on

    def insert_leap_second(self, midnight: datetime) -> None:
        """A UTC leap second before ``midnight``: the epochs of the second after it are sent
        as 23:59:60.x, every later one one second behind the true (continuous) time."""
        self._leap_midnight = midnight

    def stamp_of(self, utc: datetime) -> tuple[datetime, bool, int]:
        """(stamp sent, leap second?, GPS−UTC count) for an epoch truly at ``utc``; counts
        down a temporary shift (call once per epoch)."""
        leap, count = False, GPS_MINUS_UTC_S
        midnight = self._leap_midnight
        if midnight is not None and utc >= midnight:
            leap = utc < midnight + timedelta(seconds=1)
            count += 0 if leap else 1
            utc -= timedelta(seconds=1)
        if self._shift_epochs is None or self._shift_epochs > 0:
            utc += self._stamp_shift
            if self._shift_epochs is not None:
                self._shift_epochs -= 1
        if self._rollover:
            utc -= timedelta(weeks=1024)
        return utc, leap, count

    def unplug(self) -> None:
        """The port vanishes: both pty ends close, the reader sees EIO, the path disappears."""
        if self._pair is not None:
            self._pair.close()
            self._pair = None

    def replug(self) -> None:
        """The port comes back on the same ``link_path`` (a new pty, as a new ttyUSB would)."""
        if self._link_path is None:
            raise RuntimeError("replug needs a link_path so the daemon can find the new port")
        if self._pair is None:
            self._pair = PtyPair(self._link_path)

    # -- the epoch loop ----------------------------------------------------------------------

    def sample_epoch(self, k: int) -> list[str]:
        """Lines of epoch ``k`` (noise, faults applied) and its ground truth recorded.

        Usable without the pty (given ``t0_mono`` and ``utc_start``) for statistics tests.
        """
        if self._utc_start is None:
            raise RuntimeError("utc_start unknown: pass it or start the emulator")
        t_mono = self.t0_mono + k / self.rate_hz
        t_sim = t_mono - self.t0_mono
        utc = self._utc_start + timedelta(milliseconds=round(k * 1000.0 / self.rate_hz))
        pose = self._pose_at(t_sim)
        lat0, lon0, h0 = self.origin
        h_rad = math.radians(pose.heading_deg)
        lean = self.antenna_height_m * math.sin(math.radians(self.roll_deg))  # to the right
        ant_e = pose.east + lean * math.cos(h_rad)
        ant_n = pose.north - lean * math.sin(h_rad)
        true_lat, true_lon, _ = pymap3d.enu2geodetic(ant_e, ant_n, 0.0, lat0, lon0, h0)
        self.truth.append(
            TruthEpoch(utc, t_mono, t_sim, pose, float(true_lat), float(true_lon))
        )
        sigma = self.rtk_sigma_m * _SIGMA_FACTOR[self.fix]
        east = ant_e + self._rng.gauss(0.0, sigma)
        north = ant_n + self._rng.gauss(0.0, sigma)
        up = self._rng.gauss(0.0, 2.0 * sigma)
        lat, lon, h = pymap3d.enu2geodetic(east, north, up, lat0, lon0, h0)
        heading = (
            pose.heading_deg - self.heading_offset_deg
            + self._rng.gauss(0.0, self.heading_sigma_deg)
        ) % 360.0
        baseline_pitch = self.roll_deg * math.sin(math.radians(self.heading_offset_deg))
        if baseline_pitch:
            baseline_pitch += self._rng.gauss(0.0, 2 * self.heading_sigma_deg)
        speed = max(0.0, pose.speed_kmh + self._rng.gauss(0.0, SPEED_SIGMA_KMH))
        stamp, leap, count = self.stamp_of(utc)
        lines = um982_sentences(
            stamp, float(lat), float(lon), float(h) - GEOID_SEP_M, speed, pose.heading_deg,
            heading, self.fix, heading_ok=True, hdg_std=max(self.heading_sigma_deg, 0.01),
            pitch_deg=baseline_pitch, leap_second=leap, gps_utc_leap_s=count,
        )
        if self._drop_heading:
            lines = lines[:2]
        for i in range(len(lines)):
            if self._corrupt_left > 0:
                self._corrupt_left -= 1
                self.lines_corrupted += 1
                lines[i] = corrupt_checksum(lines[i])
        return lines

    def _write(self, data: bytes) -> None:
        if self._pair is None or self._pair.closed:
            return
        try:
            written = os.write(self._pair.master_fd, data)
        except BlockingIOError:
            written = 0
        except OSError:
            return
        self.bytes_dropped += len(data) - written

    async def _run(self) -> None:
        period = 1.0 / self.rate_hz
        k = 0
        while True:
            t_epoch = self.t0_mono + k * period
            delay = t_epoch - self._clock()
            if delay > 0:
                await asyncio.sleep(delay)
            elif delay < -period:  # we were starved (loaded CI box): skip, don't burst
                self.late_epochs.append((t_epoch, -delay))
                k += math.ceil(-delay / period)
                continue
            lines = self.sample_epoch(k)
            await asyncio.sleep(max(0.0, t_epoch + self.output_latency_s - self._clock()))
            payload = bytes(self._garbage) + b"".join(
                self._interleave + f"{ln}\r\n".encode() for ln in lines
            )
            self._garbage.clear()
            self._write(payload)
            late = self._clock() - (t_epoch + self.output_latency_s)
            if late > LATE_EPOCH_S:
                self.late_epochs.append((t_epoch, late))
            self.epochs_written += 1
            k += 1
