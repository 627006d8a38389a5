"""Prescription maps: which rate each product gets where, and the as-applied record.

A map is a set of polygons (GeoJSON or ESRI Shapefile) in WGS84 lon/lat, each carrying one
numeric attribute per product (e.g. ``seed_kg_ha``, ``deep_kg_ha``). Outside every polygon the
channel's configured default rate applies, so leaving the field edge never stops the drill.

Border rule: a point on a polygon's edge (outer ring or a hole's ring) belongs to that
polygon (shapely ``covers``). Where zones touch, the zone listed first in the file wins,
so a fitter can predict the result from the file alone. A point strictly inside a hole is
outside that polygon.

Look-ahead: the metering chain needs time (controller response, seed travel) before a rate
change reaches the ground, so the rate is looked up where the outlets *will be* after
``lookahead_s`` at the current speed along the current heading.

Bad maps fail at load with ``PrescriptionError`` naming the feature and the problem: missing
rate attribute, non-numeric, negative or absurd rate (above 2 000 kg/ha), a file that is not a
regular file or is huge, JSON nested too deep, invalid or non-polygon geometry, a CRS other
than WGS84, or coordinates that look projected (metres instead of degrees).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import shapefile
from shapely.geometry import MultiPolygon, Point, Polygon, shape
from shapely.strtree import STRtree
from shapely.validation import explain_validity

from gateway.config.metering import MAX_RATE_KG_HA
from gateway.core.errors import GatewayError
from gateway.core.files import UnreadableFile, read_regular_file, regular_file_problem

if TYPE_CHECKING:
    from gateway.config import Settings

log = logging.getLogger(__name__)

METRES_PER_DEG_LAT = 111_320.0
MAX_FEATURES = 100_000
# a map farther than this from the machine's fixed positions is another field's (alarm); the
# drive from the farmyard to a field stays well inside it
FAR_FROM_FIELD_M = 20_000.0
# check-config notes a map wider than this: zones of several farms, or a stray polygon
WIDE_MAP_KM = 20.0
MAX_MAP_BYTES = 256_000_000  # a whole farm's map is a few MB; more is not a map
AS_APPLIED_MAX_ROWS = 100_000  # in-memory as-applied rows before the oldest are dropped
WGS84_NAMES = (
    "EPSG:4326",
    "EPSG::4326",
    "urn:ogc:def:crs:OGC:1.3:CRS84",
    "urn:ogc:def:crs:OGC::CRS84",
    "urn:ogc:def:crs:EPSG::4326",
    "CRS84",
    "WGS84",
)


class PrescriptionError(GatewayError):
    """The prescription map cannot be used; the message names file, feature and problem."""


@dataclass(frozen=True, slots=True)
class Pose:
    """Where the machine is and where it is going (GNSS antenna)."""

    lon: float
    lat: float
    heading_deg: float = 0.0  # clockwise from north
    speed_kmh: float = 0.0


@dataclass(frozen=True, slots=True)
class Zone:
    index: int
    polygon: Polygon | MultiPolygon
    rates: Mapping[str, float]


def offset_position(
    lon: float, lat: float, heading_deg: float, forward_m: float, right_m: float = 0.0
) -> tuple[float, float]:
    """Move a lon/lat by metres ahead/right of a heading (flat earth; fine over < 1 km)."""
    h = math.radians(heading_deg)
    north = forward_m * math.cos(h) - right_m * math.sin(h)
    east = forward_m * math.sin(h) + right_m * math.cos(h)
    dlat = north / METRES_PER_DEG_LAT
    dlon = east / (METRES_PER_DEG_LAT * max(math.cos(math.radians(lat)), 1e-6))
    return lon + dlon, lat + dlat


def _check_crs(crs: Any, source: str) -> None:
    if crs is None:
        return
    name = None
    if isinstance(crs, dict):
        props = crs.get("properties", {})
        name = props.get("name") if isinstance(props, dict) else None
    if not isinstance(name, str) or name.strip() not in WGS84_NAMES:
        raise PrescriptionError(
            f"{source}: CRS {name or crs!r} is not WGS84 lon/lat; re-export the map as "
            "EPSG:4326 (GeoJSON's default)"
        )


def _check_degrees(geom: Polygon | MultiPolygon, source: str, index: int) -> None:
    minx, miny, maxx, maxy = geom.bounds
    if not (-180 <= minx <= maxx <= 180 and -90 <= miny <= maxy <= 90):
        raise PrescriptionError(
            f"{source}: feature {index}: coordinates {geom.bounds} are not lon/lat degrees "
            "(projected map?); re-export in WGS84 (EPSG:4326)"
        )


def _rate(value: Any, attr: str, source: str, index: int) -> float:
    if isinstance(value, bool) or value is None:
        raise PrescriptionError(f"{source}: feature {index}: rate attribute {attr!r} is empty")
    try:
        rate = float(value)
    except (TypeError, ValueError):
        raise PrescriptionError(
            f"{source}: feature {index}: rate attribute {attr!r} is not a number ({value!r})"
        ) from None
    if not math.isfinite(rate) or not 0 <= rate <= MAX_RATE_KG_HA:
        raise PrescriptionError(
            f"{source}: feature {index}: rate attribute {attr!r} must be 0..{MAX_RATE_KG_HA:g} "
            f"kg/ha (the range of a [[channel]] target_rate_kg_ha; got {value!r})"
        )
    return rate


def _polygon(geometry: Any, source: str, index: int) -> Polygon | MultiPolygon:
    try:
        geom = shape(geometry)
    except Exception as exc:  # shapely raises several types for malformed input
        raise PrescriptionError(f"{source}: feature {index}: unreadable geometry ({exc})") from None
    if not isinstance(geom, Polygon | MultiPolygon):
        raise PrescriptionError(
            f"{source}: feature {index}: geometry is {geom.geom_type}, need Polygon/MultiPolygon"
        )
    if geom.is_empty or not geom.is_valid:
        reason = explain_validity(geom) if not geom.is_empty else "empty"
        raise PrescriptionError(f"{source}: feature {index}: invalid geometry ({reason})")
    _check_degrees(geom, source, index)
    return geom


class PrescriptionMap:
    """Rate zones with an STRtree index; look-ups are pure and cheap (called at 10 Hz)."""

    def __init__(self, zones: Sequence[Zone], source: str = "<map>") -> None:
        if not zones:
            raise PrescriptionError(f"{source}: the map has no polygons")
        self.source = source
        # rates outside every zone, where the map says (an ISO-XML task's default or
        # out-of-field zone); an attribute not here falls back to the caller's default
        self.outside: dict[str, float] = {}
        # rates while the position is lost (an ISO-XML task's position-lost zone); an
        # attribute not here: the channel's own rate, as for any map
        self.position_lost: dict[str, float] = {}
        self.zones = list(zones)
        self._tree = STRtree([z.polygon for z in self.zones])
        self.attributes = set.intersection(*(set(z.rates) for z in self.zones))

    @classmethod
    def from_features(
        cls,
        features: Iterable[tuple[Any, Mapping[str, Any]]],
        attributes: Sequence[str],
        source: str = "<map>",
    ) -> PrescriptionMap:
        """Build from (geometry mapping, properties) pairs; every attribute must be present."""
        if not attributes:
            raise PrescriptionError(f"{source}: no rate attribute requested")
        zones = []
        for index, (geometry, props) in enumerate(features):
            if index >= MAX_FEATURES:
                raise PrescriptionError(f"{source}: more than {MAX_FEATURES} features")
            geom = _polygon(geometry, source, index)
            rates = {}
            for attr in attributes:
                if attr not in props:
                    have = ", ".join(sorted(props)) or "none"
                    raise PrescriptionError(
                        f"{source}: feature {index}: no rate attribute {attr!r} (has: {have})"
                    )
                rates[attr] = _rate(props[attr], attr, source, index)
            zones.append(Zone(index, geom, rates))
        return cls(zones, source)

    @classmethod
    def from_geojson(
        cls, doc: Mapping[str, Any], attributes: Sequence[str], source: str = "<geojson>"
    ) -> PrescriptionMap:
        if not isinstance(doc, Mapping) or doc.get("type") not in ("FeatureCollection", "Feature"):
            raise PrescriptionError(f"{source}: not a GeoJSON FeatureCollection")
        _check_crs(doc.get("crs"), source)
        feats = doc.get("features", []) if doc["type"] == "FeatureCollection" else [doc]
        if not isinstance(feats, list):
            raise PrescriptionError(f"{source}: 'features' must be a list")
        pairs = []
        for i, f in enumerate(feats):
            if not isinstance(f, Mapping) or f.get("geometry") is None:
                raise PrescriptionError(f"{source}: feature {i}: missing geometry")
            props = f.get("properties") or {}
            pairs.append((f["geometry"], props))
        return cls.from_features(pairs, attributes, source)

    @classmethod
    def load(cls, path: str | os.PathLike[str], attributes: Sequence[str]) -> PrescriptionMap:
        """Load ``.geojson``/``.json`` or ``.shp`` (with its .dbf/.shx, optional .prj), or an
        ISO-XML TaskData folder or zip (``gateway.metering.isoxml_prescription``)."""
        from gateway.metering.isoxml_prescription import is_taskdata

        p = Path(path)
        if not p.exists():
            raise PrescriptionError(f"{p}: prescription map not found")
        if is_taskdata(p):
            return cls._load_taskdata(p, attributes)
        # a FIFO would block the start for ever, /dev/zero would fill the memory
        problem = regular_file_problem(p, MAX_MAP_BYTES)
        if problem is not None:
            raise PrescriptionError(f"{p}: not a usable map file: {problem}")
        suffix = p.suffix.lower()
        if suffix in (".geojson", ".json"):
            try:
                doc = json.loads(read_regular_file(p, MAX_MAP_BYTES).decode("utf-8"))
            except UnreadableFile as exc:
                raise PrescriptionError(f"{p}: not a usable map file: {exc}") from None
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise PrescriptionError(f"{p}: not valid GeoJSON: {exc}") from None
            except RecursionError:
                # JSON nested 200 000 deep: not a map (GeoJSON nests 4 levels at most)
                raise PrescriptionError(
                    f"{p}: not valid GeoJSON: nested too deep (a map nests a few levels)"
                ) from None
            try:
                return cls.from_geojson(doc, attributes, str(p))
            except RecursionError:
                raise PrescriptionError(
                    f"{p}: not valid GeoJSON: a geometry nested too deep"
                ) from None
        if suffix == ".shp":
            return cls._load_shapefile(p, attributes)
        raise PrescriptionError(f"{p}: unsupported map format {suffix!r} (use .geojson or .shp)")

    @classmethod
    def _load_taskdata(cls, p: Path, attributes: Sequence[str]) -> PrescriptionMap:
        from gateway.metering.isoxml_prescription import (
            TaskDataError,
            count_per_area_products,
            read_taskdata,
        )

        try:
            plan = read_taskdata(p)
        except TaskDataError as exc:
            raise PrescriptionError(str(exc)) from None
        given = set.intersection(*(set(rates) for _, rates in plan.features))
        for attr in attributes:
            if attr in given:
                continue
            if attr in count_per_area_products(p):
                raise PrescriptionError(
                    f"{p}: {attr!r} is prescribed as seeds per area (DDI 000B); sowgate's "
                    "channels meter kg/ha and the plan gives no seed weight to convert it: "
                    "export the plan as mass per area (DDI 0006)"
                )
            have = ", ".join(sorted(given)) or "none"
            raise PrescriptionError(
                f"{p}: no mass-per-area rate {attr!r} in every zone (the zones give: {have}); "
                "[[channel]] prescription_attribute names the plan's product"
            )
        loaded = cls.from_features(plan.features, attributes, str(p))
        loaded.outside = {a: plan.outside[a] for a in attributes if a in plan.outside}
        loaded.position_lost = {
            a: plan.position_lost[a] for a in attributes if a in plan.position_lost
        }
        return loaded

    @classmethod
    def _load_shapefile(cls, p: Path, attributes: Sequence[str]) -> PrescriptionMap:
        prj = p.with_suffix(".prj")
        if prj.exists():
            wkt = prj.read_text(errors="replace").upper()
            if "PROJCS" in wkt or "PROJCRS" in wkt or "WGS" not in wkt:
                raise PrescriptionError(
                    f"{p}: .prj is not WGS84 lon/lat ({wkt[:60]}...); re-export as EPSG:4326"
                )
        try:
            reader = shapefile.Reader(str(p))
        except (shapefile.ShapefileException, OSError) as exc:
            raise PrescriptionError(f"{p}: cannot read shapefile: {exc}") from None
        with reader:
            pairs = [
                (sr.shape.__geo_interface__, sr.record.as_dict())
                for sr in reader.iterShapeRecords()
            ]
        return cls.from_features(pairs, attributes, str(p))

    def bounds(self) -> tuple[float, float, float, float]:
        """(min lon, min lat, max lon, max lat) of every zone."""
        boxes = [z.polygon.bounds for z in self.zones]
        return (min(b[0] for b in boxes), min(b[1] for b in boxes),
                max(b[2] for b in boxes), max(b[3] for b in boxes))

    def distance_m(self, lon: float, lat: float) -> float:
        """Metres from (lon, lat) to the map's extent (its bounding box; 0 inside it).
        Flat earth: a field-sized answer is exact enough, a wrong field's 100 km is 100 km."""
        min_lon, min_lat, max_lon, max_lat = self.bounds()
        d_lon = max(min_lon - lon, 0.0, lon - max_lon)
        d_lat = max(min_lat - lat, 0.0, lat - max_lat)
        east = d_lon * METRES_PER_DEG_LAT * max(math.cos(math.radians(lat)), 1e-6)
        return math.hypot(east, d_lat * METRES_PER_DEG_LAT)

    def size_km(self) -> tuple[float, float]:
        """(width east-west, height north-south) of the map's extent, km."""
        min_lon, min_lat, max_lon, max_lat = self.bounds()
        mid_lat = (min_lat + max_lat) / 2.0
        width = (max_lon - min_lon) * METRES_PER_DEG_LAT * math.cos(math.radians(mid_lat))
        return width / 1e3, (max_lat - min_lat) * METRES_PER_DEG_LAT / 1e3

    def extent_note(self) -> str:
        """Where the map lies and how big it is, for check-config's note."""
        min_lon, min_lat, max_lon, max_lat = self.bounds()
        width_km, height_km = self.size_km()
        return (f"extent {width_km:.2f} x {height_km:.2f} km around lat "
                f"{(min_lat + max_lat) / 2.0:.5f}, lon {(min_lon + max_lon) / 2.0:.5f}")

    def zone_at(self, lon: float, lat: float) -> Zone | None:
        pt = Point(lon, lat)
        hits = self._tree.query(pt, predicate="covered_by")  # pt covered_by polygon
        if len(hits) == 0:
            return None
        return self.zones[int(min(hits))]  # first in file order wins on shared borders

    def rate_at(self, lon: float, lat: float, attribute: str, default: float) -> float:
        if attribute not in self.attributes:
            raise PrescriptionError(f"{self.source}: map has no rate attribute {attribute!r}")
        zone = self.zone_at(lon, lat)
        if zone is None:
            return self.outside.get(attribute, default)
        return zone.rates[attribute]

    def rate_ahead(
        self,
        pose: Pose,
        attribute: str,
        default: float,
        lookahead_s: float,
        outlet_behind_m: float = 0.0,
        outlet_right_m: float = 0.0,
    ) -> float:
        """Rate where the outlets will be ``lookahead_s`` from now."""
        ahead = pose.speed_kmh / 3.6 * lookahead_s - outlet_behind_m
        lon, lat = offset_position(pose.lon, pose.lat, pose.heading_deg, ahead, outlet_right_m)
        return self.rate_at(lon, lat, attribute, default)


def load_prescription(settings: Settings) -> PrescriptionMap | None:
    """The map ``[prescription]`` configures, or None when it is off.

    The one place that turns the config into a map: the daemon's wiring (which alarms and
    sows at the default rates on an error) and ``sowgate check-config`` (which reports it)
    both call this, so they cannot disagree on what a usable map is. Every rate attribute a
    ``[[channel]]`` names must be in every zone.

    Raises ``PrescriptionError`` whose message starts with the key to fix:
    ``prescription.path: …`` (no path, or the file is not a usable map) or
    ``prescription.enabled: …`` (no channel reads a rate from the map).
    """
    section = settings.prescription
    if not section.enabled:
        return None
    if section.path is None:
        raise PrescriptionError("prescription.path: required when prescription.enabled")
    attributes = [c.prescription_attribute for c in settings.channel if c.prescription_attribute]
    if not attributes:
        raise PrescriptionError(
            "prescription.enabled: no [[channel]] has a prescription_attribute to read"
        )
    try:
        return PrescriptionMap.load(section.path, attributes)
    except PrescriptionError as exc:
        raise PrescriptionError(f"prescription.path: {exc}") from None


class FarFromFieldWatch:
    """``prescription.far_from_field``: the map lies far from where the machine is.

    A map 100 km from the machine was taken without a word, and outside its zones every
    channel sows its default rate: the field's map was not the one loaded. Each GNSS epoch with
    a fix (at most one a second) is compared with the map's extent; beyond ``far_m`` the alarm
    is raised (from the first fixed positions on), within it cleared (the drive from the
    farmyard to the field is well inside ``FAR_FROM_FIELD_M``).
    """

    def __init__(self, prescription: PrescriptionMap, alarms: Any,
                 far_m: float = FAR_FROM_FIELD_M, every_s: float = 1.0) -> None:
        self.map = prescription
        self.alarms = alarms
        self.far_m = far_m
        self.every_s = every_s
        self._checked_at = -math.inf
        self.distance_m: float | None = None

    def on_epoch(self, epoch: Any) -> None:
        """A GNSS epoch (``drivers.gnss_reader.GnssEpoch``: lon, lat, fix, t_mono)."""
        if epoch.fix == "none" or epoch.lat is None or epoch.lon is None:
            return
        if epoch.t_mono - self._checked_at < self.every_s:
            return
        self._checked_at = epoch.t_mono
        d = self.map.distance_m(epoch.lon, epoch.lat)
        far = d > self.far_m
        if far and not self.alarms.is_active("prescription.far_from_field"):
            log.warning("prescription map %s is %.1f km from the machine (lat %.5f, lon %.5f): "
                        "a map of another field?", self.map.source, d / 1e3, epoch.lat,
                        epoch.lon)
        self.distance_m = d
        self.alarms.set(
            "prescription.far_from_field", far,
            f"prescription map {self.map.source} is {d / 1e3:.1f} km from the machine: a map "
            "of another field? Outside its zones every channel sows its default rate",
            "warning",
        )


@dataclass(frozen=True, slots=True)
class AsAppliedRow:
    time: str  # ISO 8601 UTC
    lon: float
    lat: float
    channel: str
    product: str
    target_kg_ha: float
    applied_kg_ha: float | None


AS_APPLIED_FIELDS = tuple(AsAppliedRow.__dataclass_fields__)


def rows_to_csv(rows: Iterable[AsAppliedRow]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=AS_APPLIED_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow(asdict(r))
    return buf.getvalue()


def read_as_applied_csv(path: str | os.PathLike[str]) -> list[AsAppliedRow]:
    """The as-applied log written by ``AsAppliedLog`` (raises OSError / PrescriptionError)."""
    rows: list[AsAppliedRow] = []
    with Path(path).open(encoding="utf-8", newline="") as fh:
        for n, rec in enumerate(csv.DictReader(fh), start=2):
            try:
                applied = rec["applied_kg_ha"]
                rows.append(
                    AsAppliedRow(
                        time=rec["time"],
                        lon=float(rec["lon"]),
                        lat=float(rec["lat"]),
                        channel=rec["channel"],
                        product=rec["product"],
                        target_kg_ha=float(rec["target_kg_ha"]),
                        applied_kg_ha=float(applied) if applied not in ("", None) else None,
                    )
                )
            except (KeyError, TypeError, ValueError) as exc:
                raise PrescriptionError(f"{path}:{n}: not an as-applied row ({exc})") from None
    return rows


def rows_to_geojson(rows: Iterable[AsAppliedRow]) -> dict[str, Any]:
    feats = []
    for r in rows:
        props = asdict(r)
        lon, lat = props.pop("lon"), props.pop("lat")
        feats.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [lon, lat]},
                "properties": props,
            }
        )
    return {"type": "FeatureCollection", "features": feats}


class AsAppliedLog:
    """Keeps the last rows in memory and appends each to a CSV file when one is given.

    A failing write (disk full, read-only mount, card pulled) must not stop the metering: the
    row stays in memory, ``write_error`` says why and ``on_error`` is told (None once writing
    works again), so the daemon can raise an alarm and keep sowing.
    """

    def __init__(
        self,
        csv_path: str | os.PathLike[str] | None = None,
        max_rows: int = AS_APPLIED_MAX_ROWS,
        on_error: Callable[[str | None], None] | None = None,
    ) -> None:
        self.rows: deque[AsAppliedRow] = deque(maxlen=max_rows)
        self.csv_path = Path(csv_path) if csv_path is not None else None
        self.on_error = on_error
        self.write_error: str | None = None

    def record(self, row: AsAppliedRow) -> None:
        self.rows.append(row)
        if self.csv_path is None:
            return
        try:
            new = not self.csv_path.exists()
            with self.csv_path.open("a", encoding="utf-8", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=AS_APPLIED_FIELDS, lineterminator="\n")
                if new:
                    w.writeheader()
                w.writerow(asdict(row))
        except OSError as exc:
            error = f"{self.csv_path}: {exc.strerror or exc}"
            if error != self.write_error:
                log.error("as-applied log not written: %s", error)
                self.write_error = error
                if self.on_error is not None:
                    self.on_error(error)
            return
        if self.write_error is not None:
            log.info("as-applied log written again: %s", self.csv_path)
            self.write_error = None
            if self.on_error is not None:
                self.on_error(None)

    def record_channel(
        self, pose: Pose, channel: Any, target_kg_ha: float, applied_kg_ha: float | None,
        time: str | None = None,
    ) -> AsAppliedRow:
        """Log one channel's rates where its outlets are (``channel``: a ``[[channel]]``
        section with ``outlet_behind_m``/``outlet_lateral_m`` from the GNSS antenna)."""
        lon, lat = offset_position(
            pose.lon, pose.lat, pose.heading_deg, -channel.outlet_behind_m,
            channel.outlet_lateral_m,
        )
        row = AsAppliedRow(
            time or datetime.now(UTC).isoformat(timespec="milliseconds"), lon, lat,
            channel.name, channel.product, target_kg_ha, applied_kg_ha,
        )
        self.record(row)
        return row

    def to_csv(self) -> str:
        return rows_to_csv(self.rows)

    def to_geojson(self) -> dict[str, Any]:
        return rows_to_geojson(self.rows)
