"""The report's streaming accumulators: exact sums whatever the chunking, the spacing quality
of export's own accumulators, seeds classed by the ISO 7256-1 limits, alarms paired."""

from __future__ import annotations

import math
import random
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from gateway.core.records import SeedDrop, SeedRecord, drop_row, utc_to_us
from gateway.recording.export import quality_by_row, quality_by_row_chunks
from gateway.recording.field_stats import (
    GOOD,
    MISS,
    MULTIPLE,
    UNRATED,
    FieldStats,
    SeedMap,
    alarm_intervals,
    seed_classes,
)
from gateway.recording.store import StoredSeedRow

T0 = datetime(2026, 5, 2, 6, 0, tzinfo=UTC)
ROW_SPACING = 0.5


def stored_rows(n: int, seed: int = 1) -> list[StoredSeedRow]:
    """``n`` seeds of 4 rows: 20 cm spacing with some doubles and skips, every 50th without a
    spacing, a few on float or extrapolated, driving north at 6-10 km/h."""
    rng = random.Random(seed)
    out: list[StoredSeedRow] = []
    for i in range(n):
        row = 1 + i % 4
        sp = rng.choice([0.2, 0.21, 0.19, 0.05, 0.4]) if i % 50 else None
        drop = SeedDrop(
            row=row, utc=T0 + timedelta(milliseconds=20 * i), lat=52.0 + i * 1e-7,
            lon=13.0 + row * 1e-5, fix="rtk_float" if i % 10 == 0 else "rtk_fixed",
            speed_kmh=6.0 + (i % 5), heading_deg=0.0, heading_source="dual_antenna",
            extrapolated=i % 25 == 0, spacing_m=sp,
        )
        out.append((i + 1, *drop_row(drop)))
    return out


def span(rows: list[StoredSeedRow]) -> tuple[int, int]:
    return rows[0][1], rows[-1][1]


def chunks(rows: list[StoredSeedRow], size: int) -> list[list[StoredSeedRow]]:
    return [rows[i : i + size] for i in range(0, len(rows), size)]


def test_the_sums_do_not_depend_on_how_the_records_are_chunked() -> None:
    rows = stored_rows(2000)
    results = []
    for size in (1, 7, 500, 2000):
        stats = FieldStats(0.2, ROW_SPACING, span(rows))
        for c in chunks(rows, size):
            stats.add_rows(c)
        results.append(stats.result())
    first = results[0]
    for other in results[1:]:
        assert other.quality == first.quality  # exactly, not approximately
        assert other.seeds == first.seeds == 2000
        assert other.fixes == first.fixes
        assert other.sown_length_m == pytest.approx(first.sown_length_m, rel=1e-12)
        for k in first.drive:
            assert np.allclose(other.drive[k], first.drive[k], rtol=1e-12)


def test_counts_area_rate_and_position_quality_are_those_of_the_records() -> None:
    rows = stored_rows(1000)
    stats = FieldStats(0.2, ROW_SPACING, span(rows))
    for c in chunks(rows, 300):
        stats.add_rows(c)
    s = stats.result()
    spacings = [r[11] for r in rows if r[11] is not None]
    assert s.seeds == 1000
    assert s.seeds_by_row == {1: 250, 2: 250, 3: 250, 4: 250}
    assert s.fixes == {"rtk_fixed": 900, "rtk_float": 100}
    assert s.rtk_fixed_share == 0.9
    assert s.extrapolated == 40 and s.extrapolated_share == 0.04
    assert s.sown_length_m == pytest.approx(sum(spacings))
    assert s.area_ha == pytest.approx(sum(spacings) * ROW_SPACING / 1e4)
    # population: spacings per metre of row over the row spacing
    assert s.population_mean_per_ha == pytest.approx(
        1e4 * len(spacings) / (sum(spacings) * ROW_SPACING)
    )
    assert s.target_population_per_ha == pytest.approx(1e4 / (0.2 * ROW_SPACING))
    assert s.first_us == rows[0][1] and s.last_us == rows[-1][1]
    # per-second bins: every seed and every spacing counted once
    assert s.drive["seeds"].sum() == 1000
    assert s.drive["sp_n"].sum() == len(spacings)
    assert s.drive["sp_sum"].sum() == pytest.approx(sum(spacings))
    assert s.seeding_s == 20.0  # 1000 seeds 20 ms apart fill 20 one-second bins
    assert s.by_speed["sp_n"].sum() == len(spacings)
    # the histograms hold every spacing of their row
    for row in range(1, 5):
        assert s.hist_by_row[row].sum() == s.quality[row].n
    assert s.speed_mean_kmh == pytest.approx(sum(r[6] for r in rows) / 1000)


def test_quality_from_the_stored_chunks_is_exports_quality_bit_for_bit() -> None:
    rows = stored_rows(3000, seed=7)
    records = [
        SeedRecord(row=r[2], utc=T0 + timedelta(microseconds=r[1] - utc_to_us(T0)), lat=r[3],
                   lon=r[4], fix=r[5], speed_kmh=r[6], heading_deg=r[7], heading_source=r[8],
                   extrapolated=r[9], method=r[10], spacing_m=r[11], id=r[0], machine_id="m")
        for r in rows
    ]
    for x_ref in (0.2, None):
        assert quality_by_row_chunks(chunks(rows, 333), x_ref) == quality_by_row(records, x_ref)


def test_seeds_are_classed_by_the_iso_limits_of_their_rows_reference() -> None:
    ref = np.full(6, 0.2)
    spacing = np.array([0.1, 0.1000001, 0.3, 0.3000001, math.nan, 0.2])
    ref[5] = math.nan  # a row without a reference (no spacing seen yet)
    assert list(seed_classes(spacing, ref)) == [MULTIPLE, GOOD, GOOD, MISS, UNRATED, UNRATED]


def test_the_map_keeps_every_seed_up_to_the_limit_and_counts_cells_above_it() -> None:
    rows = stored_rows(2000)
    stats = FieldStats(0.2, ROW_SPACING, span(rows))
    stats.add_rows(rows)
    s = stats.result()
    points, raster = SeedMap(s, max_points=2000), SeedMap(s, max_points=1999)
    for c in chunks(rows, 128):
        points.add_rows(c)
        raster.add_rows(c)
    p, r = points.result(), raster.result()
    assert p.points is not None and p.raster is None and p.points[0].size == 2000
    assert r.raster is not None and r.points is None
    assert int(r.raster.sum()) == 2000
    assert p.class_counts == r.class_counts
    assert tuple(int(v) for v in r.raster.sum(axis=(1, 2))) == r.class_counts
    q = s.quality
    assert p.class_counts[MULTIPLE] == sum(
        round(q[row].multiples_index * q[row].n / 100) for row in q  # type: ignore[operator]
    )
    assert p.class_counts[MISS] == sum(
        round(q[row].miss_index * q[row].n / 100) for row in q  # type: ignore[operator]
    )
    assert p.class_counts[UNRATED] == sum(1 for row in rows if row[11] is None)
    # the local frame is metres: 2000 seeds 1e-7 deg apart northwards is ~22 m
    _x0, _x1, y0, y1 = p.extent_m
    assert y1 - y0 == pytest.approx(1999e-7 * 111_133, rel=0.01)


def test_alarms_are_paired_into_periods_even_across_the_windows_edges() -> None:
    events = [
        (100, "gnss.not_rtk_fixed", False, "warning"),  # raised before the window
        (200, "radar.lost", True, "critical"),
        (300, "radar.lost", False, "critical"),
        (400, "seed_sensors.unavailable", True, "warning"),  # still on at the end
    ]
    assert alarm_intervals(events, 50, 1000) == [
        ("gnss.not_rtk_fixed", "warning", 50, 100, "cleared"),
        ("radar.lost", "critical", 200, 300, "cleared"),
        ("seed_sensors.unavailable", "warning", 400, 1000, "open"),
    ]


def test_an_alarm_active_when_the_daemon_stopped_ends_at_that_stop() -> None:
    # run 1: 0..500 (pwm lost at 100, never cleared); run 2: 600.. (clean, a radar blip);
    # run 3 from 900 (no stop yet: running)
    events = [
        (100, "pwm.unavailable", True, "critical"),
        (700, "radar.unavailable", True, "warning"),
        (750, "radar.unavailable", False, "warning"),
        (950, "gnss.not_rtk_fixed", False, "warning"),  # its raise was in the run before
        (960, "speed.lost", True, "warning"),
    ]
    runs = [(0, 500), (600, 800), (900, None)]
    got = alarm_intervals(events, 0, 2000, runs)
    assert got == [
        ("pwm.unavailable", "critical", 100, 500, "stop"),  # not across the later runs
        ("radar.unavailable", "warning", 700, 750, "cleared"),
        ("gnss.not_rtk_fixed", "warning", 900, 950, "cleared"),  # from its run's start
        ("speed.lost", "warning", 960, 2000, "open"),
    ]
    assert not got[0].cleared and got[1].cleared
    # without the run markers (an older store) it is drawn to the end of the window
    assert alarm_intervals(events[:1], 0, 2000)[0].to_us == 2000
