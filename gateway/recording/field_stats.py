"""What ``sowgate report`` says about a stretch of stored seed records, computed streaming.

The record store is read a chunk at a time (``RecordStore.query_seed_rows``); every figure
here is an exact sum over all records in the window, held in accumulators whose size does not
grow with the number of records (per row, per second of driving, per speed class, per map
cell), so a day of a 48-row planter (~70 M records) fits in a few tens of MB. The spacing
quality per row comes from ``RowQualityAccumulators``, the very accumulators ``sowgate
export`` uses, so the two commands give the same numbers for the same records.

Two passes: ``FieldStats`` first (counts, quality, rate, speed, bounds), then ``SeedMap``, which
needs the bounds and each row's reference spacing to place and classify the seeds.

What the store has, and so what is used: each seed's time, row, position, fix, speed,
extrapolation flag and spacing to the previous seed of its row. The applied *rate* is not
stored (the controller's commanded and metered rates live in its state, published on MQTT but
not kept), so the applied rate here is the sown population measured by the seed sensors:
seeds per metre of row (spacings counted over their summed length) over the row spacing,
in seeds/ha, and in kg/ha when a thousand-seed mass is given.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from gateway.recording.export import RowQualityAccumulators
from gateway.recording.spacing_quality import MISS_LIMIT, MULTIPLE_LIMIT, SpacingQuality
from gateway.recording.store import STORED_SEED_COLUMNS, StoredSeedRow

_US, _ROW, _LAT, _LON = (STORED_SEED_COLUMNS.index(c) for c in ("utc_us", "row", "lat", "lon"))
_FIX, _SPEED, _EXTRAP, _SPACING = (
    STORED_SEED_COLUMNS.index(c) for c in ("fix", "speed_kmh", "extrapolated", "spacing_m")
)

MAX_ROW = 128
# The rate along the drive is summed per second of seeding; over a long window the bin
# widens so there are never more than this many bins (~2.4 MB per array).
MAX_TIME_BINS = 300_000
SPEED_BIN_KMH = 0.5
MAX_SPEED_KMH = 40.0
HIST_BINS = 160
# the spacing histograms span 0 .. HIST_SPAN x the target (or 0 .. HIST_SPAN_M without one)
HIST_SPAN = 3.0
HIST_SPAN_M = 1.0
# Above this many seeds the map is a raster of counts per cell (class by class) instead of a
# point per seed: a scatter of millions of points is slow to draw and unreadable anyway.
MAP_POINTS_MAX = 200_000
# Raster cells hold about this many seeds on average (so a cell's share of misses means
# something: with ~10 seeds a cell one miss is 10 %), but are never finer than
# MAP_CELLS_MAX nor coarser than MAP_CELLS_MIN along the longer side of the field.
MAP_SEEDS_PER_CELL = 150
MAP_CELLS_MAX = 800
MAP_CELLS_MIN = 60
M_PER_DEG_LAT = 111_132.954  # mean metres per degree of latitude (local equirectangular)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

# seed classes on the map: by the spacing to the previous seed of the same row
GOOD, MULTIPLE, MISS, UNRATED = 0, 1, 2, 3
CLASS_NAMES = ("good (single)", "multiple", "miss", "no spacing")


def _columns(chunk: Sequence[StoredSeedRow]) -> list[tuple[object, ...]]:
    return list(zip(*chunk, strict=True))


@dataclass
class FieldSummary:
    """Everything the report prints and draws except the map (see ``FieldStats``)."""

    seeds: int
    first_us: int
    last_us: int
    seeding_s: float  # seconds in which seeds fell (time bins with seeds x bin width)
    seeds_by_row: dict[int, int]
    quality: dict[int, SpacingQuality]
    x_ref_m: float | None  # the configured target spacing
    row_spacing_m: float
    sown_length_m: float  # summed spacings over all rows: the length of row sown
    area_ha: float
    fixes: dict[str, int]
    extrapolated: int
    bounds: tuple[float, float, float, float]  # lat_min, lat_max, lon_min, lon_max
    speed_mean_kmh: float
    time_bin_s: float
    # per time bin with seeds: start (us), seeds, spacing count, spacing sum (m), speed sum
    drive: dict[str, F64] = field(repr=False)
    # per speed class: lower edge (km/h), spacing count, spacing sum (m)
    by_speed: dict[str, F64] = field(repr=False)
    hist_edges_m: F64 = field(repr=False)
    hist_by_row: dict[int, I64] = field(repr=False)

    @property
    def rtk_fixed_share(self) -> float:
        return self.fixes.get("rtk_fixed", 0) / self.seeds if self.seeds else 0.0

    @property
    def extrapolated_share(self) -> float:
        return self.extrapolated / self.seeds if self.seeds else 0.0

    def population_per_ha(self, count: F64 | float, length_m: F64 | float) -> F64:
        """Seeds/ha from spacings counted over their summed length (NaN where none)."""
        c = np.asarray(count, dtype=float)
        s = np.asarray(length_m, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(s > 0, 1e4 * c / (s * self.row_spacing_m), np.nan)

    @property
    def target_population_per_ha(self) -> float | None:
        if self.x_ref_m is None:
            return None
        return 1e4 / (self.x_ref_m * self.row_spacing_m)

    @property
    def population_mean_per_ha(self) -> float | None:
        n = sum(q.n for q in self.quality.values())
        if n == 0 or self.sown_length_m <= 0:
            return None
        return float(self.population_per_ha(n, self.sown_length_m))


class FieldStats:
    """Pass one: exact streaming sums over the records of the window."""

    def __init__(
        self,
        x_ref_m: float | None,
        row_spacing_m: float,
        span_us: tuple[int, int],
    ) -> None:
        self.x_ref = x_ref_m
        self.row_spacing_m = row_spacing_m
        self.quality = RowQualityAccumulators(x_ref_m)
        self.n = 0
        self.first_us = 2**63 - 1
        self.last_us = -(2**63)
        self.t0 = span_us[0]
        span_s = max(1.0, (span_us[1] - span_us[0]) / 1e6 + 1)
        self.bin_us = max(1_000_000, math.ceil(span_s / MAX_TIME_BINS) * 1_000_000)
        nbins = int((span_us[1] - span_us[0]) // self.bin_us) + 1
        self.t_seeds = np.zeros(nbins, np.int64)
        self.t_sp_n = np.zeros(nbins, np.int64)
        self.t_sp_sum = np.zeros(nbins)
        self.t_speed_sum = np.zeros(nbins)
        nspeed = int(MAX_SPEED_KMH / SPEED_BIN_KMH) + 1
        self.v_sp_n = np.zeros(nspeed, np.int64)
        self.v_sp_sum = np.zeros(nspeed)
        self.row_seeds = np.zeros(MAX_ROW + 1, np.int64)
        top = HIST_SPAN * x_ref_m if x_ref_m is not None else HIST_SPAN_M
        self.hist_edges = np.linspace(0.0, top, HIST_BINS + 1)
        self.hist = np.zeros((MAX_ROW + 1, HIST_BINS + 1), np.int64)  # last bin: above top
        self.fixes: Counter[str] = Counter()
        self.extrapolated = 0
        self.sown_length = 0.0
        self.speed_sum = 0.0
        self.lat_min = self.lon_min = math.inf
        self.lat_max = self.lon_max = -math.inf

    def add_rows(self, chunk: Sequence[StoredSeedRow]) -> None:
        if not chunk:
            return
        self.quality.add_rows(chunk)
        cols = _columns(chunk)
        us = np.array(cols[_US], dtype=np.int64)
        row = np.array(cols[_ROW], dtype=np.int64)
        lat = np.array(cols[_LAT], dtype=float)
        lon = np.array(cols[_LON], dtype=float)
        speed = np.array(cols[_SPEED], dtype=float)
        spacing = np.array(cols[_SPACING], dtype=float)  # None -> NaN
        self.n += len(chunk)
        self.first_us = min(self.first_us, int(us.min()))
        self.last_us = max(self.last_us, int(us.max()))
        self.fixes.update(cols[_FIX])  # type: ignore[arg-type]
        self.extrapolated += int(np.count_nonzero(np.array(cols[_EXTRAP], dtype=bool)))
        self.speed_sum += float(speed.sum())
        self.lat_min = min(self.lat_min, float(lat.min()))
        self.lat_max = max(self.lat_max, float(lat.max()))
        self.lon_min = min(self.lon_min, float(lon.min()))
        self.lon_max = max(self.lon_max, float(lon.max()))
        self.row_seeds += np.bincount(row, minlength=MAX_ROW + 1)
        nb = self.t_seeds.size
        tb = np.clip((us - self.t0) // self.bin_us, 0, nb - 1)
        self.t_seeds += np.bincount(tb, minlength=nb)
        self.t_speed_sum += np.bincount(tb, weights=speed, minlength=nb)
        has = ~np.isnan(spacing)
        sp, tb_sp, row_sp = spacing[has], tb[has], row[has]
        self.sown_length += float(sp.sum())
        self.t_sp_n += np.bincount(tb_sp, minlength=nb)
        self.t_sp_sum += np.bincount(tb_sp, weights=sp, minlength=nb)
        nv = self.v_sp_n.size
        vb = np.clip((speed[has] / SPEED_BIN_KMH).astype(np.int64), 0, nv - 1)
        self.v_sp_n += np.bincount(vb, minlength=nv)
        self.v_sp_sum += np.bincount(vb, weights=sp, minlength=nv)
        top = self.hist_edges[-1]
        hb = np.minimum((sp / top * HIST_BINS).astype(np.int64), HIST_BINS)
        width = HIST_BINS + 1
        self.hist += np.bincount(row_sp * width + hb, minlength=self.hist.size).reshape(
            self.hist.shape
        )

    def result(self) -> FieldSummary:
        used = np.nonzero(self.t_seeds)[0]
        quality = self.quality.result()
        seen = [int(r) for r in np.nonzero(self.row_seeds)[0]]
        return FieldSummary(
            seeds=self.n,
            first_us=self.first_us,
            last_us=self.last_us,
            seeding_s=used.size * self.bin_us / 1e6,
            seeds_by_row={r: int(self.row_seeds[r]) for r in seen},
            quality=quality,
            x_ref_m=self.x_ref,
            row_spacing_m=self.row_spacing_m,
            sown_length_m=self.sown_length,
            area_ha=self.sown_length * self.row_spacing_m / 1e4,
            fixes=dict(self.fixes.most_common()),
            extrapolated=self.extrapolated,
            bounds=(self.lat_min, self.lat_max, self.lon_min, self.lon_max),
            speed_mean_kmh=self.speed_sum / self.n if self.n else 0.0,
            time_bin_s=self.bin_us / 1e6,
            drive={
                "start_us": (self.t0 + used * self.bin_us).astype(float),
                "seeds": self.t_seeds[used].astype(float),
                "sp_n": self.t_sp_n[used].astype(float),
                "sp_sum": self.t_sp_sum[used],
                "speed_sum": self.t_speed_sum[used],
            },
            by_speed={
                "kmh": np.arange(self.v_sp_n.size, dtype=np.float64) * SPEED_BIN_KMH,
                "sp_n": self.v_sp_n.astype(float),
                "sp_sum": self.v_sp_sum,
            },
            hist_edges_m=self.hist_edges,
            hist_by_row={r: self.hist[r].copy() for r in seen},
        )


@dataclass
class MapResult:
    """Either every seed (``points``: x, y in metres and class) or counts per raster cell."""

    origin: tuple[float, float]  # lat, lon of the local frame's origin (the field's centre)
    extent_m: tuple[float, float, float, float]  # x_min, x_max, y_min, y_max
    class_counts: tuple[int, int, int, int]
    points: tuple[F64, F64, npt.NDArray[np.int8]] | None = None
    raster: npt.NDArray[np.int64] | None = None  # (4 classes, ny, nx)


class SeedMap:
    """Pass two: each seed placed in a local metric frame and classed by its spacing against
    its row's reference (the quality's ``x_ref_m``: the target, or the row's median).

    Up to ``MAP_POINTS_MAX`` seeds (known from pass one) every seed is kept; above it the seeds
    are counted per cell of a raster (about ``MAP_SEEDS_PER_CELL`` seeds a cell), one layer
    per class.
    """

    def __init__(
        self,
        summary: FieldSummary,
        max_points: int = MAP_POINTS_MAX,
    ) -> None:
        lat_min, lat_max, lon_min, lon_max = summary.bounds
        self.lat0 = (lat_min + lat_max) / 2
        self.lon0 = (lon_min + lon_max) / 2
        self.kx = M_PER_DEG_LAT * math.cos(math.radians(self.lat0))
        x0, x1 = (lon_min - self.lon0) * self.kx, (lon_max - self.lon0) * self.kx
        y0, y1 = (lat_min - self.lat0) * M_PER_DEG_LAT, (lat_max - self.lat0) * M_PER_DEG_LAT
        self.extent = (x0, x1, y0, y1)
        self.ref = np.full(MAX_ROW + 1, np.nan)
        for row, q in summary.quality.items():
            if q.x_ref_m is not None:
                self.ref[row] = q.x_ref_m
        self.counts = np.zeros(4, np.int64)
        self.keep_points = summary.seeds <= max_points
        self._xs: list[F64] = []
        self._ys: list[F64] = []
        self._cs: list[npt.NDArray[np.int8]] = []
        size = max(x1 - x0, y1 - y0, 1e-3)
        # seeds per square metre of the sown strips
        density = summary.seeds / max(summary.area_ha * 1e4, 1.0)
        cell = math.sqrt(MAP_SEEDS_PER_CELL / max(density, 1e-9))
        self.cell = min(max(cell, size / MAP_CELLS_MAX), size / MAP_CELLS_MIN)
        self.nx = max(1, math.ceil((x1 - x0) / self.cell) + 1)
        self.ny = max(1, math.ceil((y1 - y0) / self.cell) + 1)
        self.grid = (
            None if self.keep_points else np.zeros((4, self.ny * self.nx), np.int64)
        )

    def add_rows(self, chunk: Sequence[StoredSeedRow]) -> None:
        if not chunk:
            return
        cols = _columns(chunk)
        row = np.array(cols[_ROW], dtype=np.int64)
        x = (np.array(cols[_LON], dtype=float) - self.lon0) * self.kx
        y = (np.array(cols[_LAT], dtype=float) - self.lat0) * M_PER_DEG_LAT
        cls = seed_classes(np.array(cols[_SPACING], dtype=float), self.ref[row])
        self.counts += np.bincount(cls, minlength=4)
        if self.grid is None:
            self._xs.append(x)
            self._ys.append(y)
            self._cs.append(cls.astype(np.int8))
            return
        ix = np.clip(((x - self.extent[0]) / self.cell).astype(np.int64), 0, self.nx - 1)
        iy = np.clip(((y - self.extent[2]) / self.cell).astype(np.int64), 0, self.ny - 1)
        flat = iy * self.nx + ix
        for c in range(4):
            sel = cls == c
            if sel.any():
                self.grid[c] += np.bincount(flat[sel], minlength=self.grid.shape[1])

    def result(self) -> MapResult:
        counts = tuple(int(c) for c in self.counts)
        out = MapResult(
            origin=(self.lat0, self.lon0),
            extent_m=self.extent,
            class_counts=(counts[0], counts[1], counts[2], counts[3]),
        )
        if self.grid is None:
            empty = np.zeros(0)
            out.points = (
                np.concatenate(self._xs) if self._xs else empty,
                np.concatenate(self._ys) if self._ys else empty,
                np.concatenate(self._cs) if self._cs else np.zeros(0, np.int8),
            )
        else:
            out.raster = self.grid.reshape(4, self.ny, self.nx)
        return out


def seed_classes(spacing: F64, ref: F64) -> npt.NDArray[np.int64]:
    """Class of each seed (ISO 7256-1 limits, as ``RowQualityAccumulator``): a spacing
    ``<= 0.5 x_ref`` is a multiple, ``> 1.5 x_ref`` a miss; no spacing or no reference:
    unrated."""
    cls = np.full(spacing.shape, UNRATED, np.int64)
    ok = ~np.isnan(spacing) & ~np.isnan(ref)
    sp, r = spacing[ok], ref[ok]
    c = np.full(sp.shape, GOOD, np.int64)
    c[sp <= MULTIPLE_LIMIT * r] = MULTIPLE
    c[sp > MISS_LIMIT * r] = MISS
    cls[ok] = c
    return cls


AlarmEnd = Literal["cleared", "stop", "open"]


class AlarmInterval(NamedTuple):
    """One alarm period: raised at ``from_us``, ended at ``to_us`` by ``end``: "cleared",
    "stop" (still active when the daemon stopped: the period ends at that stop), or "open"
    (still active at the end of the window)."""

    code: str
    severity: str
    from_us: int
    to_us: int
    end: AlarmEnd

    @property
    def cleared(self) -> bool:
        return self.end == "cleared"


def alarm_intervals(
    events: Sequence[tuple[int, str, bool, str]],
    start_us: int,
    end_us: int,
    runs: Sequence[tuple[int, int | None]] = (),
) -> list[AlarmInterval]:
    """Raise/clear events (utc_us, code, active, severity) in time order paired into
    intervals. A clear with no raise in the window was raised before it (starts at
    ``start_us``, or at the start of its daemon run if later); a raise never cleared lasts
    to the first daemon stop after it (``runs``: (start_us, stop_us or None) of each run, see
    ``gateway.recording.runs``), else to ``end_us``: an alarm active when the daemon stopped
    is not drawn across the runs that followed.
    """
    stops = sorted(stop for _start, stop in runs if stop is not None)
    starts = sorted(start for start, _stop in runs)
    open_at: dict[str, tuple[int, str]] = {}
    out: list[AlarmInterval] = []
    next_stop = 0

    def close_open_at(stop_us: int) -> None:
        for code, (began, sev) in open_at.items():
            out.append(AlarmInterval(code, sev, began, max(stop_us, began), "stop"))
        open_at.clear()

    for us, code, active, severity in events:
        while next_stop < len(stops) and stops[next_stop] < us:
            close_open_at(stops[next_stop])
            next_stop += 1
        if active:
            open_at.setdefault(code, (us, severity))
        else:
            k = bisect.bisect_right(starts, us)
            run_start = starts[k - 1] if k else start_us
            began, sev = open_at.pop(code, (max(start_us, run_start), severity))
            out.append(AlarmInterval(code, sev, began, us, "cleared"))
    if open_at and next_stop < len(stops):
        close_open_at(stops[next_stop])
    for code, (began, sev) in open_at.items():
        out.append(AlarmInterval(code, sev, began, max(end_us, began), "open"))
    out.sort(key=lambda i: (i.from_us, i.code))
    return out
