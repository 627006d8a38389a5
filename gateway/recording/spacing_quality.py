"""Per-row seed spacing quality after ISO 7256-1 and Kachman & Smith (1995).

With ``x_ref`` the theoretical (target) spacing and N the number of measured spacings:

- multiples index  M = 100 · #(x ≤ 0.5·x_ref) / N — two seeds where one was meant;
- miss index       Q = 100 · #(x > 1.5·x_ref) / N — a seed missing;
- quality of feed  A = 100 − M − Q — the share of "singles";
- precision        C = 100 · s₂ / x_ref, s₂ the sample SD of the singles (0.5 < x ≤ 1.5·x_ref).

Precision divides by ``x_ref`` (not by the singles' mean) as Kachman & Smith do, so it stays
comparable across fields sown at the same target; it is the CV of the singles relative to the
target spacing. When no target is configured, ``x_ref`` is the median of the spacings seen
(robust against the multiples and misses themselves), computed over a bounded window.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Iterable
from dataclasses import asdict, dataclass

MULTIPLE_LIMIT = 0.5
MISS_LIMIT = 1.5
# Spacings remembered per row when x_ref has to be estimated (about 4 min at 12 km/h, 20 cm).
QUALITY_WINDOW = 1000


@dataclass(frozen=True)
class SpacingQuality:
    """Indices in percent; ``None`` where there is nothing to compute them from."""

    n: int
    x_ref_m: float | None
    multiples_index: float | None
    miss_index: float | None
    quality_of_feed_index: float | None
    precision: float | None
    mean_spacing_m: float | None

    def as_dict(self) -> dict[str, float | int | None]:
        return asdict(self)


EMPTY = SpacingQuality(0, None, None, None, None, None, None)


def spacing_quality(spacings: Iterable[float], x_ref: float | None = None) -> SpacingQuality:
    """Indices over a list of spacings (metres); ``x_ref`` defaults to their median."""
    xs = [float(x) for x in spacings]
    if not xs:
        return SpacingQuality(0, x_ref, None, None, None, None, None)
    ref = statistics.median(xs) if x_ref is None else x_ref
    if ref <= 0:
        raise ValueError(f"x_ref must be > 0, got {ref}")
    acc = RowQualityAccumulator(ref)
    for x in xs:
        acc.add(x)
    return acc.result()


class RowQualityAccumulator:
    """Streaming indices for one row: O(1) per spacing when ``x_ref`` is known."""

    def __init__(self, x_ref: float | None = None) -> None:
        if x_ref is not None and x_ref <= 0:
            raise ValueError(f"x_ref must be > 0, got {x_ref}")
        self.x_ref = x_ref
        self._window: deque[float] = deque(maxlen=QUALITY_WINDOW)
        self.n = 0
        self.multiples = 0
        self.misses = 0
        self._sum = 0.0
        # Welford over the singles
        self._singles = 0
        self._mean = 0.0
        self._m2 = 0.0

    def add(self, spacing_m: float) -> None:
        if not math.isfinite(spacing_m) or spacing_m < 0:
            raise ValueError(f"spacing must be a finite distance >= 0, got {spacing_m}")
        if self.x_ref is None:
            self._window.append(spacing_m)
            return
        self.n += 1
        self._sum += spacing_m
        if spacing_m <= MULTIPLE_LIMIT * self.x_ref:
            self.multiples += 1
        elif spacing_m > MISS_LIMIT * self.x_ref:
            self.misses += 1
        else:
            self._singles += 1
            d = spacing_m - self._mean
            self._mean += d / self._singles
            self._m2 += d * (spacing_m - self._mean)

    def add_many(self, spacings: Iterable[float]) -> None:
        """``add`` for each spacing in turn (same state after, bit for bit), with the running
        sums kept in locals: the recorder feeds every seed through here, ~2 000 a second."""
        isfinite = math.isfinite
        if self.x_ref is None:  # the window of recent spacings (its median is the target)
            good: list[float] = []
            try:
                for x in spacings:
                    if not isfinite(x) or x < 0:
                        raise ValueError(f"spacing must be a finite distance >= 0, got {x}")
                    good.append(x)
            finally:
                self._window.extend(good)
            return
        multiple_at, miss_above = MULTIPLE_LIMIT * self.x_ref, MISS_LIMIT * self.x_ref
        n, total, multiples, misses = self.n, self._sum, self.multiples, self.misses
        singles, mean, m2 = self._singles, self._mean, self._m2
        try:
            for x in spacings:
                if not isfinite(x) or x < 0:
                    raise ValueError(f"spacing must be a finite distance >= 0, got {x}")
                n += 1
                total += x
                if x <= multiple_at:
                    multiples += 1
                elif x > miss_above:
                    misses += 1
                else:
                    singles += 1
                    d = x - mean
                    mean += d / singles
                    m2 += d * (x - mean)
        finally:  # what was added before a bad value stays added, as with add()
            self.n, self._sum, self.multiples, self.misses = n, total, multiples, misses
            self._singles, self._mean, self._m2 = singles, mean, m2

    def result(self) -> SpacingQuality:
        if self.x_ref is None:
            if not self._window:
                return EMPTY
            median = statistics.median(self._window)
            if median <= 0:  # most seeds at one spot (a sensor flood): no spacing to rate
                return SpacingQuality(len(self._window), None, None, None, None, None, None)
            return spacing_quality(self._window, median)
        if self.n == 0:
            return SpacingQuality(0, self.x_ref, None, None, None, None, None)
        m = 100.0 * self.multiples / self.n
        q = 100.0 * self.misses / self.n
        precision = (
            100.0 * math.sqrt(self._m2 / (self._singles - 1)) / self.x_ref
            if self._singles >= 2
            else None
        )
        return SpacingQuality(
            n=self.n,
            x_ref_m=self.x_ref,
            multiples_index=m,
            miss_index=q,
            quality_of_feed_index=100.0 - m - q,
            precision=precision,
            mean_spacing_m=self._sum / self.n,
        )
