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
import contextlib
import csv
import json
import os
import sys
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, TextIO

from gateway.config import ConfigError, Settings, load_config, parse_config, state_dir
from gateway.errors import GatewayError
from gateway.records import SeedRecord
from gateway.spacing_quality import RowQualityAccumulator, SpacingQuality

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
DEFAULT_STORE_NAME = "records.sqlite3"
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


def store_path(settings: Settings, state: Path | None = None) -> Path:
    if settings.store.path:
        return Path(settings.store.path)
    return (state if state is not None else state_dir()) / DEFAULT_STORE_NAME


@contextlib.contextmanager
def _atomic_output(path: str) -> Iterator[TextIO]:
    if path == "-":
        yield sys.stdout
        return
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            yield f
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def main_export(args: argparse.Namespace) -> int:
    """``sowgate export [--format geojson|csv] --output FILE [--since] [--until] [--rows]``.

    Opens the store read-only (safe next to the running daemon: WAL readers do not block the
    writer). Returns a process exit code; problems are printed as one line each.
    """
    from gateway.store import RecordStore, StoreError

    try:
        config = getattr(args, "config", None)
        settings = load_config(config) if config is not None else parse_config({})
        state = getattr(args, "state_dir", None)
        state = Path(state) if state is not None else None
        fmt = export_format(getattr(args, "format", None), args.output)
        since = parse_time(getattr(args, "since", None), "since")
        until = parse_time(getattr(args, "until", None), "until")
        if since is not None and until is not None and until <= since:
            raise ExportError("--until must be later than --since")
        if getattr(args, "what", "seeds") == "as-applied":
            return _export_as_applied(settings, args, since, until, fmt, state)
        rows = parse_rows(getattr(args, "rows", None), settings.machine.rows)
        path = store_path(settings, state)
        x_ref = settings.positioning.target_spacing_m
        with RecordStore.open_readonly(path, settings.machine.id) as store:
            quality = quality_by_row(store.query_seeds(since, until, rows), x_ref)
            with _atomic_output(args.output) as out:
                n = export_seeds(
                    store.query_seeds(since, until, rows),
                    fmt,
                    out,
                    quality if fmt == "geojson" else None,
                )
            if fmt == "csv" and args.output != "-":
                with _atomic_output(f"{args.output}{QUALITY_SUFFIX}") as qout:
                    export_quality_csv(quality, qout)
    except ConfigError as exc:
        for line in exc.problems:
            print(line, file=sys.stderr)
        return EXIT_USAGE
    except ExportError as exc:
        print(f"sowgate export: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (StoreError, OSError) as exc:
        print(f"sowgate export: {exc}", file=sys.stderr)
        return EXIT_FAILED
    if args.output != "-":
        print(f"wrote {n} seed records to {args.output} ({fmt})", file=sys.stderr)
        if fmt == "csv":
            print(
                f"wrote the per-row spacing quality to {args.output}{QUALITY_SUFFIX}",
                file=sys.stderr,
            )
    return 0


def _export_as_applied(
    settings: Settings,
    args: argparse.Namespace,
    since: datetime | None = None,
    until: datetime | None = None,
    fmt: ExportFormat = "geojson",
    state: Path | None = None,
) -> int:
    """The metering channels' as-applied log (paper B: every rate with its position)."""
    from gateway.prescription import (
        PrescriptionError,
        read_as_applied_csv,
        rows_to_csv,
        rows_to_geojson,
    )

    configured = settings.prescription.as_applied_path
    path = Path(configured) if configured else (state or state_dir()) / "as_applied.csv"
    try:
        rows = read_as_applied_csv(path)
    except FileNotFoundError:
        print(f"sowgate export: no as-applied log at {path}", file=sys.stderr)
        return EXIT_FAILED
    except (OSError, PrescriptionError) as exc:
        print(f"sowgate export: {exc}", file=sys.stderr)
        return EXIT_FAILED
    if since is not None or until is not None:
        kept = []
        for r in rows:
            stamp = parse_time(r.time, "time")
            if stamp is None:
                continue
            if (since is None or stamp >= since) and (until is None or stamp < until):
                kept.append(r)
        rows = kept
    with _atomic_output(args.output) as out:
        if fmt == "csv":
            out.write(rows_to_csv(rows))
        else:
            json.dump(rows_to_geojson(rows), out)
            out.write("\n")
    if args.output != "-":
        print(f"wrote {len(rows)} as-applied rows to {args.output} ({fmt})", file=sys.stderr)
    return 0
