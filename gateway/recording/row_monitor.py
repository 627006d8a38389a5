"""The row monitor: which seed rows are blocked, skipping or chattering, and whether all are
silent while the meter turns. Plain values in, plain values out: no clock, no I/O.

A blocked seed tube is the first thing a seed monitor exists to catch. Each row's seeds are
counted over a sliding window of the time the machine was working and judged against a
reference: the median row over the same window (on a machine of three rows or more, so one
row is judged against its neighbours and a change of rate or speed moves them all alike), or
the seeds the configured spacing asks for at the distance travelled (one or two rows, where no
median exists; ``positioning.target_spacing_m``).

- **blocked**: the row delivered at most ``blocked_pct`` % of the reference
- **skipping**: below ``skip_pct`` % of it (a worn disc, a partly blocked tube)
- **chattering**: the row's sensor sends edges faster than a row can drop seeds
  (``gateway.recording.seed_plausibility``); its edges are not seeds, so it is left out of
  the reference and not judged on its count
- **all rows silent**: no row delivered a seed over the window while the meter turned

Nuisance alarms at headland turns and low speed are what makes a farmer switch a monitor off,
so nothing is judged unless the machine is working (lowered, seeding) above
``min_speed_kmh``; the window restarts whenever it is not. A row is judged only over a window
of at least ``delay_s`` seconds of working in which the reference reached
``min_expected_seeds`` (so a low seed rate needs a longer window, up to ``MAX_WINDOW_S``). A
verdict then holds until a later window says otherwise: a blocked row stays blocked through
the headland turn until the next pass shows its seeds.
"""

from __future__ import annotations

import statistics
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Literal

RowVerdict = Literal["ok", "blocked", "skipping", "chattering", "unknown"]
# The longest window a verdict looks back over (a slow seed rate waits for its evidence up to
# this long); samples older than this are forgotten.
MAX_WINDOW_S = 60.0
KMH_PER_MS = 3.6


@dataclass(frozen=True, slots=True)
class RowMonitorLimits:
    """The ``[row_monitor]`` thresholds (``gateway.config.recording.RowMonitorSection``)."""

    delay_s: float = 5.0
    min_speed_kmh: float = 2.0
    min_expected_seeds: int = 20
    blocked_pct: float = 10.0
    skip_pct: float = 70.0


@dataclass(frozen=True, slots=True)
class RowReport:
    """One row as last judged: its verdict and, over the window judged, its seeds a second
    and its share of the reference (None before a first verdict)."""

    verdict: RowVerdict
    seeds_per_s: float | None
    pct_of_reference: float | None


@dataclass(frozen=True, slots=True)
class RowMonitorReport:
    """The monitor at one moment (``RowMonitor.report``)."""

    judging: bool  # working above min_speed_kmh now
    all_rows_silent: bool
    expected_seeds_per_s: float | None  # per row at the current speed (spacing configured)
    window_s: float | None  # the window of the last verdict
    rows: Mapping[int, RowReport]


@dataclass(slots=True)
class _Sample:
    t: float
    distance_m: float  # travelled while judging, cumulative
    seeds: tuple[int, ...]  # per row (index row-1), cumulative


def reference_count(
    counts: Mapping[int, int], expected: float | None, excluded: Iterable[int] = ()
) -> float | None:
    """What a healthy row delivers over the window: the median of the rows not excluded
    (three or more of them), else the count the spacing asks for (None if not configured)."""
    left = set(excluded)
    judged = [n for row, n in counts.items() if row not in left]
    if len(judged) >= 3:
        return float(statistics.median(judged))
    return expected


def verdict(count: int, reference: float, limits: RowMonitorLimits) -> RowVerdict:
    """A row that delivered ``count`` where a healthy one delivers ``reference``."""
    if count <= limits.blocked_pct / 100.0 * reference:
        return "blocked"
    if count < limits.skip_pct / 100.0 * reference:
        return "skipping"
    return "ok"


@dataclass
class RowMonitor:
    """Fed on every tick with what the machine does and the seeds counted per row since
    start (``update``); ``report`` says what it concluded."""

    rows: int
    limits: RowMonitorLimits = field(default_factory=RowMonitorLimits)
    target_spacing_m: float | None = None
    _samples: deque[_Sample] = field(default_factory=deque, init=False)
    _last_t: float | None = field(default=None, init=False)
    _distance_m: float = field(default=0.0, init=False)
    _verdicts: dict[int, RowReport] = field(default_factory=dict, init=False)
    _all_silent: bool = field(default=False, init=False)
    _judging: bool = field(default=False, init=False)
    _speed_kmh: float | None = field(default=None, init=False)
    _window_s: float | None = field(default=None, init=False)
    _chattering: set[int] = field(default_factory=set, init=False)
    _meter_since: float | None = field(default=None, init=False)  # turning, working, since
    _chattered_at: dict[int, float] = field(default_factory=dict, init=False)  # row -> last

    def __post_init__(self) -> None:
        if self.rows < 1:
            raise ValueError(f"rows must be >= 1, got {self.rows}")
        self._verdicts = {r: RowReport("unknown", None, None) for r in range(1, self.rows + 1)}

    def update(
        self,
        t: float,
        *,
        working: bool,
        speed_kmh: float | None,
        meter_turning: bool,
        seeds: Mapping[int, int],
        chattering: Iterable[int] = (),
    ) -> None:
        """One tick at ``t`` (s, monotonic): ``seeds`` is each row's count of seeds since
        start (edges that passed the plausibility check), ``chattering`` the rows whose edges
        are being dropped as implausible now."""
        speed = speed_kmh if speed_kmh is not None else 0.0
        judging = working and speed >= self.limits.min_speed_kmh
        self._judging, self._speed_kmh = judging, speed_kmh
        self._chattering = {r for r in chattering if 1 <= r <= self.rows}
        for row in self._chattering:
            self._chattered_at[row] = t
        if not judging:
            self._samples.clear()  # headland, standing, slow: the window starts again
            self._last_t = self._meter_since = None
            return
        if not meter_turning:
            self._meter_since = None
        elif self._meter_since is None:
            self._meter_since = t
        if self._last_t is not None and t > self._last_t:
            self._distance_m += speed / KMH_PER_MS * (t - self._last_t)
        self._last_t = t
        counts = tuple(seeds.get(r, 0) for r in range(1, self.rows + 1))
        self._samples.append(_Sample(t, self._distance_m, counts))
        while self._samples and self._samples[0].t < t - MAX_WINDOW_S:
            self._samples.popleft()
        self._judge_silence(t)
        self._judge_rows(t)

    def _window(self, start: _Sample) -> tuple[dict[int, int], float | None]:
        """Each row's seeds from ``start`` to the newest sample, and the count the spacing
        asks for over the distance travelled meanwhile."""
        newest = self._samples[-1]
        counts = {r: newest.seeds[r - 1] - start.seeds[r - 1] for r in range(1, self.rows + 1)}
        return counts, self._expected(newest.distance_m - start.distance_m)

    def _judge_silence(self, t: float) -> None:
        """All rows silent: no seed at all over the last ``delay_s`` while the meter turned
        (and, with a spacing configured, the distance asked for ``min_expected_seeds``)."""
        samples = self._samples
        if len(samples) >= 2 and samples[-1].seeds != samples[-2].seeds:
            self._all_silent = False  # seeds are coming
        since = self._meter_since
        if since is None or t - since < self.limits.delay_s:
            return
        start = next((s for s in reversed(samples) if t - s.t >= self.limits.delay_s), None)
        if start is None:
            return
        counts, expected = self._window(start)
        if sum(counts.values()) == 0 and (
            expected is None or expected >= self.limits.min_expected_seeds
        ):
            self._all_silent = True

    def _judge_rows(self, t: float) -> None:
        """Each row against the reference, over the newest window that spans ``delay_s``
        and in which the reference reached ``min_expected_seeds``."""
        limits = self.limits
        for start in reversed(self._samples):
            span = t - start.t
            if span < limits.delay_s:
                continue
            counts, expected = self._window(start)
            # a row that chattered within the window had its edges (real seeds among them)
            # dropped: its count says nothing, so no verdict and no part in the reference
            unjudged = {r for r, at in self._chattered_at.items() if at >= start.t}
            reference = reference_count(counts, expected, unjudged)
            if reference is None or reference < limits.min_expected_seeds:
                continue  # not enough evidence yet: look further back
            self._window_s = span
            for row, n in counts.items():
                if row in unjudged:
                    continue
                self._verdicts[row] = RowReport(
                    verdict(n, reference, limits), n / span, 100.0 * n / reference
                )
            return

    def _expected(self, distance_m: float) -> float | None:
        if self.target_spacing_m is None:
            return None
        return distance_m / self.target_spacing_m

    def report(self) -> RowMonitorReport:
        speed = self._speed_kmh
        expected = None
        if self.target_spacing_m is not None and speed is not None and self._judging:
            expected = speed / KMH_PER_MS / self.target_spacing_m
        return RowMonitorReport(
            judging=self._judging,
            all_rows_silent=self._all_silent,
            expected_seeds_per_s=expected,
            window_s=self._window_s,
            rows={
                row: RowReport("chattering", r.seeds_per_s, r.pct_of_reference)
                if row in self._chattering else r
                for row, r in self._verdicts.items()
            },
        )
