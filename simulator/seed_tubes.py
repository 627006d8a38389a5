"""Planter rows dropping seeds, with the true landing point of every seed kept as ground truth.

``plan_seeds`` is pure: given a ``Drive`` it decides when each row's seed passes its tube
sensor (the metering follows ground speed, so seeds are spaced in distance, with jitter and
the occasional miss and double, only while the implement is lowered and moving) and where
that seed really lands: the row outlet's position at ``t_edge + fall_time(speed)`` — the same
fall-time law the position model uses (paper C, Table 1), plus optional fall-time scatter and
bounce along the furrow. Because that truth is the position model's own law, it only checks
plumbing (integration tests: every seed positioned, stored, published); the positioning benchmark
judges accuracy against ``simulator.field_truth`` instead, which shares nothing with the model.

``SeedTubeEmulator`` plays a plan in real time on a pty as the edge-capture module would,
``D,<row>\\r\\n`` per seed at its edge instant, on the shared time line
``t_sim = time.monotonic() − t0_mono`` used by every simulator of a run. On a starved host
its timer can fire late; the line then tells the daemon of the seed late, and the truth is
the seed as sent (``SeedTubeEmulator.truth``: edge, landing instant and point moved by the
lateness), since a machine whose sensor edge comes 0.2 s late dropped that seed 0.2 s later
as far as anything can tell. Judging the daemon against the plan instead blamed it for the
simulator's own stall (two seeds written 0.17 s late, "no record stamped when they landed").
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import math
import os
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from drivers.tasks import StartClose
from gateway.config.machine import MachineSection
from gateway.config.recording import (
    DEFAULT_FALL_TIME_TABLE,
    PositioningSection,
    row_lateral_from_width,
)
from protocol.seed_line import encode_seed_line
from simulator.plant import Drive, Pose
from simulator.pty_link import PtyPair, unplug

PLAN_STEP_S = 0.002  # distance integration step: 6.7 mm at 12 km/h
MIN_SOWING_KMH = 1.0  # the metering drive stops below this
DOUBLE_GAP_S = (0.004, 0.02)  # a double: the second seed follows within this window
MAX_PLANNED_SEEDS = 1_000_000
# An edge written later than this after its plan was late (a starved host): counted, and its
# truth moved to when it was written. Below it, timer and write jitter of a sound host.
LATE_WRITE_S = 0.005


@dataclass(frozen=True)
class SeedTruth:
    """One seed: when it passed the sensor and where it really came to rest (local ENU)."""

    row: int
    t_edge: float  # trajectory time (t_sim) of the sensor edge
    t_land: float
    east: float
    north: float
    # how late the emulator wrote its edge (a starved host): the times and place above are
    # already those of the seed as sent, ``late_s`` after its plan
    late_s: float = 0.0


def _default_row_lateral() -> tuple[float, ...]:
    """The outlets a daemon derives for the default ``[machine]`` (rows, working width), so a
    default planter and a default daemon config describe the same machine."""
    machine = MachineSection()
    return tuple(row_lateral_from_width(machine.working_width_m, machine.rows))


@dataclass(frozen=True)
class PlanterModel:
    """How the planter meters and where its outlets are."""

    row_lateral_m: Sequence[float] = field(default_factory=_default_row_lateral)
    outlet_behind_antenna_m: float = 1.2
    spacing_m: float = 0.2
    spacing_cv: float = 0.08  # seed-to-seed variation of a good vacuum meter
    miss_prob: float = 0.01
    double_prob: float = 0.01
    fall_time_table: Sequence[tuple[float, float]] = tuple(DEFAULT_FALL_TIME_TABLE)
    fall_time_sigma_s: float = 0.0015
    bounce_sigma_m: float = 0.0
    # the field's side slope (positive = right side down): the outlets, spread along the
    # tilted toolbar, sit r·cos(roll) to the side of the ground point below the antenna
    roll_deg: float = 0.0

    @classmethod
    def from_positioning(cls, section: PositioningSection, **kw: Any) -> PlanterModel:
        """The planter a daemon config describes (outlets, fall-time table, target spacing)."""
        base: dict[str, Any] = {
            "row_lateral_m": tuple(section.lateral_offsets()),
            "outlet_behind_antenna_m": section.outlet_behind_antenna_m,
            "fall_time_table": tuple(section.fall_time_table),
        }
        if section.target_spacing_m is not None:
            base["spacing_m"] = section.target_spacing_m
        base.update(kw)
        return cls(**base)

    def fall_time_s(self, speed_kmh: float) -> float:
        """Paper C's Table 1, linear between entries, flat beyond (written out here rather
        than imported from the position model, so ground truth is not the model checking
        itself)."""
        speeds = [v for v, _ in self.fall_time_table]
        i = bisect.bisect_left(speeds, speed_kmh)
        if i == 0:
            return self.fall_time_table[0][1] / 1000.0
        if i == len(speeds):
            return self.fall_time_table[-1][1] / 1000.0
        (v0, t0), (v1, t1) = self.fall_time_table[i - 1], self.fall_time_table[i]
        return (t0 + (t1 - t0) * (speed_kmh - v0) / (v1 - v0)) / 1000.0


def landing_point(
    pose_at: Callable[[float], Pose], model: PlanterModel, row: int, t_land: float
) -> tuple[float, float]:
    """The row outlet's true position at ``t_land`` (no bounce): behind the ground point
    below the antenna (the pose) along the heading, and to its right for a positive lateral
    offset."""
    p = pose_at(t_land)
    h = math.radians(p.heading_deg)
    back, right = model.outlet_behind_antenna_m, model.row_lateral_m[row - 1]
    if model.roll_deg:
        right *= math.cos(math.radians(model.roll_deg))
    east = p.east - back * math.sin(h) + right * math.cos(h)
    north = p.north - back * math.cos(h) - right * math.sin(h)
    return east, north


def plan_seeds(
    drive: Drive,
    model: PlanterModel | None = None,
    *,
    seed: int = 0,
    t_start: float = 0.0,
    t_end: float | None = None,
) -> list[SeedTruth]:
    """Every seed of every row over the drive, sorted by edge time."""
    model = model or PlanterModel()
    if model.spacing_m <= 0:
        raise ValueError(f"spacing_m must be > 0, got {model.spacing_m}")
    rng = random.Random(seed)
    end = drive.duration_s if t_end is None else min(t_end, drive.duration_s)
    rows = len(model.row_lateral_m)
    travelled = [0.0] * rows
    next_at = [rng.uniform(0.0, model.spacing_m) for _ in range(rows)]  # rows out of phase
    edges: list[tuple[float, int]] = []
    t = t_start
    prev = drive.pose_at(t)
    while t < end:
        t = min(t + PLAN_STEP_S, end)
        cur = drive.pose_at(t)
        step = math.hypot(cur.east - prev.east, cur.north - prev.north)
        sowing = not cur.raised and cur.speed_kmh >= MIN_SOWING_KMH
        if sowing:
            for r in range(rows):
                before = travelled[r]
                travelled[r] += step
                while travelled[r] >= next_at[r]:
                    frac = 0.0 if step == 0 else (next_at[r] - before) / step
                    t_edge = t - PLAN_STEP_S + max(0.0, min(1.0, frac)) * PLAN_STEP_S
                    next_at[r] += model.spacing_m * max(0.2, rng.gauss(1.0, model.spacing_cv))
                    if rng.random() < model.miss_prob:
                        continue  # the cell came round empty
                    edges.append((t_edge, r + 1))
                    if rng.random() < model.double_prob:
                        edges.append((t_edge + rng.uniform(*DOUBLE_GAP_S), r + 1))
                    if len(edges) > MAX_PLANNED_SEEDS:
                        raise ValueError("drive too long: more than MAX_PLANNED_SEEDS seeds")
        prev = cur
    edges.sort()
    out: list[SeedTruth] = []
    for t_edge, row in edges:
        speed = drive.pose_at(t_edge).speed_kmh
        fall = model.fall_time_s(speed) + rng.gauss(0.0, model.fall_time_sigma_s)
        t_land = t_edge + max(0.0, fall)
        if t_land > drive.duration_s:
            continue  # the drive ends while it falls: its landing point is undefined
        east, north = landing_point(drive.pose_at, model, row, t_land)
        if model.bounce_sigma_m > 0:
            # seeds roll on along the furrow, i.e. along the direction of travel
            h = math.radians(drive.pose_at(t_land).heading_deg)
            b = rng.gauss(0.0, model.bounce_sigma_m)
            east, north = east + b * math.sin(h), north + b * math.cos(h)
        out.append(SeedTruth(row, t_edge, t_land, east, north))
    return out


@dataclass
class SeedTubeEmulator(StartClose):
    """Writes a seed plan to a pty in real time; ``truth`` lists the seeds actually written.

    ``model`` may be a daemon's ``PositioningSection``: the planter it describes is used.
    Pass the run's shared ``t0_mono`` so seeds and GNSS share one time line.
    """

    drive: Drive
    model: PlanterModel | PositioningSection = field(default_factory=PlanterModel)
    t0_mono: float | None = None
    seed: int = 0
    t_end: float | None = None
    clock: Callable[[], float] = time.monotonic
    truth: list[SeedTruth] = field(default_factory=list, init=False)
    late_writes: int = field(default=0, init=False)
    # rows whose seeds are not sent while listed (a blocked tube, a dead sensor): change it
    # while running; their planned seeds are skipped, not delayed, and are not in ``truth``
    silent_rows: set[int] = field(default_factory=set, init=False)
    _pair: PtyPair | None = field(default=None, init=False, repr=False)
    _task: asyncio.Task[None] | None = field(default=None, init=False, repr=False)
    _plan: list[SeedTruth] = field(default_factory=list, init=False, repr=False)

    async def start(self) -> None:
        if isinstance(self.model, PositioningSection):
            self.model = PlanterModel.from_positioning(self.model)
        self._plan = plan_seeds(self.drive, self.model, seed=self.seed, t_end=self.t_end)
        self._pair = PtyPair()
        if self.t0_mono is None:
            self.t0_mono = self.clock()
        self._task = asyncio.create_task(self._run(), name="seed-tube-emulator")

    async def close(self) -> None:
        await unplug(self._task, self._pair)
        self._task, self._pair = None, None

    @property
    def device_path(self) -> str:
        if self._pair is None:
            raise RuntimeError("seed tube emulator not started")
        return self._pair.device_path

    def inject(self, data: bytes) -> int:
        """Write ``data`` (line noise, junk) on the sensor line now, between the seeds; the
        bytes the pty took (a full buffer drops the rest, as a UART would)."""
        if self._pair is None:
            raise RuntimeError("seed tube emulator not started")
        try:
            return os.write(self._pair.master_fd, data)
        except OSError:
            return 0

    @property
    def planned(self) -> list[SeedTruth]:
        return list(self._plan)

    @property
    def done(self) -> bool:
        return self._task is not None and self._task.done()

    async def wait_done(self) -> None:
        """Return once every planned seed has been written."""
        if self._task is None:
            raise RuntimeError("seed tube emulator not started")
        await asyncio.shield(self._task)

    async def _run(self) -> None:
        assert self.t0_mono is not None and self._pair is not None
        for s in self._plan:
            delay = self.t0_mono + s.t_edge - self.clock()
            if delay > 0:
                await asyncio.sleep(delay)
                delay = self.t0_mono + s.t_edge - self.clock()
            if delay < -LATE_WRITE_S:
                self.late_writes += 1  # starved box: the edge goes out late, still goes out
            if s.row in self.silent_rows:
                continue
            line = encode_seed_line(s.row)
            written = 0
            with contextlib.suppress(BlockingIOError, OSError):
                written = os.write(self._pair.master_fd, line)
            # a full line buffer (a reader starved as long as the writer) drops the line as a
            # UART would: that seed was never told of, so it is no one's truth
            if written == len(line):
                self.truth.append(s if delay >= -LATE_WRITE_S else self._sent_late(s, -delay))
            if delay < -LATE_WRITE_S:
                await asyncio.sleep(0)  # catching up: let a reader on this loop drain the line

    def _sent_late(self, s: SeedTruth, late_s: float) -> SeedTruth:
        """The seed as the line told of it: edge and landing ``late_s`` later, its landing
        point (bounce kept) moved as far as the outlet moved meanwhile."""
        assert isinstance(self.model, PlanterModel)
        t_land = s.t_land + late_s
        if t_land > self.drive.duration_s:  # no pose to move it to: the plan's place
            return replace(s, t_edge=s.t_edge + late_s, t_land=t_land, late_s=late_s)
        e0, n0 = landing_point(self.drive.pose_at, self.model, s.row, s.t_land)
        e1, n1 = landing_point(self.drive.pose_at, self.model, s.row, t_land)
        return SeedTruth(s.row, s.t_edge + late_s, t_land, s.east + e1 - e0,
                         s.north + n1 - n0, late_s)
