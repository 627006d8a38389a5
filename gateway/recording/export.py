"""``sowgate export``: the as-planted map as GeoJSON or CSV, with per-row spacing quality.

GeoJSON (RFC 7946): a FeatureCollection of Points ``[lon, lat]`` whose properties are the
record's fields; the per-row ISO 7256-1 quality summary rides in a top-level ``"quality"``
member (a foreign member, which GIS tools ignore and scripts can read). It is written before
the features so a reader can get it without parsing a million points.

CSV: one row per seed with a header; the quality summary goes to a sidecar
``<output>.quality.csv`` because CSV has no place for a second table (the command says it
wrote it, and ``--help`` says so).

Without ``--format`` the output file's extension picks the format (``.csv``, ``.geojson``,
``.json``); standard output (``-``) gets GeoJSON. Any other extension is refused rather than
guessed: a GeoJSON document inside ``applied.csv`` is what the old default produced.

Records are streamed, never held in memory all at once, and the output file is written to a
temporary name and renamed at the end, so a failed export never leaves half a map behind.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, TextIO

from gateway.core.errors import GatewayError
from gateway.core.records import SeedRecord
from gateway.recording.spacing_quality import RowQualityAccumulator, SpacingQuality

ExportFormat = Literal["geojson", "csv"]
CSV_FIELDS = [
    "id",
    "machine_id",
    "row",
    "utc",
    "lat",
    "lon",
    "fix",
    "speed_kmh",
    "heading_deg",
    "heading_source",
    "extrapolated",
    "method",
    "spacing_m",
    "attitude",
    "roll_deg",
    "pitch_deg",
]
QUALITY_FIELDS = [
    "row",
    "n",
    "x_ref_m",
    "multiples_index",
    "miss_index",
    "quality_of_feed_index",
    "precision",
    "mean_spacing_m",
]
EXIT_USAGE = 2
EXIT_FAILED = 1
FORMAT_BY_EXTENSION: dict[str, ExportFormat] = {
    ".csv": "csv",
    ".geojson": "geojson",
    ".json": "geojson",
}
QUALITY_SUFFIX = ".quality.csv"


class ExportError(GatewayError):
    """The export cannot be made (bad filter, no store, unwritable output)."""


def quality_by_row(
    records: Iterable[SeedRecord], x_ref: float | None = None
) -> dict[int, SpacingQuality]:
    """Spacing quality per row over the records' ``spacing_m`` (None spacings are skipped)."""
    acc: dict[int, RowQualityAccumulator] = {}
    for r in records:
        a = acc.setdefault(r.row, RowQualityAccumulator(x_ref))
        if r.spacing_m is not None:
            a.add(r.spacing_m)
    return {row: a.result() for row, a in sorted(acc.items())}


def quality_json(quality: Mapping[int, SpacingQuality]) -> dict[str, dict[str, Any]]:
    return {str(row): q.as_dict() for row, q in sorted(quality.items())}


def _properties(record: SeedRecord) -> dict[str, Any]:
    props = record.model_dump(mode="json")
    props["utc"] = _iso(record.utc)
    return props


def _iso(t: datetime) -> str:
    return t.astimezone(UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


def export_seeds(
    records: Iterable[SeedRecord],
    fmt: ExportFormat,
    out: TextIO,
    quality: Mapping[int, SpacingQuality] | None = None,
) -> int:
    """Write ``records`` to ``out``; returns how many were written."""
    if fmt == "geojson":
        return _geojson(records, out, quality)
    if fmt == "csv":
        return _csv(records, out)
    raise ExportError(f"unknown export format {fmt!r} (geojson or csv)")


def _geojson(
    records: Iterable[SeedRecord], out: TextIO, quality: Mapping[int, SpacingQuality] | None
) -> int:
    out.write('{"type": "FeatureCollection",\n')
    if quality is not None:
        out.write(f'"quality": {json.dumps(quality_json(quality))},\n')
    out.write('"features": [')
    n = 0
    for r in records:
        feature = {
            "type": "Feature",
            "id": r.id,
            "geometry": {"type": "Point", "coordinates": [r.lon, r.lat]},
            "properties": _properties(r),
        }
        out.write(("\n" if n == 0 else ",\n") + json.dumps(feature))
        n += 1
    out.write("\n]}\n")
    return n


def _csv(records: Iterable[SeedRecord], out: TextIO) -> int:
    w = csv.DictWriter(out, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    n = 0
    for r in records:
        row = _properties(r)
        w.writerow({k: "" if row[k] is None else row[k] for k in CSV_FIELDS})
        n += 1
    return n


def export_quality_csv(quality: Mapping[int, SpacingQuality], out: TextIO) -> None:
    w = csv.DictWriter(out, fieldnames=QUALITY_FIELDS, lineterminator="\n")
    w.writeheader()
    for row, q in sorted(quality.items()):
        d = q.as_dict()
        w.writerow({"row": row, **{k: "" if d[k] is None else d[k] for k in QUALITY_FIELDS[1:]}})


# ---------------------------------------------------------------- command line


def parse_time(text: str | None, name: str) -> datetime | None:
    """ISO 8601; a time without an offset is taken as UTC (records are stored in UTC)."""
    if text is None:
        return None
    try:
        t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ExportError(f"--{name}: not an ISO 8601 time: {text!r}") from None
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def parse_rows(text: str | None, rows: int) -> list[int] | None:
    if text is None:
        return None
    try:
        wanted = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ExportError(f"--rows: expected comma-separated row numbers, got {text!r}") from None
    bad = [r for r in wanted if not 1 <= r <= rows]
    if bad or not wanted:
        raise ExportError(f"--rows: rows must be in 1..{rows}, got {text!r}")
    return wanted


def export_format(requested: str | None, output: str) -> ExportFormat:
    """``--format`` if given, else the one ``output``'s extension names (GeoJSON for ``-``)."""
    if requested is not None:
        if requested not in ("geojson", "csv"):
            raise ExportError(f"--format: unknown export format {requested!r} (geojson or csv)")
        return "csv" if requested == "csv" else "geojson"
    if output == "-":
        return "geojson"
    name = Path(output).name
    suffix = Path(output).suffix.lower()
    if suffix in FORMAT_BY_EXTENSION:
        return FORMAT_BY_EXTENSION[suffix]
    choices = "name the file .csv, .geojson or .json, or pass --format csv|geojson"
    if suffix == ".shp":
        raise ExportError(
            f"shapefile export is not supported ({name!r}): {choices} "
            "(ogr2ogr converts GeoJSON to a shapefile)"
        )
    raise ExportError(f"cannot tell the format of {name!r}: {choices}")
