"""What the report's plots put in front of a farmer: points that mean something, time labels
that tell ticks apart, histograms large enough to read."""

from __future__ import annotations

import random
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from gateway.core.records import SeedDrop
from gateway.recording.field_stats import FieldStats, FieldSummary
from gateway.recording.store import RecordStore
from gateway.report import figures
from tests.gateway.report.test_command import make_store

T0 = datetime(2026, 5, 2, 6, 0, 0, 400_000, tzinfo=UTC)
ROW_SPACING_M = 2.0 / 6


def noisy_drive(seconds: float, per_second: int = 30) -> list[SeedDrop]:
    """Six rows at 0.2 m (10 % CV), starting and ending inside a second: thin first and last
    time bins, as in the demo's store."""
    rnd = random.Random(7)
    n = int(seconds * per_second)
    return [
        SeedDrop(row=1 + i % 6, utc=T0 + timedelta(seconds=i / per_second), lat=52.0 + i * 2e-7,
                 lon=13.0 + (i % 6) * 5e-6, fix="rtk_fixed", speed_kmh=4.5, heading_deg=0.0,
                 heading_source="dual_antenna",
                 spacing_m=None if i < 6 else max(0.01, rnd.gauss(0.2, 0.02)))
        for i in range(n)
    ]


def summary_of(tmp_path: Path, seeds: list[SeedDrop]) -> FieldSummary:
    path = make_store(tmp_path, seeds)
    with RecordStore.open_readonly(path, "seeder-01") as store:
        span = store.seed_time_span(None, None)
        assert span is not None
        stats = FieldStats(0.2, ROW_SPACING_M, span)
        for chunk in store.query_seed_rows(None, None, None):
            stats.add_rows(chunk)
    return stats.result()


def test_every_point_of_the_rate_along_the_drive_is_the_mean_of_enough_spacings(
    tmp_path: Path,
) -> None:
    s = summary_of(tmp_path, noisy_drive(40.3))
    assert s.drive["sp_n"][-1] < figures.MIN_STRETCH_SPACINGS  # the thin last second is there
    st = figures._drive_stretches(s)
    assert st["n"].min() >= figures.MIN_STRETCH_SPACINGS
    assert st["n"].sum() == s.drive["sp_n"].sum()  # merged, not dropped
    target = 1 / (0.2 * ROW_SPACING_M) * 1e4
    # 50+ spacings of 10 % CV: each point within 6 % of the truth (4 sigma)
    assert np.all(np.abs(st["pop"] / target - 1) < 0.06), st["pop"]


def test_a_drive_shorter_than_one_point_is_one_point(tmp_path: Path) -> None:
    st = figures._drive_stretches(summary_of(tmp_path, noisy_drive(1.2)))
    assert st["pop"].size == 1


def test_time_ticks_of_a_short_window_are_round_distinct_clock_times() -> None:
    start = int(datetime(2026, 11, 24, 10, 56, 55, tzinfo=UTC).timestamp() * 1e6)
    span_h = 98 / 3600
    ticks = figures.clock_ticks_h(start, span_h)
    fmt = figures.time_tick_formatter(start, span_h)
    labels = [fmt(t, None) for t in ticks]
    assert labels == ["10:57:00", "10:57:10", "10:57:20", "10:57:30", "10:57:40",
                      "10:57:50", "10:58:00", "10:58:10", "10:58:20", "10:58:30"]
    day = figures.clock_ticks_h(start, 9.5)
    assert len(day) <= 12
    assert [fmt2 for fmt2 in (figures.time_tick_formatter(start, 9.5)(day[0], None),)] == [
        "11:00"]


def test_histograms_of_a_six_row_planter_are_three_to_a_line_and_readable() -> None:
    assert figures.histogram_columns(6) == 3
    assert figures.histogram_columns(2) == 2
    assert figures.histogram_columns(12) == 4
    assert figures.histogram_columns(48) == 6
