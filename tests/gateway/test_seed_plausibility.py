"""The per-row plausibility limit: impossible seed rates are counted, real seeding untouched."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.config.recording import DEFAULT_MAX_SEEDS_PER_S_PER_ROW
from gateway.seed_plausibility import WINDOW_S, SeedRatePlausibility


def _feed(
    limit: SeedRatePlausibility, edges: list[tuple[int, float]], batch_s: float = 0.1
) -> list[tuple[int, float]]:
    """Hand ``edges`` (sorted by time) over in batches as the recorder does, between epochs."""
    kept: list[tuple[int, float]] = []
    i = 0
    while i < len(edges):
        end = edges[i][1] + batch_s
        j = i
        while j < len(edges) and edges[j][1] < end:
            j += 1
        rows, times = limit.filter([r for r, _ in edges[i:j]], [t for _, t in edges[i:j]])
        kept += zip(rows, times, strict=True)
        i = j
    return kept


def _planter(rows: int, seeds_per_s_per_row: float, duration_s: float) -> list[tuple[int, float]]:
    rng = random.Random(3)
    edges = []
    for row in range(1, rows + 1):
        t = rng.random() / seeds_per_s_per_row
        while t < duration_s:
            edges.append((row, 100.0 + t))
            # irregular spacing as a real meter makes: misses, and doubles 2 ms apart
            gap = rng.choice([1.0, 1.0, 1.0, 2.0, 0.002 * seeds_per_s_per_row])
            t += gap / seeds_per_s_per_row * rng.uniform(0.8, 1.2)
    return sorted(edges, key=lambda e: e[1])


def test_a_48_row_planter_at_2100_seeds_per_second_is_untouched() -> None:
    limit = SeedRatePlausibility(DEFAULT_MAX_SEEDS_PER_S_PER_ROW)
    edges = _planter(48, 2100 / 48, 30.0)
    assert _feed(limit, edges) == edges
    assert limit.implausible_total == 0 and limit.rows_implausible_since(0.0) == []


def test_seeding_just_below_the_limit_keeps_every_seed() -> None:
    limit = SeedRatePlausibility(200.0)
    edges = [(1, 100.0 + k / 195.0) for k in range(195 * 20)]
    assert _feed(limit, edges) == edges


def test_a_burst_of_200000_edges_on_one_row_keeps_at_most_the_plausible_number() -> None:
    limit = SeedRatePlausibility(200.0)
    burst = [(1, 100.0 + k * 1e-6) for k in range(200_000)]  # 0.2 s
    neighbour = [(2, 100.0 + k / 40.0) for k in range(8)]
    edges = sorted(burst + neighbour, key=lambda e: e[1])
    kept = _feed(limit, edges)
    kept_row1 = [e for e in kept if e[0] == 1]
    assert len(kept_row1) <= 200.0 * (0.2 + WINDOW_S)
    assert len(kept_row1) >= 200  # the bucket's worth: a real seed in there is not lost
    assert [e for e in kept if e[0] == 2] == neighbour  # other rows unaffected
    assert limit.implausible == {1: 200_000 - len(kept_row1)}
    assert limit.rows_implausible_since(100.1) == [1]
    assert limit.rows_implausible_since(100.3) == []


def test_a_row_recovers_once_the_flood_stops() -> None:
    limit = SeedRatePlausibility(200.0)
    _feed(limit, [(1, 100.0 + k * 1e-5) for k in range(10_000)])
    after = [(1, 103.0 + k / 40.0) for k in range(80)]
    assert _feed(limit, after) == after


@settings(max_examples=100, deadline=None)
@given(
    gaps=st.lists(st.floats(0.0, 0.05), min_size=1, max_size=1500),
    batch_s=st.sampled_from([0.01, 0.1, 0.5]),
    window=st.floats(0.5, 5.0),
)
def test_no_interval_ever_keeps_more_than_the_limit_allows(
    gaps: list[float], batch_s: float, window: float
) -> None:
    limit = SeedRatePlausibility(100.0, window)
    t, edges = 50.0, []
    for gap in gaps:
        t += gap
        edges.append((1, t))
    kept = [tk for _, tk in _feed(limit, edges, batch_s)]
    assert limit.implausible_total == len(edges) - len(kept)
    for i, start in enumerate(kept):  # every interval that begins at a kept edge
        for j in range(i, len(kept)):
            span = kept[j] - start
            assert j - i + 1 <= 100.0 * (span + window) + 1e-6


def test_a_non_positive_limit_is_refused() -> None:
    with pytest.raises(ValueError, match="max_per_s"):
        SeedRatePlausibility(0.0)
