"""``sowgate export``: seed records (the recording domain) or the as-applied log (metering).

The command sits above both domains, so neither imports the other. Outputs are written to a
temporary name and renamed at the end, so a failed export never leaves half a file behind.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import os
import sys
import tempfile
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import TextIO

from gateway.config import (
    ConfigError,
    Settings,
    as_applied_path,
    load_config,
    parse_config,
    store_path,
)
from gateway.core.records import us_to_utc, utc_to_us
from gateway.metering.prescription import (
    PrescriptionError,
    read_as_applied_csv,
    rows_to_csv,
    rows_to_geojson,
)
from gateway.recording.export import (
    EXIT_FAILED,
    QUALITY_SUFFIX,
    ExportError,
    ExportFormat,
    chunks_of_records,
    database_options,
    export_failed,
    export_format,
    export_quality_csv,
    export_rows,
    parse_rows,
    parse_time,
    quality_by_row_chunks,
    target_spacing,
)
from gateway.recording.source import open_source


@contextlib.contextmanager
def atomic_output(path: str) -> Iterator[TextIO]:
    if path == "-":
        yield sys.stdout
        return
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
    try:
        # as open() would make it (mkstemp makes it 0600), like the report next to it
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
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
    from gateway.recording.store import StoreError

    if getattr(args, "format", None) == "isoxml":  # a folder of several files, its own writer
        from gateway.app.isoxml_export import main_export_isoxml

        return main_export_isoxml(args)
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
        database_options(args)  # a bad --database/--machine before anything is read
        if getattr(args, "what", "seeds") == "as-applied":
            return _export_as_applied(settings, args, since, until, fmt, state)
        if getattr(args, "what", "seeds") == "alarms":
            return _export_alarms(settings, args, since, until, fmt, state)
        rows = parse_rows(getattr(args, "rows", None), settings.machine.rows)
        path = store_path(settings, state)
        database, machine = database_options(args)
        moved = None
        if getattr(args, "reposition", False):
            from gateway.app.position_calibration import Repositioner, calibrated_settings

            moved = Repositioner(calibrated_settings(settings, state))
        with open_source(path, settings.machine.id, database, machine) as store:
            x_ref = target_spacing(settings.positioning.target_spacing_m, store, since, until)
            # two passes over the store, each streaming: the quality goes before the features
            quality = quality_by_row_chunks(store.query_seed_rows(since, until, rows), x_ref)
            chunks = store.query_seed_rows(since, until, rows)
            if moved is not None:  # re-positioned: a record at a time, still streamed
                chunks = chunks_of_records(moved(store.query_seeds(since, until, rows)))
            with atomic_output(args.output) as out:
                n = export_rows(
                    chunks,
                    settings.machine.id,
                    fmt,
                    out,
                    quality if fmt == "geojson" else None,
                )
            if fmt == "csv" and args.output != "-":
                with atomic_output(f"{args.output}{QUALITY_SUFFIX}") as qout:
                    export_quality_csv(quality, qout)
    except (ConfigError, ExportError, StoreError, OSError) as exc:
        return export_failed(exc)
    if moved is not None:
        print(
            f"re-positioned with the current position model and calibration; "
            f"{moved.kept_as_stored} records keep no raw data and are as stored",
            file=sys.stderr,
        )
    if args.output != "-":
        print(f"wrote {n} seed records to {args.output} ({fmt})", file=sys.stderr)
        if fmt == "csv":
            print(
                f"wrote the per-row spacing quality to {args.output}{QUALITY_SUFFIX}",
                file=sys.stderr,
            )
    return 0


ALARM_FIELDS = ["code", "severity", "raised_utc", "ended_utc", "ended", "message"]


def _export_alarms(
    settings: Settings,
    args: argparse.Namespace,
    since: datetime | None,
    until: datetime | None,
    fmt: ExportFormat,
    state: Path | None,
) -> int:
    """The alarm periods of the record store as CSV: raised, ended, and how it ended:
    ``cleared``, ``stop`` (still active when sowgate stopped: it ends at that stop, see
    ``gateway.recording.runs``) or ``open`` (still active at the end of the store or window).
    The same periods as the report's alarm timeline."""
    from gateway.recording.field_stats import alarm_intervals

    if fmt != "csv" or args.output == "-":
        raise ExportError("--what alarms writes CSV: name the file .csv or pass --format csv")
    path = store_path(settings, state)
    database, machine = database_options(args)
    with open_source(path, settings.machine.id, database, machine) as store:
        events = list(store.query_alarms(since, until))
        runs = store.runs()
        span = store.seed_time_span(since, until)
    times = [utc_to_us(e.utc) for e in events]
    start = min([*times, *(span[:1] if span else [])], default=0)
    end = max([*times, *(span[1:] if span else [])], default=0)
    messages = {(e.code, t): e.message for e, t in zip(events, times, strict=True)}
    periods = alarm_intervals(
        [(t, e.code, e.active, e.severity) for e, t in zip(events, times, strict=True)],
        start, end, [(r.start_us, r.stop_us) for r in runs],
    )
    with atomic_output(args.output) as out:
        w = csv.writer(out, lineterminator="\n")
        w.writerow(ALARM_FIELDS)
        for p in periods:
            message = messages.get((p.code, p.from_us)) or messages.get((p.code, p.to_us), "")
            w.writerow([p.code, p.severity, _iso(p.from_us), _iso(p.to_us), p.end, message])
    print(f"wrote {len(periods)} alarm periods to {args.output} (csv)", file=sys.stderr)
    return 0


def _iso(us: int) -> str:
    return us_to_utc(us).isoformat().replace("+00:00", "Z")


def _export_as_applied(
    settings: Settings,
    args: argparse.Namespace,
    since: datetime | None = None,
    until: datetime | None = None,
    fmt: ExportFormat = "geojson",
    state: Path | None = None,
) -> int:
    """The metering channels' as-applied log (paper B: every rate with its position)."""
    path = as_applied_path(settings, state)
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
    with atomic_output(args.output) as out:
        if fmt == "csv":
            out.write(rows_to_csv(rows))
        else:
            json.dump(rows_to_geojson(rows), out)
            out.write("\n")
    if args.output != "-":
        print(f"wrote {len(rows)} as-applied rows to {args.output} ({fmt})", file=sys.stderr)
    return 0
