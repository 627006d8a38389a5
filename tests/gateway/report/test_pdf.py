"""The PDF report prints: A4 pages throughout, no word on top of another (a caption over an
axis label, a table header over its neighbour), nothing off the page, the alarm table in it,
and page 1 used. Checked as a reader sees it: poppler's word boxes and the rendered pages."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import Image

from gateway.app.cli import main as sowgate
from gateway.core.records import AlarmEvent, SeedDrop, utc_to_us
from gateway.recording.field_stats import FieldStats, SeedMap, alarm_intervals
from gateway.recording.store import RecordStore
from gateway.report.document import FieldReport
from gateway.report.pdf import to_pdf
from tests.gateway.report.test_command import T0, config
from tests.pdf_pages import (
    A4_PT,
    overlapping_words,
    pages,
    render_png,
    require_poppler,
    words_off_the_page,
)

LONG_MESSAGE = ("PWM module not answering on RS485: no reply within 0.2 s (timeout); the "
                "metering motor keeps its last duty until the module's watchdog stops it")


def field(rows: int, per_row: int) -> list[SeedDrop]:
    """``rows`` rows sown side by side at 8 km/h, spacings around 0.2 m with some misses."""
    rnd = np.random.default_rng(3)
    out = []
    for k in range(per_row):
        for r in range(1, rows + 1):
            sp = None if k == 0 else float(rnd.choice([0.2, 0.2, 0.2, 0.19, 0.21, 0.42, 0.08]))
            out.append(SeedDrop(
                row=r, utc=T0 + timedelta(milliseconds=90 * k + r), lat=52.0 + k * 1.8e-6,
                lon=13.0 + r * 7.5e-6, fix="rtk_fixed", speed_kmh=8.0, heading_deg=0.0,
                heading_source="dual_antenna", spacing_m=sp))
    return out


def alarm_events(n: int) -> list[AlarmEvent]:
    codes = ["pwm.unavailable", "radar.unavailable", "gnss.not_rtk_fixed",
             "seed_sensors.unavailable", "channel.fertiliser_2.feedback_lost"]
    return [
        AlarmEvent(code=codes[i % len(codes)], active=(i // len(codes)) % 2 == 0,
                   severity="critical" if i % 2 else "warning",
                   message=LONG_MESSAGE if i % 3 == 0 else "back", utc=T0 + timedelta(
                       seconds=1 + i))
        for i in range(n)
    ]


def store_with(tmp_path: Path, seeds: list[SeedDrop], alarms: list[AlarmEvent]) -> Path:
    path = tmp_path / "records.sqlite3"
    with RecordStore(path, "seeder-01") as store:
        store.start_run({"target_spacing_m": 0.2}, T0 - timedelta(seconds=5))
        store.add_seeds(seeds)
        for a in alarms:
            store.add_alarm(a)
        store.flush()
        store.stop_run(T0 + timedelta(seconds=30))  # alarms still active end here
    return path


def check_printable(pdf: Path, out: Path) -> list[str]:
    """Every check of a printable report; returns the text of each page."""
    found = pages(pdf)
    assert found
    for n, page in enumerate(found, 1):
        assert (page.width, page.height) == pytest.approx(A4_PT, abs=0.5), f"page {n}"
        assert not overlapping_words(page), (n, overlapping_words(page)[:5])
        assert not words_off_the_page(page, margin_pt=14), (n, words_off_the_page(page, 14))
    pngs = render_png(pdf, out, dpi=50)
    assert len(pngs) == len(found)
    sizes = {Image.open(p).size for p in pngs}
    assert sizes == {(414, 585)}  # A4 at 50 dpi, every page
    # page 1 is used down to its footer: content below 80 % of the page's height
    grey = np.asarray(Image.open(pngs[0]).convert("L"))
    inked = np.nonzero((grey < 200).any(axis=1))[0]
    body = inked[inked < grey.shape[0] - 0.6 * 50]  # above the footer's half inch
    assert body.max() > 0.8 * grey.shape[0], body.max() / grey.shape[0]
    return [p.text() for p in found]


def test_a_six_row_report_prints_on_a4_with_its_alarm_table(tmp_path: Path) -> None:
    require_poppler()
    path = store_with(tmp_path, field(6, 300), alarm_events(7))
    out = tmp_path / "report.pdf"
    assert sowgate(["report", "--config", str(config(tmp_path, path)), "--output",
                    str(out)]) == 0
    texts = check_printable(out, tmp_path)
    everything = " ".join(texts)
    assert "Alarm events" in everything and "channel.fertiliser_2.feedback_lost" in everything
    assert "watchdog stops it" in everything  # a long message, wrapped, whole
    assert "alarms still active end here" in everything  # the run's stop in the table
    assert texts[0].startswith("Field report: seeder-01") and "Seed map" in texts[0]


def test_48_rows_and_a_long_alarm_list_continue_on_further_a4_pages(tmp_path: Path) -> None:
    require_poppler()
    path = store_with(tmp_path, field(48, 60), alarm_events(90))
    out = tmp_path / "report.pdf"
    cfg = config(tmp_path, path)
    cfg.write_text(cfg.read_text().replace("[machine]\n", "[machine]\nrows = 48\n"
                                           "working_width_m = 36.0\n"))
    assert sowgate(["report", "--config", str(cfg), "--output", str(out)]) == 0
    texts = check_printable(out, tmp_path)
    everything = " ".join(texts)
    assert "Spacing quality per row (ISO 7256-1) (continued)" in everything
    assert "Spacing per row (continued: rows" in everything
    assert "Alarm events (continued)" in everything
    assert "row 48: singles" in everything


def test_a_raster_map_prints_too(tmp_path: Path) -> None:
    """Past the point limit the map is three rasters (singles, misses, multiples)."""
    require_poppler()
    path = store_with(tmp_path, field(12, 200), alarm_events(3))
    with RecordStore.open_readonly(path, "seeder-01") as store:
        span = store.seed_time_span()
        assert span is not None
        stats = FieldStats(0.2, 0.5, span)
        for chunk in store.query_seed_rows():
            stats.add_rows(chunk)
        summary = stats.result()
        seed_map = SeedMap(summary, max_points=100)
        for chunk in store.query_seed_rows():
            seed_map.add_rows(chunk)
        alarms = list(store.query_alarms())
        runs = store.runs()
    result = seed_map.result()
    assert result.raster is not None
    report = FieldReport(
        machine_id="seeder-01", machine_rows=12, working_width_m=6.0, crop="maize",
        summary=summary, seed_map=result, alarms=alarms, alarms_total=len(alarms),
        intervals=alarm_intervals([(utc_to_us(a.utc), a.code, a.active, a.severity)
                                   for a in alarms], summary.first_us, summary.last_us,
                                  [(r.start_us, r.stop_us) for r in runs]),
        since=None, until=None, rows=None, tsw_g=5.0, runs=runs,
    )
    out = tmp_path / "raster.pdf"
    out.write_bytes(to_pdf(report))
    texts = check_printable(out, tmp_path)
    assert "misses %" in texts[0]


def test_the_overlap_check_finds_words_on_top_of_each_other(tmp_path: Path) -> None:
    """The check above can fail: two words drawn at one place are found."""
    fig = Figure(figsize=(8.27, 11.69))
    fig.text(0.3, 0.5, "caption over")
    fig.text(0.32, 0.5, "axis label")
    out = tmp_path / "overlap.pdf"
    fig.savefig(out, format="pdf")
    (page,) = pages(out)
    assert overlapping_words(page)
