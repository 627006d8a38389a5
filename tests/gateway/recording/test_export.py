"""``sowgate export``: GeoJSON/CSV as-planted maps from the real record store, with quality."""

from __future__ import annotations

import argparse
import csv
import io
import json
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from gateway.app.cli import main as cli_main
from gateway.app.export import main_export
from gateway.core.records import SeedDrop, SeedRecord
from gateway.recording.export import (
    CSV_FIELDS,
    ExportError,
    export_quality_csv,
    export_seeds,
    parse_rows,
    parse_time,
    quality_by_row,
)
from gateway.recording.store import RecordStore

T0 = datetime(2026, 5, 2, 6, 0, 0, tzinfo=UTC)
# row 1: one multiple (0.05) and one miss (0.45) among 0.2 m spacings; row 2: perfect
SPACINGS = {1: [None, 0.2, 0.2, 0.05, 0.45, 0.2, 0.22, 0.18], 2: [None, 0.2, 0.2, 0.2]}


def drops() -> list[SeedDrop]:
    out = []
    k = 0
    for row, spacings in SPACINGS.items():
        for sp in spacings:
            out.append(
                SeedDrop(
                    row=row,
                    utc=T0 + timedelta(seconds=k),
                    lat=45.75 + k * 1e-6,
                    lon=126.63 + row * 1e-5,
                    fix="rtk_fixed" if k % 2 else "rtk_float",
                    speed_kmh=8.0,
                    heading_deg=None if k == 3 else 90.0,
                    heading_source="none" if k == 3 else "dual_antenna",
                    extrapolated=k == 4,
                    spacing_m=sp,
                )
            )
            k += 1
    return out


def records() -> list[SeedRecord]:
    return [
        SeedRecord(**d.model_dump(), id=i + 1, machine_id="seeder-01")
        for i, d in enumerate(drops())
    ]


@pytest.fixture
def store_file(tmp_path: Path) -> Iterator[Path]:
    path = tmp_path / "state" / "records.sqlite3"
    store = RecordStore(path, "seeder-01")
    store.add_seeds(drops())
    store.flush()
    store.close()
    yield path


def args(out: Path | str, config: Path | None = None, **kw: str | None) -> argparse.Namespace:
    base: dict[str, object] = {
        "format": "geojson",
        "output": str(out),
        "since": None,
        "until": None,
        "rows": None,
        "config": config,
    }
    base.update(kw)
    return argparse.Namespace(**base)


def config_for(tmp_path: Path, store: Path, target: float | None = 0.2) -> Path:
    cfg = tmp_path / "sowgate.toml"
    lines = [f'[store]\npath = "{store}"\n']
    if target is not None:
        lines.append(f"[positioning]\ntarget_spacing_m = {target}\n")
    cfg.write_text("".join(lines))
    return cfg


# ---------------------------------------------------------------- formats


def test_geojson_is_a_feature_collection_of_lon_lat_points_with_every_field() -> None:
    buf = io.StringIO()
    n = export_seeds(records(), "geojson", buf, quality_by_row(records(), 0.2))
    doc = json.loads(buf.getvalue())
    assert n == len(records()) == len(doc["features"])
    assert doc["type"] == "FeatureCollection"
    f = doc["features"][0]
    r = records()[0]
    assert f["geometry"] == {"type": "Point", "coordinates": [r.lon, r.lat]}
    assert f["id"] == 1
    assert f["properties"]["row"] == 1 and f["properties"]["fix"] == "rtk_float"
    assert f["properties"]["utc"] == "2026-05-02T06:00:00.000000Z"
    assert set(f["properties"]) == set(CSV_FIELDS)


def test_geojson_carries_the_per_row_quality_summary() -> None:
    buf = io.StringIO()
    export_seeds(records(), "geojson", buf, quality_by_row(records(), 0.2))
    q = json.loads(buf.getvalue())["quality"]
    assert q["1"]["n"] == 7
    assert q["1"]["multiples_index"] == pytest.approx(100 / 7)
    assert q["1"]["miss_index"] == pytest.approx(100 / 7)
    assert q["1"]["quality_of_feed_index"] == pytest.approx(500 / 7)
    assert q["2"]["quality_of_feed_index"] == pytest.approx(100.0)


def test_an_empty_export_is_still_valid_geojson() -> None:
    buf = io.StringIO()
    assert export_seeds([], "geojson", buf) == 0
    assert json.loads(buf.getvalue()) == {"type": "FeatureCollection", "features": []}


def test_csv_has_a_header_and_one_line_per_seed_with_blanks_for_none() -> None:
    buf = io.StringIO()
    export_seeds(records(), "csv", buf)
    rows = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert list(rows[0]) == CSV_FIELDS
    assert len(rows) == len(records())
    assert rows[0]["spacing_m"] == "" and rows[1]["spacing_m"] == "0.2"
    assert rows[3]["heading_deg"] == "" and rows[4]["extrapolated"] == "True"


def test_quality_csv_lists_every_row() -> None:
    buf = io.StringIO()
    export_quality_csv(quality_by_row(records(), 0.2), buf)
    rows = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert [r["row"] for r in rows] == ["1", "2"]
    assert float(rows[1]["quality_of_feed_index"]) == pytest.approx(100.0)


def test_an_unknown_format_is_refused() -> None:
    with pytest.raises(ExportError, match="unknown export format"):
        export_seeds(records(), "kml", io.StringIO())  # type: ignore[arg-type]


# ---------------------------------------------------------------- filters


def test_times_are_iso_and_naive_means_utc() -> None:
    assert parse_time("2026-05-02T06:00:03", "since") == T0 + timedelta(seconds=3)
    assert parse_time("2026-05-02T08:00:00+02:00", "since") == T0
    assert parse_time("2026-05-02T06:00:00Z", "since") == T0
    with pytest.raises(ExportError, match="--since: not an ISO 8601 time"):
        parse_time("yesterday", "since")


def test_rows_are_checked_against_the_machine() -> None:
    assert parse_rows("1, 3", 6) == [1, 3]
    with pytest.raises(ExportError, match=r"rows must be in 1\.\.6"):
        parse_rows("0,7", 6)
    with pytest.raises(ExportError, match="comma-separated"):
        parse_rows("one", 6)


# ---------------------------------------------------------------- the command


def test_export_command_writes_geojson_from_the_store(tmp_path: Path, store_file: Path) -> None:
    out = tmp_path / "map.geojson"
    assert main_export(args(out, config_for(tmp_path, store_file))) == 0
    doc = json.loads(out.read_text())
    assert len(doc["features"]) == len(drops())
    assert doc["quality"]["1"]["x_ref_m"] == pytest.approx(0.2)
    assert [f["id"] for f in doc["features"]] == sorted(f["id"] for f in doc["features"])


def test_export_command_filters_by_row_and_time(tmp_path: Path, store_file: Path) -> None:
    out = tmp_path / "map.geojson"
    cfg = config_for(tmp_path, store_file)
    a = args(out, cfg, rows="2", since="2026-05-02T06:00:09Z", until="2026-05-02T06:00:11Z")
    assert main_export(a) == 0
    feats = json.loads(out.read_text())["features"]
    assert [(f["properties"]["row"], f["properties"]["utc"][17:19]) for f in feats] == [
        (2, "09"),
        (2, "10"),
    ]


def test_export_command_csv_writes_a_quality_sidecar(tmp_path: Path, store_file: Path) -> None:
    out = tmp_path / "seeds.csv"
    assert main_export(args(out, config_for(tmp_path, store_file), format="csv")) == 0
    assert len(out.read_text().splitlines()) == len(drops()) + 1
    sidecar = Path(f"{out}.quality.csv").read_text().splitlines()
    assert sidecar[0].startswith("row,n,x_ref_m") and len(sidecar) == 3


def test_export_uses_the_state_directory_by_default(
    tmp_path: Path, store_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SOWGATE_STATE_DIR", str(store_file.parent))
    out = tmp_path / "map.geojson"
    assert main_export(args(out)) == 0
    # without a target spacing the median is x_ref
    assert json.loads(out.read_text())["quality"]["2"]["x_ref_m"] == pytest.approx(0.2)


def test_export_without_a_store_fails_with_a_clear_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "map.geojson"
    code = main_export(args(out, config_for(tmp_path, tmp_path / "missing.sqlite3")))
    assert code == 1
    assert "no record store at" in capsys.readouterr().err
    assert not out.exists()


def test_bad_filters_exit_2_and_leave_no_file(
    tmp_path: Path, store_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "map.geojson"
    cfg = config_for(tmp_path, store_file)
    assert main_export(args(out, cfg, since="2026-05-02T07:00:00Z", until="2026-05-02")) == 2
    assert "--until must be later than --since" in capsys.readouterr().err
    assert main_export(args(out, cfg, rows="9")) == 2
    assert not out.exists()


def test_sowgate_export_on_the_command_line(tmp_path: Path, store_file: Path) -> None:
    out = tmp_path / "map.csv"
    cfg = config_for(tmp_path, store_file)
    code = cli_main(
        ["export", "--format", "csv", "--output", str(out), "--config", str(cfg), "--rows", "1"]
    )
    assert code == 0
    assert len(out.read_text().splitlines()) == len(SPACINGS[1]) + 1


def test_as_applied_log_exports_as_geojson_and_csv(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from gateway.app.cli import main
    from gateway.metering.prescription import AsAppliedLog, AsAppliedRow

    monkeypatch.setenv("SOWGATE_STATE_DIR", str(tmp_path))
    log = AsAppliedLog(tmp_path / "as_applied.csv")
    log.record(
        AsAppliedRow("2026-04-20T08:00:00+00:00", 125.3, 43.8, "seed", "wheat", 225.0, 224.1)
    )
    log.record(
        AsAppliedRow("2026-04-20T08:00:01+00:00", 125.30001, 43.8, "seed", "wheat", 300.0, None)
    )
    out = tmp_path / "applied.geojson"
    assert main(["export", "--what", "as-applied", "--output", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert [f["properties"]["target_kg_ha"] for f in doc["features"]] == [225.0, 300.0]
    assert doc["features"][0]["geometry"]["coordinates"][:2] == [125.3, 43.8]
    csv_out = tmp_path / "applied.csv"
    assert (
        main(["export", "--what", "as-applied", "--format", "csv", "--output", str(csv_out)]) == 0
    )
    assert csv_out.read_text().splitlines()[0].startswith("time,lon,lat,channel")


def test_missing_as_applied_log_is_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from gateway.app.cli import main

    monkeypatch.setenv("SOWGATE_STATE_DIR", str(tmp_path))
    assert main(["export", "--what", "as-applied", "--output", str(tmp_path / "x.csv")]) == 1
    assert "no as-applied log at" in capsys.readouterr().err


def test_as_applied_export_honours_since_and_until(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from gateway.app.cli import main
    from gateway.metering.prescription import AsAppliedLog, AsAppliedRow

    monkeypatch.setenv("SOWGATE_STATE_DIR", str(tmp_path))
    log = AsAppliedLog(tmp_path / "as_applied.csv")
    for second in range(5):
        log.record(AsAppliedRow(f"2026-04-20T08:00:0{second}.000+00:00", 125.3, 43.8, "seed",
                                "wheat", 200.0 + second, None))
    out = tmp_path / "part.csv"
    argv = ["export", "--what", "as-applied", "--format", "csv", "--output", str(out),
            "--since", "2026-04-20T08:00:01Z", "--until", "2026-04-20T08:00:03Z"]
    assert main(argv) == 0
    targets = [line.split(",")[5] for line in out.read_text().splitlines()[1:]]
    assert targets == ["201.0", "202.0"]
    assert "wrote 2 as-applied rows" in capsys.readouterr().err
    assert main([*argv[:-4], "--since", "yesterday"]) == 2  # a bad time is a usage error


# ---------------------------------------------------------------- format from the file name


@pytest.mark.parametrize(
    ("name", "kind"),
    [("seeds.csv", "csv"), ("SEEDS.CSV", "csv"), ("map.geojson", "geojson"),
     ("map.json", "geojson")],
)
def test_the_format_comes_from_the_output_extension(
    tmp_path: Path, store_file: Path, name: str, kind: str
) -> None:
    out = tmp_path / name
    argv = ["export", "--output", str(out), "--config", str(config_for(tmp_path, store_file))]
    assert cli_main(argv) == 0
    text = out.read_text()
    if kind == "csv":
        assert text.splitlines()[0] == ",".join(CSV_FIELDS)
    else:
        assert json.loads(text)["type"] == "FeatureCollection"


def test_as_applied_to_a_csv_file_is_csv_as_the_readme_shows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`sowgate export --what as-applied --output applied.csv` used to write GeoJSON."""
    from gateway.metering.prescription import AsAppliedLog, AsAppliedRow

    monkeypatch.setenv("SOWGATE_STATE_DIR", str(tmp_path))
    AsAppliedLog(tmp_path / "as_applied.csv").record(
        AsAppliedRow("2026-04-20T08:00:00+00:00", 125.3, 43.8, "seed", "wheat", 225.0, 224.1)
    )
    out = tmp_path / "applied.csv"
    assert cli_main(["export", "--what", "as-applied", "--output", str(out)]) == 0
    assert out.read_text().splitlines()[0].startswith("time,lon,lat,channel")


@pytest.mark.parametrize(
    ("name", "message"),
    [("seeds.txt", "cannot tell the format of 'seeds.txt'"),
     ("seeds", "cannot tell the format of 'seeds'"),
     ("seeds.shp", "shapefile export is not supported")],
)
def test_an_unknown_extension_is_a_usage_error_naming_the_choices(
    tmp_path: Path, store_file: Path, capsys: pytest.CaptureFixture[str], name: str, message: str
) -> None:
    out = tmp_path / name
    argv = ["export", "--output", str(out), "--config", str(config_for(tmp_path, store_file))]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "--format" in err and ".geojson" in err, err
    assert not out.exists()


def test_an_explicit_format_wins_over_the_extension(tmp_path: Path, store_file: Path) -> None:
    out = tmp_path / "seeds.dat"
    cfg = config_for(tmp_path, store_file)
    assert cli_main(["export", "--format", "csv", "--output", str(out), "--config", str(cfg)]) == 0
    assert out.read_text().startswith("id,")


def test_standard_output_without_a_format_is_geojson(
    tmp_path: Path, store_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = config_for(tmp_path, store_file)
    assert cli_main(["export", "--output", "-", "--config", str(cfg)]) == 0
    assert json.loads(capsys.readouterr().out)["type"] == "FeatureCollection"


def test_the_csv_quality_sidecar_is_announced(
    tmp_path: Path, store_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "seeds.csv"
    cfg = config_for(tmp_path, store_file)
    assert cli_main(["export", "--output", str(out), "--config", str(cfg)]) == 0
    err = capsys.readouterr().err
    assert f"{out}.quality.csv" in err and "spacing quality" in err, err


def test_export_reads_the_store_in_the_state_dir_given(
    tmp_path: Path, store_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What `sowgate demo` tells the user to run next: `--state-dir sowgate-demo`."""
    monkeypatch.setenv("SOWGATE_STATE_DIR", str(tmp_path / "elsewhere"))
    out = tmp_path / "seeds.csv"
    assert cli_main(["export", "--state-dir", str(store_file.parent), "--output", str(out)]) == 0
    assert len(out.read_text().splitlines()) == len(drops()) + 1


def test_export_help_says_how_the_format_is_chosen(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli_main(["export", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "default: from the --output extension" in out
    assert ".quality.csv" in out


def test_features_carry_exactly_the_records_own_fields_without_a_model_per_seed() -> None:
    """The writer builds each feature from the stored row; its properties are still the
    record's JSON dump, value for value (what the model-per-seed writer produced)."""
    buf = io.StringIO()
    export_seeds(records(), "geojson", buf)
    features = json.loads(buf.getvalue())["features"]
    for f, r in zip(features, records(), strict=True):
        want = r.model_dump(mode="json")
        want["utc"] = r.utc.isoformat(timespec="microseconds").replace("+00:00", "Z")
        assert f["properties"] == want
        assert list(f["properties"]) == list(want)  # the same order too
    rows = list(csv.DictReader(io.StringIO(_csv_text())))
    for row, r in zip(rows, records(), strict=True):
        assert row["extrapolated"] == str(r.extrapolated)
        assert row["heading_deg"] == ("" if r.heading_deg is None else str(r.heading_deg))
        assert row["spacing_m"] == ("" if r.spacing_m is None else str(r.spacing_m))


def _csv_text() -> str:
    buf = io.StringIO()
    export_seeds(records(), "csv", buf)
    return buf.getvalue()


def test_float_and_extrapolated_seeds_carry_the_receivers_stated_accuracy() -> None:
    """RTK fixed 0.01 m, float 0.4 m (UM982 datasheet), +0.1 m extrapolated: in the record,
    the published batch, the CSV and the GeoJSON alike."""
    recs = records()
    assert [r.accuracy_m for r in recs[:5]] == [0.4, 0.01, 0.4, 0.01, 0.5]
    buf = io.StringIO()
    export_seeds(recs, "csv", buf)
    rows = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert [(r["fix"], r["extrapolated"], r["accuracy_m"]) for r in rows[:5]] == [
        ("rtk_float", "False", "0.4"), ("rtk_fixed", "False", "0.01"),
        ("rtk_float", "False", "0.4"), ("rtk_fixed", "False", "0.01"),
        ("rtk_float", "True", "0.5"),
    ]
    buf = io.StringIO()
    export_seeds(recs, "geojson", buf)
    props = [f["properties"] for f in json.loads(buf.getvalue())["features"]]
    assert [p["accuracy_m"] for p in props[:2]] == [0.4, 0.01]
    no_fix = SeedDrop(row=1, utc=T0, lat=45.0, lon=126.0, fix="none", speed_kmh=8.0)
    assert no_fix.accuracy_m is None
