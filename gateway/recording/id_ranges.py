"""Which record ids the broker has acknowledged, kept as a few id ranges instead of a flag per row.

Records are published in id order, 500 to a batch, and PUBACKs come back nearly in order, so the
acknowledged ids are almost always one run ``1..W`` plus a few runs for the batches still in
flight. Marking a batch is then a merge of one range (not an UPDATE of 500 rows, which rewrote
every page a moment after it was written), and the set stays a handful of rows on disk.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Iterable, Iterator


class IdRanges:
    """Sorted, disjoint, non-adjacent closed ranges ``[lo, hi]`` of positive ids."""

    def __init__(self, ranges: Iterable[tuple[int, int]] = ()) -> None:
        self._lo: list[int] = []
        self._hi: list[int] = []
        for lo, hi in ranges:
            self.add(lo, hi)

    def __len__(self) -> int:
        return len(self._lo)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        return zip(self._lo, self._hi, strict=True)

    def __contains__(self, i: object) -> bool:
        if not isinstance(i, int):
            return False
        k = bisect_right(self._lo, i) - 1
        return k >= 0 and i <= self._hi[k]

    def add(self, lo: int, hi: int) -> int:
        """Cover ``lo..hi``; returns how many of those ids were not covered before."""
        if hi < lo:
            return 0
        los, his = self._lo, self._hi
        # the ranges that overlap or touch [lo, hi]: indexes k .. end-1
        k = bisect_right(los, lo - 1)
        if k > 0 and his[k - 1] >= lo - 1:
            k -= 1
        end = bisect_right(los, hi + 1)
        before = sum(max(0, min(his[j], hi) - max(los[j], lo) + 1) for j in range(k, end))
        new = hi - lo + 1 - before
        if k < end:
            lo, hi = min(lo, los[k]), max(hi, his[end - 1])
        los[k:end] = [lo]
        his[k:end] = [hi]
        return new

    def add_ids(self, ids: Iterable[int]) -> int:
        """Cover these ids (any order, duplicates allowed); returns how many were new."""
        unique = set(ids)
        if not unique:
            return 0
        lo, hi = min(unique), max(unique)
        if hi - lo + 1 == len(unique):  # one run, as a published batch is: no loop per id
            return self.add(lo, hi)
        new = 0
        run: list[int] | None = None
        for i in sorted(unique):
            if run is not None and i == run[1] + 1:
                run[1] = i
                continue
            if run is not None:
                new += self.add(run[0], run[1])
            run = [i, i]
        if run is not None:
            new += self.add(run[0], run[1])
        return new

    def through(self) -> int:
        """The largest ``w`` with every id ``1..w`` covered (0 if id 1 is not)."""
        return self._hi[0] if self._lo and self._lo[0] <= 1 else 0

    def gaps(self, after: int, ceiling: int) -> Iterator[tuple[int, int]]:
        """The uncovered runs of ids in ``after+1 .. ceiling``, in order."""
        lo = after + 1
        k = bisect_right(self._lo, lo) - 1
        if k >= 0 and self._hi[k] >= lo:
            lo = self._hi[k] + 1
        k += 1
        while lo <= ceiling:
            if k < len(self._lo) and self._lo[k] <= ceiling:
                if self._lo[k] > lo:
                    yield lo, self._lo[k] - 1
                lo = self._hi[k] + 1
                k += 1
            else:
                yield lo, ceiling
                return
