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

import argparse
import csv
import json
import sys
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, TextIO

import orjson

from gateway.core.errors import GatewayError
from gateway.core.records import SeedRecord, stated_accuracy_m, utc_to_us
from gateway.recording.runs import stored_setting
from gateway.recording.source import MACHINE_ID, RecordSource
from gateway.recording.spacing_quality import RowQualityAccumulator, SpacingQuality
from gateway.recording.store import STORED_SEED_COLUMNS, StoredSeedRow

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
    "accuracy_m",
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
# Decimals of degrees written for a CSV coordinate: 1e-8 degree is about 1 mm, well below
# what RTK resolves; the float's full 15 digits only made the file larger and harder to read.
COORD_DECIMALS = 8


class ExportError(GatewayError):
    """The export cannot be made (bad filter, no store, unwritable output)."""

    exit_code = EXIT_USAGE  # a bad request; a damaged input says EXIT_FAILED


def export_failed(exc: Exception) -> int:
    """Say why an export failed, one line each on standard error, and return its exit status:
    a bad request (config, option) EXIT_USAGE, a store or file that failed EXIT_FAILED."""
    problems = getattr(exc, "problems", None)  # a ConfigError's lines, each naming its key
    if isinstance(problems, list):
        for line in problems:
            print(line, file=sys.stderr)
        return EXIT_USAGE
    print(f"sowgate export: {exc}", file=sys.stderr)
    return exc.exit_code if isinstance(exc, ExportError) else EXIT_FAILED


def target_spacing(
    configured: float | None,
    store: RecordSource,
    since: datetime | None = None,
    until: datetime | None = None,
) -> float | None:
    """The target spacing the spacings are judged against: the config's, else the one the
    daemon ran with (kept in its run marker, ``gateway.recording.runs``), so ``sowgate
    export`` without ``--config`` gives the same per-row numbers as ``sowgate report`` and
    the daemon. None (each row's median is the reference) when neither has one."""
    if configured is not None:
        return configured
    stored = stored_setting(
        store.runs(), "target_spacing_m",
        None if since is None else utc_to_us(since), None if until is None else utc_to_us(until),
    )
    return float(stored) if isinstance(stored, int | float) and stored > 0 else None


def quality_by_row(
    records: Iterable[SeedRecord], x_ref: float | None = None
) -> dict[int, SpacingQuality]:
    """Spacing quality per row over the records' ``spacing_m`` (None spacings are skipped)."""
    return quality_by_row_chunks(([_row_of(r)] for r in records), x_ref)


def quality_by_row_chunks(
    chunks: Iterable[Sequence[StoredSeedRow]], x_ref: float | None = None
) -> dict[int, SpacingQuality]:
    """``quality_by_row`` over the store's chunks of stored rows (``query_seed_rows``).

    Each row's spacings go to its accumulator in id order, as ``add`` one by one would (same
    state bit for bit): ``sowgate export`` and ``sowgate report`` both get their numbers from
    here, so they are equal for the same records.
    """
    acc = RowQualityAccumulators(x_ref)
    for chunk in chunks:
        acc.add_rows(chunk)
    return acc.result()


class RowQualityAccumulators:
    """One ``RowQualityAccumulator`` per row seen, fed whole chunks of stored rows."""

    def __init__(self, x_ref: float | None = None) -> None:
        self.x_ref = x_ref
        self.rows: dict[int, RowQualityAccumulator] = {}

    def add_rows(self, chunk: Sequence[StoredSeedRow]) -> None:
        by_row: dict[int, list[float]] = {}
        for r in chunk:
            spacings = by_row.get(r[_ROW])
            if spacings is None:
                spacings = by_row[r[_ROW]] = []
            if r[_SPACING] is not None:
                spacings.append(r[_SPACING])
        for row, spacings in by_row.items():
            a = self.rows.get(row)
            if a is None:
                a = self.rows[row] = RowQualityAccumulator(self.x_ref)
            a.add_many(spacings)

    def result(self) -> dict[int, SpacingQuality]:
        return {row: a.result() for row, a in sorted(self.rows.items())}


_ROW = STORED_SEED_COLUMNS.index("row")
_SPACING = STORED_SEED_COLUMNS.index("spacing_m")


def _row_of(r: SeedRecord) -> StoredSeedRow:
    """A record back in the store's column order (``STORED_SEED_COLUMNS``)."""
    return (
        r.id, utc_to_us(r.utc), r.row, r.lat, r.lon, r.fix, r.speed_kmh, r.heading_deg,
        r.heading_source, r.extrapolated, r.method, r.spacing_m, r.attitude, r.roll_deg,
        r.pitch_deg, r.delay_ms, r.offset_east_m, r.offset_north_m,
    )


def chunks_of_records(
    records: Iterable[SeedRecord], size: int = 10_000
) -> Iterator[list[StoredSeedRow]]:
    """Records (e.g. re-positioned ones) as the store's chunks of stored rows, for
    ``export_rows``: never more than ``size`` of them in memory."""
    chunk: list[StoredSeedRow] = []
    for r in records:
        chunk.append(_row_of(r))
        if len(chunk) >= size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def quality_json(quality: Mapping[int, SpacingQuality]) -> dict[str, dict[str, Any]]:
    return {str(row): q.as_dict() for row, q in sorted(quality.items())}


def export_seeds(
    records: Iterable[SeedRecord],
    fmt: ExportFormat,
    out: TextIO,
    quality: Mapping[int, SpacingQuality] | None = None,
) -> int:
    """Write ``records`` (already in memory, e.g. a test's) to ``out``; returns how many were
    written. The command streams the store's rows through ``export_rows`` instead."""
    machine = ""
    rows: list[StoredSeedRow] = []
    for r in records:
        machine = r.machine_id
        rows.append(_row_of(r))
    return export_rows([rows], machine, fmt, out, quality)


def export_rows(
    chunks: Iterable[Sequence[StoredSeedRow]],
    machine_id: str,
    fmt: ExportFormat,
    out: TextIO,
    quality: Mapping[int, SpacingQuality] | None = None,
) -> int:
    """Write the store's chunks of stored rows (``query_seed_rows``) to ``out``; returns how
    many seeds were written. Each record's properties are those of its ``SeedRecord`` (the
    same names, order and JSON values), built without a model per seed: ~70 M a day."""
    if fmt == "geojson":
        return _geojson(chunks, machine_id, out, quality)
    if fmt == "csv":
        return _csv(chunks, machine_id, out)
    raise ExportError(f"unknown export format {fmt!r} (geojson or csv)")


_UTC_SECOND_FORMAT = "%Y-%m-%dT%H:%M:%S"


class _UtcText:
    """``2026-05-02T06:00:00.000000Z`` for stored microseconds; a second is formatted once."""

    def __init__(self) -> None:
        self._s = -1
        self._text = ""

    def __call__(self, us: int) -> str:
        s, frac = divmod(us, 1_000_000)
        if s != self._s:
            self._s, self._text = s, time.strftime(_UTC_SECOND_FORMAT, time.gmtime(s))
        return f"{self._text}.{frac:06d}Z"


def _geojson(
    chunks: Iterable[Sequence[StoredSeedRow]],
    machine_id: str,
    out: TextIO,
    quality: Mapping[int, SpacingQuality] | None,
) -> int:
    out.write('{"type": "FeatureCollection",\n')
    if quality is not None:
        out.write(f'"quality": {json.dumps(quality_json(quality))},\n')
    out.write('"features": [')
    n = 0
    utc = _UtcText()
    dumps = orjson.dumps
    for chunk in chunks:
        features = [
            dumps({
                "type": "Feature",
                "id": i,
                "geometry": {"type": "Point", "coordinates": [lon, lat]},
                "properties": {
                    "row": row, "utc": utc(us), "lat": lat, "lon": lon, "fix": fix,
                    "speed_kmh": speed, "heading_deg": heading, "heading_source": source,
                    "extrapolated": bool(extrapolated), "method": method, "spacing_m": spacing,
                    "attitude": attitude, "roll_deg": roll, "pitch_deg": pitch,
                    "accuracy_m": stated_accuracy_m(fix, bool(extrapolated)),
                    "id": i, "machine_id": machine_id,
                },
            })
            for (i, us, row, lat, lon, fix, speed, heading, source, extrapolated, method,
                 spacing, attitude, roll, pitch, *_) in chunk
        ]
        if not features:
            continue
        out.write(("\n" if n == 0 else ",\n") + b",\n".join(features).decode())
        n += len(features)
    out.write("\n]}\n")
    return n


def _csv(chunks: Iterable[Sequence[StoredSeedRow]], machine_id: str, out: TextIO) -> int:
    w = csv.writer(out, lineterminator="\n")
    w.writerow(CSV_FIELDS)
    n = 0
    utc = _UtcText()
    for chunk in chunks:
        w.writerows(
            (i, machine_id, row, utc(us), f"{lat:.{COORD_DECIMALS}f}",
             f"{lon:.{COORD_DECIMALS}f}", fix, speed,
             "" if heading is None else heading, source, bool(extrapolated), method,
             "" if spacing is None else spacing, attitude, "" if roll is None else roll,
             "" if pitch is None else pitch, _blank(stated_accuracy_m(fix, bool(extrapolated))))
            for (i, us, row, lat, lon, fix, speed, heading, source, extrapolated, method,
                 spacing, attitude, roll, pitch, *_) in chunk
        )
        n += len(chunk)
    return n


def _blank(x: float | None) -> float | str:
    return "" if x is None else x


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


def database_options(args: argparse.Namespace) -> tuple[str | None, str | None]:
    """``--database URL --machine M``: read the farm server's PostgreSQL, not the store.

    ``--machine`` is needed with ``--database`` (a farm database holds every machine), and
    means nothing without it; the as-applied log and ``--reposition`` exist only on the cab."""
    database = getattr(args, "database", None)
    machine = getattr(args, "machine", None)
    if database is None:
        if machine is not None:
            raise ExportError("--machine: only with --database (the record store holds one "
                              "machine, the config's)")
        return None, None
    if not database.strip():
        raise ExportError("--database: empty; a PostgreSQL URL, e.g. "
                          "postgresql://reader@farm-server/farm")
    if machine is None or not MACHINE_ID.fullmatch(machine):
        raise ExportError("--machine: required with --database, a machine id "
                          f"([A-Za-z0-9_.-], 1..64 characters; got {machine!r})")
    if getattr(args, "reposition", False):
        raise ExportError("--reposition: needs the record store (the raw timing it uses is "
                          "not published to the farm server)")
    if getattr(args, "what", "seeds") == "as-applied":
        raise ExportError("--what as-applied: the as-applied log is on the cab only, not in "
                          "the farm database")
    return database, machine
