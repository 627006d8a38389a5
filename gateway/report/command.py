"""``sowgate report``: the field report from the record store, as HTML or PDF.

Reads the store read-only (safe next to the running daemon) in two streaming passes through
``RecordStore.query_seed_rows``, the reader ``sowgate export`` uses: first the statistics
(``FieldStats``, with export's spacing-quality accumulators), then the map (``SeedMap``). The
output is written to a temporary name and renamed, so a failed report leaves no file, and
nothing at all is written when there is nothing to report.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sqlite3
import sys
import tempfile
from pathlib import Path
from typing import Literal

from gateway.config import EXIT_CONFIG, ConfigError, load_config, store_path
from gateway.core.records import AlarmEvent, utc_to_us
from gateway.recording.export import (
    ExportError,
    database_options,
    parse_rows,
    parse_time,
    target_spacing,
)
from gateway.recording.source import open_source, source_text
from gateway.recording.store import StoreError

ReportFormat = Literal["html", "pdf"]

EXIT_FAILED = 1  # the store could not be read or the report not written
EXIT_USAGE = 2  # a bad option: --since/--until/--rows/--format/--tsw
EXIT_NO_RECORDS = 66  # EX_NOINPUT: no store, or no seed record in it or in the window
# alarm events kept for the timeline and the table; more are counted (a flapping sensor)
MAX_ALARM_EVENTS = 20_000

REPORT_DESCRIPTION = """\
Write a field report from the record store (read-only; safe while the daemon runs): a summary,
the seed map by spacing class, per-row spacing histograms and the ISO 7256-1 table (the same
numbers as sowgate export), the applied rate against the target along the drive and against
speed, and the alarm timeline. One self-contained file that opens offline. The map draws
every seed up to 200 000 seeds, above that shares per square of the field."""

HELP_EPILOG = f"""\
exit status:
  0   the report was written
  {EXIT_NO_RECORDS}  nothing to report: no record store, or no seed record in it, in the
      --since/--until window or in the --rows asked (nothing is written)
  {EXIT_USAGE}   a bad option (--since/--until not ISO 8601 or not in order, --rows, --format)
  {EXIT_CONFIG}  the config file is invalid
  {EXIT_FAILED}   the store could not be read or the output not written
"""


class ReportError(ExportError):
    """A bad option for the report."""


def add_report_command(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    r = sub.add_parser(
        "report",
        help="field report (seed map, per-row quality, rate, alarms) as HTML or PDF",
        description=REPORT_DESCRIPTION,
        epilog=HELP_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    r.add_argument("--config", type=Path, required=True,
                   help="config file (store path, machine, rows, target spacing)")
    r.add_argument("--output", required=True, help="file to write (.html or .pdf)")
    r.add_argument("--format", choices=["html", "pdf"], default=None,
                   help="default: from the --output extension (.pdf -> pdf, else html)")
    r.add_argument("--since", default=None, help="ISO 8601 start time (UTC if no offset)")
    r.add_argument("--until", default=None, help="ISO 8601 end time (UTC if no offset)")
    r.add_argument("--rows", default=None, help="comma-separated row numbers (default: all)")
    r.add_argument("--tsw", type=float, default=None, metavar="GRAMS",
                   help="thousand-seed mass of the seed lot, for the seed mass and kg/ha")
    r.add_argument("--state-dir", type=Path, default=None,
                   help="read the store here (e.g. sowgate-demo), not in $SOWGATE_STATE_DIR")
    add_database_options(r)


def add_database_options(p: argparse.ArgumentParser) -> None:
    """``--database URL --machine M``: read the farm server's PostgreSQL, not the store."""
    p.add_argument("--database", default=None, metavar="URL",
                   help="read the farm server's PostgreSQL (what sowgate ingest wrote), "
                   "not the record store: e.g. postgresql://reader@farm-server/farm "
                   "(docs/farm-server.md)")
    p.add_argument("--machine", default=None, metavar="ID",
                   help="with --database: the machine whose records to read")


def report_format(requested: str | None, output: str) -> ReportFormat:
    if requested is not None:
        if requested not in ("html", "pdf"):
            raise ReportError(f"--format: unknown report format {requested!r} (html or pdf)")
        return "pdf" if requested == "pdf" else "html"
    return "pdf" if Path(output).suffix.lower() == ".pdf" else "html"


def main_report(args: argparse.Namespace) -> int:
    """Returns the exit status; every problem is one line on standard error."""
    # numpy and matplotlib only for this command, not for every ``sowgate`` start
    from gateway.recording.field_stats import FieldStats, SeedMap, alarm_intervals
    from gateway.report.document import FieldReport, to_html
    from gateway.report.pdf import to_pdf

    try:
        settings = load_config(args.config)
    except ConfigError as exc:
        for line in exc.problems:
            print(line, file=sys.stderr)
        return EXIT_CONFIG
    try:
        fmt = report_format(getattr(args, "format", None), args.output)
        since = parse_time(args.since, "since")
        until = parse_time(args.until, "until")
        if since is not None and until is not None and until <= since:
            raise ReportError("--until must be later than --since")
        rows = parse_rows(args.rows, settings.machine.rows)
        tsw = getattr(args, "tsw", None)
        if tsw is not None and not 0 < tsw < 5000:
            raise ReportError(f"--tsw: the thousand-seed mass in grams, 0..5000 (got {tsw})")
        database, machine = database_options(args)
    except ExportError as exc:
        print(f"sowgate report: {exc}", file=sys.stderr)
        return EXIT_USAGE
    state = getattr(args, "state_dir", None)
    path = store_path(settings, Path(state) if state is not None else None)
    if database is None and not path.exists():
        print(f"sowgate report: nothing to report: no record store at {path}", file=sys.stderr)
        return EXIT_NO_RECORDS
    window = _window_text(args.since, args.until, args.rows)
    where = source_text(database, machine, path)
    machine_id = machine or settings.machine.id
    try:
        with open_source(path, settings.machine.id, database, machine) as store:
            span = store.seed_time_span(since, until)
            if span is None:
                print(f"sowgate report: nothing to report: no seed records in {where}{window}",
                      file=sys.stderr)
                return EXIT_NO_RECORDS
            row_spacing = settings.machine.working_width_m / settings.machine.rows
            x_ref = target_spacing(settings.positioning.target_spacing_m, store, since, until)
            stats = FieldStats(x_ref, row_spacing, span)
            for chunk in store.query_seed_rows(since, until, rows):
                stats.add_rows(chunk)
            summary = stats.result()
            if summary.seeds == 0:
                print(f"sowgate report: nothing to report: no seed records in {where}{window}",
                      file=sys.stderr)
                return EXIT_NO_RECORDS
            seed_map = SeedMap(summary)
            for chunk in store.query_seed_rows(since, until, rows):
                seed_map.add_rows(chunk)
            runs = store.runs()
            alarms: list[AlarmEvent] = []
            total = 0
            for a in store.query_alarms(since, until):
                total += 1
                if len(alarms) < MAX_ALARM_EVENTS:
                    alarms.append(a)
    except StoreError as exc:
        print(f"sowgate report: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except sqlite3.Error as exc:  # a damaged file: one line, no traceback
        print(f"sowgate report: cannot read the record store {path}: {exc}", file=sys.stderr)
        return EXIT_FAILED
    intervals = alarm_intervals(
        [(utc_to_us(a.utc), a.code, a.active, a.severity) for a in alarms],
        summary.first_us, summary.last_us,
        [(r.start_us, r.stop_us) for r in runs],
    )
    report = FieldReport(
        machine_id=machine_id,
        machine_rows=settings.machine.rows,
        working_width_m=settings.machine.working_width_m,
        crop=settings.control.crop,
        summary=summary,
        seed_map=seed_map.result(),
        alarms=alarms,
        alarms_total=total,
        intervals=intervals,
        runs=runs,
        since=since,
        until=until,
        rows=rows,
        tsw_g=tsw,
        source="the record store" if database is None else "the farm database",
    )
    try:
        data = to_pdf(report) if fmt == "pdf" else to_html(report)
        _write_atomic(Path(args.output), data)
    except OSError as exc:
        print(f"sowgate report: cannot write {args.output}: {exc}", file=sys.stderr)
        return EXIT_FAILED
    print(f"wrote the field report for {summary.seeds:,} seeds to {args.output} ({fmt})",
          file=sys.stderr)
    return 0


def _window_text(since: str | None, until: str | None, rows: str | None) -> str:
    parts = []
    if since is not None:
        parts.append(f"since {since}")
    if until is not None:
        parts.append(f"until {until}")
    if rows is not None:
        parts.append(f"on rows {rows}")
    return f" ({', '.join(parts)})" if parts else ""


def _write_atomic(target: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # as open() would make it (mkstemp makes it 0600)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
