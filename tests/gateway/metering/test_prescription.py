"""Prescription maps: look-ups (inside, outside, borders, holes), look-ahead, bad maps."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any

import pytest
import shapefile

from gateway.config import Settings, parse_config
from gateway.core.errors import GatewayError
from gateway.metering.prescription import (
    AsAppliedLog,
    AsAppliedRow,
    FarFromFieldWatch,
    Pose,
    PrescriptionError,
    PrescriptionMap,
    load_prescription,
    offset_position,
)

DEG_PER_M = 1 / 111_320
WGS84_PRJ = (
    'GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137,298.257223563]],'
    'PRIMEM["Greenwich",0],UNIT["Degree",0.0174532925199433]]'
)
UTM_PRJ = 'PROJCS["WGS_1984_UTM_Zone_50N",GEOGCS["GCS_WGS_1984"],PROJECTION["Transverse_Mercator"]]'


def square(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]


def feature(rings: list[list[list[float]]], **props: Any) -> dict[str, Any]:
    return {"type": "Feature", "geometry": {"type": "Polygon", "coordinates": rings},
            "properties": props}


def fc(*features: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"type": "FeatureCollection", "features": list(features), **extra}


@pytest.fixture
def field_map() -> PrescriptionMap:
    """West zone 100, east zone 200 sharing the border x=1; the west zone has a hole."""
    west = feature([square(0, 0, 1, 1), square(0.4, 0.4, 0.6, 0.6)], seed=100.0, deep=250)
    east = feature([square(1, 0, 2, 1)], seed=200.0, deep=320)
    return PrescriptionMap.from_geojson(fc(west, east), ["seed", "deep"])


def test_inside_a_zone_gets_its_rate(field_map: PrescriptionMap) -> None:
    assert field_map.rate_at(0.2, 0.2, "seed", 150.0) == 100.0
    assert field_map.rate_at(1.5, 0.5, "deep", 300.0) == 320.0


def test_outside_the_map_gets_the_default_rate(field_map: PrescriptionMap) -> None:
    assert field_map.rate_at(3.0, 3.0, "seed", 150.0) == 150.0
    assert field_map.rate_at(-0.001, 0.5, "seed", 150.0) == 150.0


def test_inside_a_hole_is_outside_the_polygon(field_map: PrescriptionMap) -> None:
    assert field_map.rate_at(0.5, 0.5, "seed", 150.0) == 150.0


def test_on_a_hole_edge_belongs_to_the_polygon(field_map: PrescriptionMap) -> None:
    assert field_map.rate_at(0.4, 0.5, "seed", 150.0) == 100.0


def test_on_the_outer_edge_belongs_to_the_polygon(field_map: PrescriptionMap) -> None:
    assert field_map.rate_at(0.0, 0.5, "seed", 150.0) == 100.0
    assert field_map.rate_at(2.0, 1.0, "seed", 150.0) == 200.0  # corner


def test_on_a_shared_border_the_first_zone_in_the_file_wins(field_map: PrescriptionMap) -> None:
    assert field_map.rate_at(1.0, 0.5, "seed", 150.0) == 100.0
    swapped = PrescriptionMap.from_geojson(
        fc(feature([square(1, 0, 2, 1)], seed=200.0), feature([square(0, 0, 1, 1)], seed=100.0)),
        ["seed"],
    )
    assert swapped.rate_at(1.0, 0.5, "seed", 150.0) == 200.0


def test_multipolygon_zones_work() -> None:
    mp = {"type": "Feature", "properties": {"r": 5},
          "geometry": {"type": "MultiPolygon",
                       "coordinates": [[square(0, 0, 1, 1)], [square(2, 2, 3, 3)]]}}
    m = PrescriptionMap.from_geojson(fc(mp), ["r"])
    assert m.rate_at(2.5, 2.5, "r", 0.0) == 5.0 and m.rate_at(1.5, 1.5, "r", 0.0) == 0.0


def test_offset_moves_along_heading() -> None:
    lon, lat = offset_position(10.0, 0.0, 90.0, 111.32)  # 111.32 m east at the equator
    assert lon == pytest.approx(10.001, abs=1e-7) and lat == pytest.approx(0.0, abs=1e-9)
    lon, lat = offset_position(10.0, 0.0, 0.0, 0.0, right_m=111.32)  # right of north = east
    assert lon == pytest.approx(10.001, abs=1e-7)


def test_look_ahead_uses_speed_heading_and_outlet_offset() -> None:
    """Zone starts 10 m east; heading east at 9 km/h (2.5 m/s) with 2 s look-ahead = 5 m."""
    m = PrescriptionMap.from_geojson(
        fc(feature([square(10 * DEG_PER_M, -1, 1, 1)], seed=180.0)), ["seed"])
    at_6m = Pose(6 * DEG_PER_M, 0.0, 90.0, 9.0)
    assert m.rate_ahead(at_6m, "seed", 225.0, lookahead_s=2.0) == 180.0
    assert m.rate_ahead(at_6m, "seed", 225.0, lookahead_s=0.0) == 225.0
    # outlets 2 m behind the antenna: they reach the zone 2 m later
    assert m.rate_ahead(at_6m, "seed", 225.0, lookahead_s=2.0, outlet_behind_m=2.0) == 225.0


def test_unknown_attribute_at_lookup_is_an_error(field_map: PrescriptionMap) -> None:
    with pytest.raises(PrescriptionError, match="fert"):
        field_map.rate_at(0.2, 0.2, "fert", 1.0)


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        (fc(feature([square(0, 0, 1, 1)], other=1)), r"feature 0: no rate attribute 'seed'"),
        (fc(feature([square(0, 0, 1, 1)], seed="lots")), "not a number"),
        (fc(feature([square(0, 0, 1, 1)], seed=-5)), r"must be 0\.\.2000 kg/ha"),
        (fc(feature([square(0, 0, 1, 1)], seed=1e308)), r"must be 0\.\.2000 kg/ha.*1e\+308"),
        (fc(feature([square(0, 0, 1, 1)], seed=None)), "empty"),
        (fc(feature([[[0, 0], [1, 1], [1, 0], [0, 1], [0, 0]]], seed=1)), "invalid geometry"),
        (fc({"type": "Feature", "geometry": {"type": "Point", "coordinates": [0, 0]},
             "properties": {"seed": 1}}), "Point"),
        (fc(feature([square(0, 0, 1, 1)], seed=1),
            crs={"type": "name", "properties": {"name": "EPSG:32650"}}), "not WGS84"),
        (fc(feature([square(500000, 4000000, 500100, 4000100)], seed=1)), "projected"),
        (fc(), "no polygons"),
        ({"type": "Polygon"}, "FeatureCollection"),
        (fc({"type": "Feature", "properties": {"seed": 1}}), "missing geometry"),
    ],
)
def test_bad_maps_are_rejected_with_a_clear_error(doc: dict[str, Any], match: str) -> None:
    with pytest.raises(PrescriptionError, match=match) as exc:
        PrescriptionMap.from_geojson(doc, ["seed"], source="rx.geojson")
    assert isinstance(exc.value, GatewayError)
    assert "rx.geojson" in str(exc.value)


def test_explicit_wgs84_crs_is_accepted() -> None:
    doc = fc(feature([square(0, 0, 1, 1)], seed=1),
             crs={"type": "name", "properties": {"name": "urn:ogc:def:crs:OGC:1.3:CRS84"}})
    assert PrescriptionMap.from_geojson(doc, ["seed"]).rate_at(0.5, 0.5, "seed", 0) == 1


def test_load_geojson_file_and_file_errors(tmp_path: Path) -> None:
    p = tmp_path / "rx.geojson"
    p.write_text(json.dumps(fc(feature([square(0, 0, 1, 1)], seed=7))))
    assert PrescriptionMap.load(p, ["seed"]).rate_at(0.5, 0.5, "seed", 0) == 7
    with pytest.raises(PrescriptionError, match="not found"):
        PrescriptionMap.load(tmp_path / "missing.geojson", ["seed"])
    (tmp_path / "bad.geojson").write_text("{nope")
    with pytest.raises(PrescriptionError, match="not valid GeoJSON"):
        PrescriptionMap.load(tmp_path / "bad.geojson", ["seed"])
    (tmp_path / "rx.kml").write_text("<kml/>")
    with pytest.raises(PrescriptionError, match="unsupported"):
        PrescriptionMap.load(tmp_path / "rx.kml", ["seed"])


def test_a_map_nested_deeper_than_any_geojson_is_a_clear_error(tmp_path: Path) -> None:
    """200 000 levels of JSON crashed ``run`` and ``check-config`` with a RecursionError."""
    p = tmp_path / "deep.geojson"
    p.write_text('{"type": "FeatureCollection", "features": ' + "[" * 200_000 + "]" * 200_000
                 + "}")
    with pytest.raises(PrescriptionError, match=r"deep\.geojson: not valid GeoJSON: nested too"):
        PrescriptionMap.load(p, ["seed"])


def test_a_map_that_is_not_a_regular_file_is_refused_without_waiting(tmp_path: Path) -> None:
    fifo = tmp_path / "rx.geojson"
    os.mkfifo(fifo)  # opened for reading, a FIFO blocks until a writer comes
    with pytest.raises(PrescriptionError, match=r"rx\.geojson: not a usable map file: a FIFO"):
        PrescriptionMap.load(fifo, ["seed"])
    with pytest.raises(PrescriptionError, match="a device, not a file"):
        PrescriptionMap.load(_zero(tmp_path), ["seed"])


def _zero(tmp_path: Path) -> Path:
    link = tmp_path / "zero.geojson"
    link.symlink_to("/dev/zero")
    return link


def _configured(path: str | None, *attrs: str | None) -> Settings:
    """Settings with ``[prescription]`` on at ``path`` and one channel per rate attribute."""
    prescription: dict[str, Any] = {"enabled": True}
    if path is not None:
        prescription["path"] = path
    return parse_config({
        "prescription": prescription,
        "channel": [
            {"name": f"c{i}", "node_id": i + 1, "target_rate_kg_ha": 100,
             "prescription_attribute": attr}
            for i, attr in enumerate(attrs)
        ],
    })


def test_the_configured_map_loads_with_every_channels_rate_attribute(tmp_path: Path) -> None:
    p = tmp_path / "rx.geojson"
    p.write_text(json.dumps(fc(feature([square(0, 0, 1, 1)], seed=7, deep=9))))
    m = load_prescription(_configured(str(p), "seed", None, "deep"))
    assert m is not None and m.attributes == {"seed", "deep"}
    assert load_prescription(parse_config({})) is None  # [prescription] off: no map


@pytest.mark.parametrize(
    ("path", "attrs", "problem"),
    [
        (None, ("seed",), "prescription.path: required when prescription.enabled"),
        ("rx.geojson", (None,),
         "prescription.enabled: no [[channel]] has a prescription_attribute to read"),
        ("rx.geojson", ("other",), "prescription.path: {dir}/rx.geojson: feature 0: no rate "
         "attribute 'other' (has: seed)"),
        ("missing.geojson", ("seed",),
         "prescription.path: {dir}/missing.geojson: prescription map not found"),
    ],
)
def test_an_unusable_configured_map_names_the_key_to_fix(
    tmp_path: Path, path: str | None, attrs: tuple[str | None, ...], problem: str
) -> None:
    (tmp_path / "rx.geojson").write_text(json.dumps(fc(feature([square(0, 0, 1, 1)], seed=7))))
    settings = _configured(None if path is None else str(tmp_path / path), *attrs)
    with pytest.raises(PrescriptionError) as info:
        load_prescription(settings)
    assert str(info.value) == problem.format(dir=tmp_path)


def write_shapefile(base: Path, prj: str | None, coords: list[list[float]]) -> Path:
    with shapefile.Writer(str(base), shapeType=shapefile.POLYGON) as w:
        w.field("SEED", "N", decimal=2)
        w.poly([coords])
        w.record(165.5)
    if prj is not None:
        base.with_suffix(".prj").write_text(prj)
    return base.with_suffix(".shp")


def test_shapefile_with_wgs84_prj_loads(tmp_path: Path) -> None:
    shp = write_shapefile(tmp_path / "rx", WGS84_PRJ, square(116.0, 40.0, 116.01, 40.01))
    m = PrescriptionMap.load(shp, ["SEED"])
    assert m.rate_at(116.005, 40.005, "SEED", 0.0) == pytest.approx(165.5)


def test_shapefile_in_a_projected_crs_is_rejected(tmp_path: Path) -> None:
    shp = write_shapefile(tmp_path / "rx", UTM_PRJ, square(116.0, 40.0, 116.01, 40.01))
    with pytest.raises(PrescriptionError, match="not WGS84"):
        PrescriptionMap.load(shp, ["SEED"])


def test_shapefile_without_prj_but_metre_coordinates_is_rejected(tmp_path: Path) -> None:
    shp = write_shapefile(tmp_path / "rx", None, square(450000, 4400000, 450100, 4400100))
    with pytest.raises(PrescriptionError, match="projected"):
        PrescriptionMap.load(shp, ["SEED"])


def test_as_applied_log_exports_csv_and_geojson(tmp_path: Path) -> None:
    path = tmp_path / "as_applied.csv"
    log = AsAppliedLog(path)
    rows = [AsAppliedRow("2026-04-01T08:00:00.000+00:00", 116.1, 40.2, "seed", "wheat", 225.0,
                         224.1),
            AsAppliedRow("2026-04-01T08:00:01.000+00:00", 116.2, 40.3, "deep", "npk", 300.0,
                         None)]
    for r in rows:
        log.record(r)
    parsed = list(csv.DictReader(io.StringIO(log.to_csv())))
    assert [p["channel"] for p in parsed] == ["seed", "deep"]
    assert float(parsed[0]["applied_kg_ha"]) == 224.1
    assert path.read_text() == log.to_csv()  # the file on disk has the same rows
    gj = log.to_geojson()
    assert gj["features"][1]["geometry"]["coordinates"] == [116.2, 40.3]
    assert gj["features"][1]["properties"]["applied_kg_ha"] is None


def test_as_applied_memory_is_capped() -> None:
    log = AsAppliedLog(max_rows=3)
    for i in range(5):
        log.record(AsAppliedRow(str(i), 0, 0, "c", "p", 1, 1))
    assert [r.time for r in log.rows] == ["2", "3", "4"]


def test_a_failing_as_applied_write_is_reported_not_raised(tmp_path: Path) -> None:
    """Disk full / card pulled: metering must go on; the log says so once, then recovers."""
    reports: list[str | None] = []
    log = AsAppliedLog(tmp_path / "gone" / "as_applied.csv", on_error=reports.append)
    for i in range(3):
        log.record(AsAppliedRow(str(i), 0, 0, "c", "p", 1, 1))  # directory missing
    assert len(reports) == 1 and reports[0] is not None and "as_applied.csv" in reports[0]
    assert log.write_error is not None and len(log.rows) == 3  # kept in memory
    (tmp_path / "gone").mkdir()
    log.record(AsAppliedRow("3", 0, 0, "c", "p", 1, 1))
    assert reports[-1] is None and log.write_error is None
    assert (tmp_path / "gone" / "as_applied.csv").read_text().splitlines()[1].startswith("3,")


def test_as_applied_position_is_the_outlets_not_the_antenna() -> None:
    from types import SimpleNamespace

    log = AsAppliedLog()
    ch = SimpleNamespace(name="seed", product="wheat", outlet_behind_m=3.0, outlet_lateral_m=1.0)
    pose = Pose(lon=116.0, lat=40.0, heading_deg=0.0, speed_kmh=5.0)  # heading north
    row = log.record_channel(pose, ch, 225.0, 224.0)
    assert row.lat == pytest.approx(40.0 - 3.0 / 111_320.0)
    assert row.lon == pytest.approx(116.0 + 1.0 / (111_320.0 * math.cos(math.radians(40.0))))


class _Epoch:
    def __init__(self, lon: float, lat: float, t: float, fix: str = "rtk_fixed") -> None:
        self.lon, self.lat, self.t_mono, self.fix = lon, lat, t, fix


def test_a_map_far_from_the_machine_raises_far_from_field_and_near_clears_it() -> None:
    """A map 100 km from the field was taken without a word (default rates everywhere)."""
    from gateway.core.alarms import AlarmBoard

    rx = PrescriptionMap.from_geojson(fc(feature([square(10.0, 50.0, 10.01, 50.01)], seed=7)),
                                      ["seed"], source="rx.geojson")
    assert rx.distance_m(10.005, 50.005) == 0.0
    assert rx.distance_m(10.005, 50.01 + 100_000 / 111_320) == pytest.approx(100_000, rel=1e-3)
    alarms = AlarmBoard("m")
    watch = FarFromFieldWatch(rx, alarms)
    watch.on_epoch(_Epoch(10.005, 50.9, 0.0, fix="none"))  # no fix: no judgement
    assert not alarms.is_active("prescription.far_from_field")
    watch.on_epoch(_Epoch(10.005, 50.91, 1.0))  # the first fixed position: ~100 km north
    (alarm,) = [a for a in alarms.active if a.code == "prescription.far_from_field"]
    assert "rx.geojson is 100.2 km from the machine" in alarm.message, alarm.message
    watch.on_epoch(_Epoch(10.005, 50.02, 1.5))  # within a second: not checked again
    assert alarms.is_active("prescription.far_from_field")
    watch.on_epoch(_Epoch(10.005, 50.02, 2.5))  # 1 km from the map: the farmyard, fine
    assert not alarms.is_active("prescription.far_from_field")


def test_the_extent_is_described_for_check_config() -> None:
    rx = PrescriptionMap.from_geojson(fc(feature([square(10.0, 50.0, 10.01, 50.01)], seed=7)),
                                      ["seed"])
    width, height = rx.size_km()
    assert width == pytest.approx(0.716, abs=0.01) and height == pytest.approx(1.113, abs=0.01)
    assert rx.extent_note() == "extent 0.72 x 1.11 km around lat 50.00500, lon 10.00500"
