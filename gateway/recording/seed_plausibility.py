"""Seed edges a row cannot physically produce are counted, not stored as seeds.

A seed-tube module that floods its UART (200 000 valid ``D,1`` lines in one burst, seen in the
field), or a GPIO line picking up motor noise, delivers edges faster than any seed meter can
drop seeds. Stored as records, they would put thousands of phantom seeds on the as-planted map
and wreck every spacing statistic. So each row gets a limit, ``seed_sensors.
max_seeds_per_s_per_row`` (default and reasoning in ``gateway.config.recording``), and edges
beyond it are counted per row and dropped; ``RecordingHealth`` raises
``seed_sensors.implausible_rate`` while it happens.

The limit is a token bucket per row: it holds ``limit x WINDOW_S`` tokens, refills at the
limit, and each edge takes one; normal seeding (a fraction of the limit) never finds the
bucket short, however irregular its spacing. A row whose bucket runs dry is chattering, and
then none of its edges can be told from the noise: every edge of the batch that ran it dry is
dropped, and every later edge of that row until ``QUARANTINE_S`` after the last one that found
the bucket dry (the bucket keeps being charged meanwhile, so a row still chattering stays
quarantined). Keeping the bucket's worth of a chattering row, as this did before, stored about
``limit`` phantom seeds a second for as long as the chatter lasted (issue 20: a row sending
~2 300 lines a second put ~200 a second on the map). So over any interval of T seconds a row
stores at most ``limit x (T + WINDOW_S)`` edges, and a chattering one none. All times are the
edges' own stamps (host monotonic clock), so the check means the same whether the edges came
over a UART or with kernel timestamps from GPIO, and however late the recorder gets to them.

Cost: this runs on every batch of edges the recorder hands to the positioner (the edges
between two GNSS epochs, ~200 at 2 100 seeds/s), not per seed: one ``Counter`` over the
batch's rows (in C) and a few float operations per row present. Only a row that is over its
limit is walked edge by edge, to keep exactly the edges that fit.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

# The bucket holds this many seconds' worth of the limit: 100 edges at the default 200/s, more
# than any row drops in half a second (a 48-row planter at 16 km/h: 22), so a burst of chatter
# shorter than that is all a row can store before it is seen.
WINDOW_S = 0.5
# A row that ran its bucket dry is quarantined (every edge dropped and counted) until this
# long after the last edge that found it dry.
QUARANTINE_S = 2.0


class SeedRatePlausibility:
    """Per-row rate limit on seed edges: ``filter`` keeps the plausible ones, counts the rest."""

    def __init__(self, max_per_s: float, window_s: float = WINDOW_S) -> None:
        if max_per_s <= 0 or window_s <= 0:
            raise ValueError(f"max_per_s and window_s must be > 0, got {max_per_s}, {window_s}")
        self.max_per_s = max_per_s
        self.capacity = max_per_s * window_s
        self._tokens: dict[int, float] = {}  # row -> tokens at self._at[row]
        self._at: dict[int, float] = {}
        self.implausible: dict[int, int] = {}  # row -> edges dropped as implausible
        self.last_implausible_at: dict[int, float] = {}  # row -> stamp of the latest dropped
        self._quarantined_until: dict[int, float] = {}  # row -> end of its quarantine

    @property
    def implausible_total(self) -> int:
        return sum(self.implausible.values())

    def rows_implausible_since(self, t_mono: float) -> list[int]:
        """Rows that had an edge dropped at or after ``t_mono``, in row order."""
        return sorted(row for row, at in self.last_implausible_at.items() if at >= t_mono)

    def filter(
        self, rows: Sequence[int], times: Sequence[float]
    ) -> tuple[Sequence[int], Sequence[float]]:
        """The edges (parallel lists, in arrival order) that fit their row's limit.

        Returns the inputs themselves when every edge fits, the common case."""
        if not rows:
            return rows, times
        t_start, t_end = min(times), max(times)
        rate, capacity = self.max_per_s, self.capacity
        tokens, at, quarantined = self._tokens, self._at, self._quarantined_until
        over: list[tuple[int, float]] = []
        for row, count in Counter(rows).items():
            last = at.get(row)
            available = capacity if last is None else min(
                capacity, tokens[row] + rate * max(0.0, t_start - last)
            )
            if count <= available and quarantined.get(row, -1.0) <= t_start:
                # refilled once to the batch's end and charged for all its edges: never more
                # tokens than edge-by-edge accounting would leave
                tokens[row] = min(capacity, available + rate * (t_end - t_start)) - count
                at[row] = t_end
            else:
                over.append((row, available))
        if not over:
            return rows, times
        return self._drop_excess(rows, times, over, t_end)

    def _drop_excess(
        self,
        rows: Sequence[int],
        times: Sequence[float],
        over: list[tuple[int, float]],
        t_end: float,
    ) -> tuple[list[int], list[float]]:
        """Walk the rows over their limit (or quarantined) edge by edge: a row whose bucket
        runs dry in this batch loses all its edges of the batch, a quarantined row those
        before its quarantine ends; every dropped edge is counted."""
        rate, capacity = self.max_per_s, self.capacity
        dropped: set[int] = set()
        t_start = min(times)
        for row, available in over:
            level, prev = available, t_start  # ``available`` is the row's level at t_start
            until = self._quarantined_until.get(row, -1.0)
            mine = [i for i, r in enumerate(rows) if r == row]
            dried = False
            for i in mine:
                t = times[i]
                if t > prev:
                    level = min(capacity, level + rate * (t - prev))
                    prev = t
                if level >= 1.0:
                    level -= 1.0
                else:
                    dried = True
                    until = max(until, t + QUARANTINE_S)
            self._tokens[row] = min(capacity, level + rate * (t_end - prev))
            self._at[row] = t_end
            self._quarantined_until[row] = until
            lost = mine if dried else [i for i in mine if times[i] < until]
            if lost:
                dropped.update(lost)
                self.implausible[row] = self.implausible.get(row, 0) + len(lost)
                latest = max(times[i] for i in lost)
                self.last_implausible_at[row] = max(self.last_implausible_at.get(row, latest),
                                                    latest)
        kept = [i for i in range(len(rows)) if i not in dropped]
        return [rows[i] for i in kept], [times[i] for i in kept]
