"""``sowgate report`` on small stores made here: nothing to report, alarms, the seed mass,
a store without a target spacing, and outputs that cannot be written."""

from __future__ import annotations

import csv
import html
import json
import os
import re
import stat
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from gateway.app.cli import main as sowgate
from gateway.config import EXIT_CONFIG
from gateway.core.records import AlarmEvent, SeedDrop
from gateway.recording.store import RecordStore
from gateway.report.command import EXIT_FAILED, EXIT_NO_RECORDS
from gateway.report.document import signed_pct

T0 = datetime(2026, 5, 2, 6, 0, tzinfo=UTC)


def drops(n: int = 400) -> list[SeedDrop]:
    return [
        SeedDrop(row=1 + i % 6, utc=T0 + timedelta(milliseconds=25 * i), lat=52.0 + i * 2e-7,
                 lon=13.0 + (i % 6) * 5e-6, fix="rtk_fixed", speed_kmh=8.0, heading_deg=0.0,
                 heading_source="dual_antenna", spacing_m=None if i < 6 else 0.2)
        for i in range(n)
    ]


def make_store(tmp_path: Path, seeds: list[SeedDrop], alarms: Sequence[AlarmEvent] = ()) -> Path:
    path = tmp_path / "records.sqlite3"
    store = RecordStore(path, "seeder-01")
    if seeds:
        store.add_seeds(seeds)
    for a in alarms:
        store.add_alarm(a)
    store.flush()
    store.close()
    return path


def config(tmp_path: Path, store: Path, target: float | None = 0.2) -> Path:
    cfg = tmp_path / "sowgate.toml"
    text = f'[machine]\nid = "seeder-01"\n[store]\npath = "{store}"\n'
    if target is not None:
        text += f"[positioning]\ntarget_spacing_m = {target}\n"
    cfg.write_text(text)
    return cfg


def report(cfg: Path, out: Path, *extra: str) -> int:
    return sowgate(["report", "--config", str(cfg), "--output", str(out), *extra])


def embedded(out: Path) -> dict[str, object]:
    m = re.search(r'id="report-data">(.*?)</script>', out.read_text(), re.S)
    assert m is not None
    data: dict[str, object] = json.loads(m.group(1).replace("<\\/", "</"))
    return data


def test_an_empty_store_is_nothing_to_report(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    cfg = config(tmp_path, make_store(tmp_path, []))
    out = tmp_path / "out" / "r.html"
    out.parent.mkdir()
    assert report(cfg, out) == EXIT_NO_RECORDS
    assert "nothing to report: no seed records in" in capsys.readouterr().err
    assert list(out.parent.iterdir()) == []


def test_no_store_at_all_is_nothing_to_report(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    cfg = config(tmp_path, tmp_path / "nowhere.sqlite3")
    assert report(cfg, tmp_path / "r.html") == EXIT_NO_RECORDS
    assert "no record store at" in capsys.readouterr().err
    assert not (tmp_path / "r.html").exists()


def test_rows_with_no_seeds_in_the_window_are_nothing_to_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = config(tmp_path, make_store(tmp_path, [d for d in drops() if d.row != 6]))
    assert report(cfg, tmp_path / "r.html", "--rows", "6") == EXIT_NO_RECORDS
    assert "on rows 6" in capsys.readouterr().err
    assert not (tmp_path / "r.html").exists()


def test_alarms_are_listed_with_their_times(tmp_path: Path) -> None:
    alarms = [
        AlarmEvent(code="radar.lost", active=True, severity="critical",
                   message="radar speed sensor not answering", utc=T0 + timedelta(seconds=2)),
        AlarmEvent(code="radar.lost", active=False, severity="critical",
                   message="radar back", utc=T0 + timedelta(seconds=5)),
    ]
    cfg = config(tmp_path, make_store(tmp_path, drops(), alarms))
    out = tmp_path / "r.html"
    assert report(cfg, out) == 0
    text = html.unescape(out.read_text())
    assert "2026-05-02 06:00:02" in text and "radar speed sensor not answering" in text
    assert "2 events, 1 alarm periods" in text
    assert embedded(out)["alarm_events"] == 2


def test_row_monitor_alarms_are_in_the_table_and_the_timeline(tmp_path: Path) -> None:
    """Issue 20: a blocked row and all rows silent, as the daemon stores them."""
    alarms = [
        AlarmEvent(code="row.4.blocked", active=True, severity="critical",
                   message="row 4 blocked: no seeds (0 % of the median row); check its tube "
                   "and sensor", utc=T0 + timedelta(seconds=3)),
        AlarmEvent(code="row.4.blocked", active=False, severity="critical",
                   message="row 4 blocked", utc=T0 + timedelta(seconds=6)),
        AlarmEvent(code="seed_sensors.all_rows_silent", active=True, severity="critical",
                   message="no seed on any row for 5 s while the meter turns",
                   utc=T0 + timedelta(seconds=7)),
        AlarmEvent(code="row.2.chattering", active=True, severity="warning",
                   message="row 2: its sensor sends edges faster than a row can drop seeds",
                   utc=T0 + timedelta(seconds=8)),
    ]
    cfg = config(tmp_path, make_store(tmp_path, drops(), alarms))
    out = tmp_path / "r.html"
    assert report(cfg, out) == 0
    text = html.unescape(out.read_text())
    for code in ("row.4.blocked", "seed_sensors.all_rows_silent", "row.2.chattering"):
        assert code in text
    assert "row 4 blocked: no seeds" in text
    assert "4 events, 3 alarm periods" in text


def test_the_seed_mass_needs_the_thousand_seed_mass(tmp_path: Path) -> None:
    cfg = config(tmp_path, make_store(tmp_path, drops(400)))
    out = tmp_path / "r.html"
    assert report(cfg, out) == 0
    assert embedded(out)["seed_mass_kg"] is None
    assert "not stored (give --tsw GRAMS" in html.unescape(out.read_text())
    assert report(cfg, out, "--tsw", "350") == 0
    assert embedded(out)["seed_mass_kg"] == pytest.approx(400 * 0.35 / 1000)


def test_without_a_target_spacing_the_rows_median_is_the_reference(tmp_path: Path) -> None:
    cfg = config(tmp_path, make_store(tmp_path, drops()), target=None)
    out = tmp_path / "r.html"
    assert report(cfg, out) == 0
    data = embedded(out)
    assert data["target_population_per_ha"] is None
    q = data["quality"]
    assert isinstance(q, dict) and q["1"]["x_ref_m"] == pytest.approx(0.2)
    assert "No target spacing is configured" in html.unescape(out.read_text())


def test_an_output_that_cannot_be_written_is_one_line(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    cfg = config(tmp_path, make_store(tmp_path, drops()))
    assert report(cfg, tmp_path / "missing-dir" / "r.html") == EXIT_FAILED
    assert "cannot write" in capsys.readouterr().err


def test_a_bad_config_is_a_config_error(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[machine]\nrows = 0\n")
    assert report(cfg, tmp_path / "r.html") == EXIT_CONFIG


@pytest.mark.parametrize(
    "seeds",
    [
        drops(1),  # one seed: no spacing, no distance, a map of one point
        [d.model_copy(update={"speed_kmh": 0.0}) for d in drops(50)],  # standing still
        [d.model_copy(update={"spacing_m": None}) for d in drops(50)],  # no spacing at all
    ],
    ids=["one-seed", "speed-zero", "no-spacings"],
)
def test_degenerate_stores_still_give_a_whole_report(
    tmp_path: Path, seeds: list[SeedDrop]
) -> None:
    cfg = config(tmp_path, make_store(tmp_path, seeds))
    for out in (tmp_path / "r.html", tmp_path / "r.pdf"):
        assert report(cfg, out) == 0
    assert embedded(tmp_path / "r.html")["seeds"] == len(seeds)
    assert (tmp_path / "r.pdf").read_bytes().startswith(b"%PDF-")


def test_export_without_config_judges_spacings_against_the_runs_target_as_report_does(
    tmp_path: Path,
) -> None:
    """The daemon keeps its target spacing in its run marker: ``sowgate export`` without
    ``--config`` (as the demo prints it) gives the report's per-row numbers, not numbers
    judged against each row's median."""
    # spacings that vary, so the median and the 0.2 m target give different precisions
    seeds = [d.model_copy(update={"spacing_m": None if d.spacing_m is None
                                  else 0.17 + 0.01 * (i % 4)}) for i, d in enumerate(drops())]
    path = tmp_path / "records.sqlite3"
    with RecordStore(path, "seeder-01") as store:
        store.start_run({"target_spacing_m": 0.2}, T0)
        store.add_seeds(seeds)
        store.flush()
        store.stop_run(T0 + timedelta(minutes=1))
    cfg = config(tmp_path, path, target=None)  # a config that does not say it
    out = tmp_path / "r.html"
    assert report(cfg, out) == 0
    exported = tmp_path / "seeds.csv"
    assert sowgate(["export", "--state-dir", str(tmp_path), "--output", str(exported)]) == 0
    rows = list(csv.DictReader((tmp_path / "seeds.csv.quality.csv").open()))
    quality = embedded(out)["quality"]
    assert isinstance(quality, dict)
    assert {r["row"] for r in rows} == set(quality) and len(rows) == 6
    for r in rows:
        assert float(r["x_ref_m"]) == quality[r["row"]]["x_ref_m"] == 0.2
        assert float(r["precision"]) == pytest.approx(quality[r["row"]]["precision"], rel=1e-12)


def test_a_rate_a_hair_off_the_target_reads_0_0_not_minus_0_0() -> None:
    assert signed_pct(-0.04) == "0.0 %" and signed_pct(0.049) == "0.0 %"
    assert signed_pct(-1.25) == "-1.2 %" and signed_pct(2.0) == "+2.0 %"


def test_export_files_are_as_readable_as_the_report_and_coordinates_are_to_a_millimetre(
    tmp_path: Path,
) -> None:
    cfg = config(tmp_path, make_store(tmp_path, drops(50)))
    old = os.umask(0o022)
    try:
        assert report(cfg, tmp_path / "r.html") == 0
        assert sowgate(["export", "--config", str(cfg), "--output",
                        str(tmp_path / "s.csv")]) == 0
        assert sowgate(["export", "--config", str(cfg), "--output",
                        str(tmp_path / "s.geojson")]) == 0
    finally:
        os.umask(old)
    modes = {p.name: stat.S_IMODE(p.stat().st_mode)
             for p in tmp_path.iterdir() if p.suffix in (".html", ".csv", ".geojson")}
    assert modes == {"r.html": 0o644, "s.csv": 0o644, "s.csv.quality.csv": 0o644,
                     "s.geojson": 0o644}
    first = next(csv.DictReader((tmp_path / "s.csv").open()))
    assert first["lat"] == "52.00000000" and first["lon"] == "13.00000000"


def test_float_and_dropout_seeds_are_reported_apart_with_their_stated_accuracy(
    tmp_path: Path,
) -> None:
    seeds = drops()
    seeds[100:140] = [d.model_copy(update={"fix": "rtk_float", "accuracy_m": None})
                      for d in seeds[100:140]]
    seeds[200:205] = [d.model_copy(update={"extrapolated": True, "accuracy_m": None})
                      for d in seeds[200:205]]
    cfg = config(tmp_path, make_store(tmp_path, seeds))
    out = tmp_path / "r.html"
    assert report(cfg, out) == 0
    text = html.unescape(out.read_text())
    assert "40 seeds not RTK-fixed: rtk_float 40 (stated accuracy 0.4 m)" in text
    assert "5 extrapolated over dropouts (+0.1 m)" in text


def test_a_field_all_on_rtk_fixed_says_so(tmp_path: Path) -> None:
    cfg = config(tmp_path, make_store(tmp_path, drops()))
    out = tmp_path / "r.html"
    assert report(cfg, out) == 0
    assert "none: every seed on RTK fixed, none extrapolated" in html.unescape(out.read_text())
