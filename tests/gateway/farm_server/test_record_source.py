"""``sowgate report`` and ``sowgate export`` (GeoJSON, CSV, ISO-XML, alarms) read from the farm
server's PostgreSQL with ``--database URL --machine M`` give what they give from the cab's
record store: the drive's records are stored on the "cab", committed into a fresh database by
ingest's own writer, and the outputs of both sources are compared."""

from __future__ import annotations

import html
import json
import random
import re
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from gateway.app.cli import main as sowgate
from gateway.core.records import AlarmEvent, SeedDrop
from gateway.farm_server.db import IngestDatabase
from gateway.recording.database_source import DatabaseSource
from gateway.recording.store import RecordStore

T0 = datetime(2026, 5, 2, 6, 0, tzinfo=UTC)
MACHINE = "seeder-01"


def drive(seconds: float = 90, per_second: int = 60) -> list[SeedDrop]:
    """Six rows at 0.2 m with multiples and misses, a turn every 30 s (no seeds for 3 s)."""
    rnd = random.Random(11)
    out = []
    for i in range(int(seconds * per_second)):
        t = i / per_second
        if t % 30 > 27:
            continue
        spacing = rnd.choice([0.06] + [0.2] * 20 + [0.41]) * rnd.gauss(1, 0.08)
        out.append(SeedDrop(
            row=1 + i % 6, utc=T0 + timedelta(seconds=t), lat=52.0 + i * 2.3e-7,
            lon=13.0 + (i % 6) * 5e-6 + rnd.gauss(0, 1e-8), fix="rtk_fixed",
            speed_kmh=round(rnd.uniform(7.5, 8.5), 3), heading_deg=rnd.uniform(0, 359.9),
            heading_source="dual_antenna", extrapolated=i % 97 == 0,
            spacing_m=None if i < 6 else max(0.005, spacing),
            attitude="inclinometer", roll_deg=rnd.gauss(0, 2), pitch_deg=rnd.gauss(0, 1),
            delay_ms=310.5, offset_east_m=0.4, offset_north_m=-1.2))
    return out


ALARMS = [
    AlarmEvent(code="radar.lost", active=True, severity="critical",
               message="radar speed sensor not answering", utc=T0 + timedelta(seconds=12)),
    AlarmEvent(code="radar.lost", active=False, severity="critical", message="radar back",
               utc=T0 + timedelta(seconds=19.5)),
    AlarmEvent(code="row.4.blocked", active=True, severity="critical",
               message="row 4 blocked: no seeds", utc=T0 + timedelta(seconds=40)),
    AlarmEvent(code="row.4.blocked", active=False, severity="critical",
               message="row 4 blocked", utc=T0 + timedelta(seconds=44)),
]


@pytest.fixture
def both(tmp_path: Path, database: str) -> tuple[Path, str]:
    """The cab's store and the farm database holding the same drive; the config's path."""
    store_file = tmp_path / "records.sqlite3"
    store = RecordStore(store_file, MACHINE)
    store.add_seeds(drive())
    for a in ALARMS:
        store.add_alarm(a)
    store.flush()
    store.close()
    db = IngestDatabase(database)
    try:
        with RecordStore.open_readonly(store_file, MACHINE) as cab:
            records = list(cab.query_seeds())
            for i in range(0, len(records), 500):  # in the batches the cab publishes
                db.write_seeds(MACHINE, records[i:i + 500])
            db.write_alarms(list(cab.query_alarms()))
    finally:
        db.close()
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(f'[machine]\nid = "{MACHINE}"\nrows = 6\n[store]\npath = "{store_file}"\n'
                   "[positioning]\ntarget_spacing_m = 0.2\n")
    return cfg, database


def embedded(out: Path) -> dict[str, object]:
    m = re.search(r'id="report-data">(.*?)</script>', out.read_text(), re.S)
    assert m is not None
    data: dict[str, object] = json.loads(m.group(1).replace("<\\/", "</"))
    return data


def test_the_database_reads_back_the_stores_rows_to_the_last_digit(
        both: tuple[Path, str], tmp_path: Path) -> None:
    _, url = both
    with RecordStore.open_readonly(tmp_path / "records.sqlite3", MACHINE) as store, \
            DatabaseSource(url, MACHINE) as db:
        cab_rows = [r[:15] for chunk in store.query_seed_rows() for r in chunk]
        db_rows = [r[:15] for chunk in db.query_seed_rows() for r in chunk]
        assert len(db_rows) == len(cab_rows) > 4000
        # extrapolated is 0/1 in SQLite, a boolean in PostgreSQL
        assert [(*r[:9], bool(r[9]), *r[10:]) for r in cab_rows] == db_rows
        assert list(store.query_alarms()) == list(db.query_alarms())
        assert store.seed_time_span() == db.seed_time_span()
        since, until = T0 + timedelta(seconds=20), T0 + timedelta(seconds=50)
        assert store.seed_time_span(since, until) == db.seed_time_span(since, until)
        assert [r.id for r in store.query_seeds(since, until, [2, 5])] == \
            [r.id for r in db.query_seeds(since, until, [2, 5])]


@pytest.mark.parametrize("window", [(), ("--since", "2026-05-02T06:00:20Z",
                                          "--until", "2026-05-02T06:01:05Z", "--rows", "1,3,4")])
def test_report_and_every_export_are_the_same_from_the_store_and_the_database(
        both: tuple[Path, str], tmp_path: Path, window: tuple[str, ...]) -> None:
    cfg, url = both
    db = ("--database", url, "--machine", MACHINE)
    out: dict[str, Path] = {}
    for name, extra in (("cab", ()), ("db", db)):
        d = tmp_path / name
        d.mkdir()
        out[name] = d
        base = ["--config", str(cfg), *window, *extra]
        assert sowgate(["report", *base, "--output", str(d / "r.html")]) == 0
        assert sowgate(["export", *base, "--output", str(d / "s.geojson")]) == 0
        assert sowgate(["export", *base, "--output", str(d / "s.csv")]) == 0
        assert sowgate(["export", *base, "--format", "isoxml", "--output", str(d / "iso")]) == 0
        if "--rows" not in window:
            assert sowgate(["export", *base, "--what", "alarms",
                            "--output", str(d / "a.csv")]) == 0
    cab, farm = out["cab"], out["db"]
    r_cab, r_db = embedded(cab / "r.html"), embedded(farm / "r.html")
    assert r_db == r_cab  # every figure: seeds, per-row ISO 7256-1 numbers, rate, alarms
    assert isinstance(r_cab["seeds"], int) and r_cab["seeds"] > 1000
    assert r_cab["alarm_events"] == (2 if window else 4)
    # the whole page too, but for the line saying when and from where it was made
    page_cab, page_db = ((d / "r.html").read_text() for d in (cab, farm))
    made = re.compile(r"Made by sowgate report on [^<]*? from the (record store|farm database)")
    assert made.findall(page_db) == ["farm database"]
    assert made.findall(page_cab) == ["record store"]
    assert made.sub("", page_db) == made.sub("", page_cab)
    text = html.unescape((farm / "r.html").read_text())
    if not window:
        assert "4 events, 2 alarm periods" in text
    # the exports byte for byte: features, per-row quality, CSV rows, alarm periods
    for f in ("s.geojson", "s.csv", "s.csv.quality.csv", *(() if window else ("a.csv",))):
        assert (farm / f).read_bytes() == (cab / f).read_bytes(), f
    quality = json.loads((farm / "s.geojson").read_text())["quality"]
    assert set(quality) == ({"1", "3", "4"} if window else {str(r) for r in range(1, 7)})
    # ISO-XML: the same time logs (binaries and their headers) and the same task
    iso_cab = sorted(p.relative_to(cab / "iso") for p in (cab / "iso").rglob("*") if p.is_file())
    iso_db = sorted(p.relative_to(farm / "iso") for p in (farm / "iso").rglob("*")
                    if p.is_file())
    assert iso_db == iso_cab and any(p.suffix == ".BIN" for p in iso_cab)
    for p in iso_cab:
        assert (farm / "iso" / p).read_bytes() == (cab / "iso" / p).read_bytes(), p


def test_bad_database_options_are_one_clear_line(
        both: tuple[Path, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg, url = both
    base = ["--config", str(cfg), "--output", str(tmp_path / "x.geojson")]
    assert sowgate(["export", *base, "--database", url]) == 2
    assert "--machine: required with --database" in capsys.readouterr().err
    assert sowgate(["export", *base, "--machine", MACHINE]) == 2
    assert "--machine: only with --database" in capsys.readouterr().err
    assert sowgate(["export", *base, "--database", url, "--machine", "a b"]) == 2
    assert "--machine" in capsys.readouterr().err
    assert sowgate(["export", *base, "--database", url, "--machine", MACHINE,
                    "--reposition"]) == 2
    assert "--reposition: needs the record store" in capsys.readouterr().err
    bad = url.rsplit("/", 1)[0] + "/no_such_database_here"
    assert sowgate(["export", *base, "--database", bad, "--machine", MACHINE]) == 1
    err = capsys.readouterr().err
    assert "--database: cannot connect" in err and "no_such_database_here" in err
    assert sowgate(["report", "--config", str(cfg), "--output", str(tmp_path / "r.html"),
                    "--database", url, "--machine", "seeder-99"]) == 66
    assert "no seed records in the farm database (machine seeder-99)" in capsys.readouterr().err
    assert sowgate(["report", "--config", str(cfg), "--output", str(tmp_path / "r.html"),
                    "--database", url, "--machine", MACHINE, "--since", "yesterday"]) == 2
    assert "--since: not an ISO 8601 time" in capsys.readouterr().err
    assert not (tmp_path / "x.geojson").exists() and not (tmp_path / "r.html").exists()
