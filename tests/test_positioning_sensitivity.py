"""The positioning headline's sensitivity rows: each changes what it says and nothing else."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from benchmarks import positioning_sensitivity as ps
from benchmarks.positioning_draws import draw


def _changed(a: object, b: object) -> set[str]:
    return {f.name for f in dataclasses.fields(a) if getattr(a, f.name) != getattr(b, f.name)}  # type: ignore[arg-type]


def test_each_row_changes_one_part_of_the_draw() -> None:
    d = draw(103)
    parts = {}
    for cond in ps.CONDITIONS:
        parts[cond.name] = _changed(d.config, cond.apply(d.config))
    names = [c.name for c in ps.CONDITIONS]
    for name in names[:3]:  # multipath: the receiver's multipath alone
        assert parts[name] == {"receiver"}
        assert _changed(d.config.receiver, ps.CONDITIONS[names.index(name)].apply(
            d.config).receiver) == {"multipath"}
    assert parts[names[3]] == parts[names[4]] == parts[names[6]] == {"furrow"}
    assert parts[names[7]] == {"lot"}
    assert parts[names[8]] == parts[names[9]] == {"receiver"}
    assert parts[names[10]] == {"timing"}
    assert parts[names[11]] == {"furrow", "lot", "receiver", "timing"}


def test_switching_off_the_furrow_scatter_keeps_the_mean_slide_the_oracle_knows() -> None:
    d = draw(104)
    off = ps.CONDITIONS[6].apply(d.config).furrow
    u = np.array([0.5, 2.0, 4.0])
    assert off.retained[0] == off.retained[1]
    assert off.bounce_along_sd_m == off.bounce_across_sd_m == 0.0
    np.testing.assert_allclose(off.mean_slide_m(u), d.config.furrow.mean_slide_m(u))


def test_the_hard_furrow_is_outside_the_drawn_range() -> None:
    d = draw(101)
    hard = ps.CONDITIONS[5].apply(d.config).furrow
    assert hard.retained[0] == pytest.approx(d.config.furrow.retained[0] + 0.15)
    assert hard.bounce_along_sd_m == pytest.approx(3 * d.config.furrow.bounce_along_sd_m)


def test_the_table_marks_a_p90_above_its_target() -> None:
    def rows(v412: float, v16: float) -> list[dict[str, object]]:
        return [{"calibrated": {"4–12 km/h": v412 + i * 0.1, "16 km/h": v16},
                 "oracle": {"4–12 km/h": 10.0, "16 km/h": 10.0}} for i in range(20)]

    results = [rows(20.0, 40.0)] + [rows(10.0, 10.0)] * (len(ps.CONDITIONS) - 1)
    text = ps.markdown(results)
    first = next(ln for ln in text.splitlines() if ln.startswith("| GNSS multipath"))
    cells = first.split(" | ")
    assert "**" not in cells[1] and cells[2].startswith("40.0 / **40.0**")
    assert "| 20 |" in first


def test_the_reading_names_what_breaks_a_target_and_the_floors_parts() -> None:
    def rows(cal16: float, or16: float) -> list[dict[str, object]]:
        return [{"calibrated": {"4–12 km/h": 10.0, "16 km/h": cal16},
                 "oracle": {"4–12 km/h": 10.0, "16 km/h": or16}} for _ in range(20)]

    results = [rows(10.0, 10.0) for _ in ps.CONDITIONS]
    results[3] = rows(45.0, 40.0)  # retained speed breaks 16 km/h, the oracle too
    text = ps.markdown(results, rows(36.0, 31.0))
    assert ("Targets broken by a condition (p90 after survey calibration): furrow retained "
            "speed +0.15 (16 km/h; the oracle too at 16 km/h).") in text
    assert "the oracle's p90 is 31.0 mm (sowgate after survey calibration 36.0)" in text
    assert ", multipath (" not in text and ": multipath (" not in text
