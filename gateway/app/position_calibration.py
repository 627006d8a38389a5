"""``sowgate calibrate positions --survey FILE.csv`` and ``sowgate export --reposition``.

The field check of paper C: dig up seeds, survey them with an RTK rover, and compare. Here the
comparison becomes a calibration: the surveyed seeds are matched to their stored records, the
along-track delay and the lever arm are fitted to them (``gateway.recording.positioning.
survey``), the residuals before and after are printed with paper C's statistics, and the fit
is saved in ``calibration.json`` like the other calibrations (``calibrate undo`` restores the
values it replaced). A running daemon positions new seeds with it once it sees the file change
(``gateway.app.live_calibration``, no restart); stored seeds are re-positioned on export with
``--reposition``.

It lives in the app layer because it joins the record store (recording) and the calibration
file (calibration), which must not import each other.

Survey CSV: a header, then one seed a line: ``id`` (the record id, as exported) or ``utc``
(the record's landing time, ISO 8601), then ``lat``, ``lon`` (WGS84 degrees), optionally
``row`` (checked against the record, and used to match by ``utc``).
"""

from __future__ import annotations

import argparse
import csv
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from gateway.calibration.apply import apply_calibrations
from gateway.calibration.fits import CalibrationError, CalibrationStore, to_entry
from gateway.config import ConfigError, Settings, load_config, parse_config, state_dir, store_path
from gateway.core.errors import GatewayError
from gateway.core.records import SeedRecord
from gateway.recording.export import parse_time
from gateway.recording.positioning.implement_track import ImplementTrack
from gateway.recording.positioning.record_attitude import smooth_attitude
from gateway.recording.positioning.survey import (
    Sown,
    SurveyError,
    SurveyFit,
    fit_survey,
    reposition,
    repositionable,
)

CALIBRATION_KEY = "positions.survey"
EXIT_OK = 0
EXIT_FAILED = 1
UTC_MATCH_S = 0.0005  # a record's utc is stored to the microsecond; survey files may round


@dataclass(frozen=True)
class SurveyedSeed:
    line: int
    lat: float
    lon: float
    id: int | None = None
    utc: datetime | None = None
    row: int | None = None


def read_survey(path: Path) -> list[SurveyedSeed]:
    """The survey CSV; every bad line is named (line number, column, value)."""
    try:
        with path.open(encoding="utf-8", newline="") as fh:
            reader = csv.DictReader(fh)
            fields = [f.strip().lower() for f in (reader.fieldnames or [])]
            if "lat" not in fields or "lon" not in fields or not (
                "id" in fields or "utc" in fields
            ):
                raise SurveyError(
                    f"{path}: the header must name id (or utc), lat and lon (got "
                    f"{', '.join(fields) or 'no header'})"
                )
            out = []
            for i, raw in enumerate(reader, start=2):
                row = {k.strip().lower(): (v or "").strip() for k, v in raw.items() if k}
                out.append(_surveyed(path, i, row))
    except OSError as exc:
        raise SurveyError(f"{path}: {exc.strerror or exc}") from None
    if not out:
        raise SurveyError(f"{path}: no surveyed seeds")
    return out


def _surveyed(path: Path, line: int, row: dict[str, str]) -> SurveyedSeed:
    def number(key: str, lo: float, hi: float) -> float:
        try:
            value = float(row[key])
        except (KeyError, ValueError):
            raise SurveyError(f"{path}:{line}: {key} is not a number (got "
                              f"{row.get(key)!r})") from None
        if not lo <= value <= hi:
            raise SurveyError(f"{path}:{line}: {key} outside {lo:g}..{hi:g} (got {value})")
        return value

    def whole(key: str) -> int | None:
        text = row.get(key, "")
        if not text:
            return None
        try:
            return int(text)
        except ValueError:
            raise SurveyError(f"{path}:{line}: {key} is not a whole number (got "
                              f"{text!r})") from None

    utc = None
    if row.get("utc"):
        try:
            utc = parse_time(row["utc"], "utc")
        except GatewayError as exc:
            raise SurveyError(f"{path}:{line}: {exc}") from None
    seed_id = whole("id")
    if seed_id is None and utc is None:
        raise SurveyError(f"{path}:{line}: needs an id or a utc")
    return SurveyedSeed(line, number("lat", -90, 90), number("lon", -180, 180), seed_id, utc,
                        whole("row"))


def match_survey(
    seeds: list[SurveyedSeed], records: Iterable[SeedRecord], sown: Sown | None = None,
) -> tuple[list[SeedRecord], list[tuple[float, float]], list[str]]:
    """Surveyed seeds paired with their records (by id, else by utc and row); the reasons
    for the ones left unmatched. ``sown`` collects every record on the way (the survey's
    coverage is judged against them)."""
    by_id: dict[int, SurveyedSeed] = {s.id: s for s in seeds if s.id is not None}
    by_ms: dict[int, list[SurveyedSeed]] = {}  # surveyed by utc, by whole millisecond
    for s in seeds:
        if s.id is None and s.utc is not None:
            by_ms.setdefault(_ms(s.utc), []).append(s)
    found: dict[int, SeedRecord] = {}  # survey line -> record
    ambiguous: set[int] = set()
    for r in records:  # one pass over the store, a dictionary look-up a record
        if sown is not None:
            sown.add(r)
        s_id = by_id.get(r.id)
        if s_id is not None:
            found[s_id.line] = r
            if sown is not None:
                sown.keep(r)
            continue
        if not by_ms:
            continue
        ms = _ms(r.utc)
        for s in (*by_ms.get(ms - 1, ()), *by_ms.get(ms, ()), *by_ms.get(ms + 1, ())):
            assert s.utc is not None
            if abs((r.utc - s.utc) / timedelta(seconds=1)) <= UTC_MATCH_S and (
                s.row is None or s.row == r.row
            ):
                if s.line in found:
                    ambiguous.add(s.line)
                found[s.line] = r
                if sown is not None:
                    sown.keep(r)
    matched: list[SeedRecord] = []
    surveyed: list[tuple[float, float]] = []
    problems: list[str] = []
    for s in seeds:
        rec = found.get(s.line)
        if rec is None:
            what = f"id {s.id}" if s.id is not None else f"utc {s.utc}"
            problems.append(f"line {s.line}: no stored record with {what}")
        elif s.line in ambiguous:
            problems.append(f"line {s.line}: several records at utc {s.utc}; give row")
        elif s.row is not None and s.row != rec.row:
            problems.append(f"line {s.line}: row {s.row}, but record {rec.id} is row {rec.row}")
        elif not repositionable(rec):
            problems.append(f"line {s.line}: record {rec.id} keeps no raw edge time and "
                            "antenna offset (stored by an older version or method = paper)")
        else:
            matched.append(rec)
            surveyed.append((s.lat, s.lon))
    return matched, surveyed, problems


def _ms(t: datetime) -> int:
    return round(t.timestamp() * 1000.0)


def calibrated_settings(settings: Settings, state: Path | None) -> Settings:
    """``settings`` with the saved calibrations laid over it, as the daemon starts with."""
    current = settings.model_copy(deep=True)
    apply_calibrations(current, state or state_dir())
    return current


def _stats_table(fit: SurveyFit) -> Table:
    t = Table(title="surveyed seeds: distance from the record to the surveyed point")
    for h in ("", "mean (mm)", "SD (mm)", "CV (%)", "max (mm)", "n"):
        t.add_column(h, justify="right")
    for name, st in (("before", fit.before), ("after", fit.after)):
        t.add_row(name, f"{st.mean_m * 1000:.1f}", f"{st.sd_m * 1000:.1f}",
                  f"{st.cv_pct:.1f}", f"{st.max_m * 1000:.1f}", str(st.n))
    return t


def main_calibrate_positions(args: argparse.Namespace, console: Console | None = None) -> int:
    """Fit, show, and (unless refused) save the seed position calibration."""
    from gateway.recording.store import RecordStore, StoreError

    con = console or Console(soft_wrap=True)  # paths and messages unbroken (copyable)
    try:
        config = getattr(args, "config", None)
        settings = load_config(config) if config else parse_config({})
        state = Path(args.state_dir) if getattr(args, "state_dir", None) else None
        current = calibrated_settings(settings, state)
        seeds = read_survey(Path(args.survey))
        path = store_path(settings, state)
        sown = Sown.empty(current.positioning)  # with a hitch: the implement's track
        with RecordStore.open_readonly(path, settings.machine.id) as store:
            # each record's roll and pitch again from the records around it (lag, noise)
            smoothed = smooth_attitude(store.query_seeds(), current.positioning,
                                       settings.gnss.heading_offset_deg)
            records, surveyed, problems = match_survey(seeds, smoothed, sown)
        for p in problems:
            con.print(f"[yellow]skipped[/yellow] {escape(p)}")
        fit = fit_survey(records, surveyed, current.positioning,
                         fit_delay=not getattr(args, "lever_only", False), sown=sown)
        new = fit.settings(current.positioning)
        con.print(_stats_table(fit))
        con.print(
            f"fitted: delay {fit.delay_ms:+.1f} ms"
            f"{'' if fit.delay_fitted else ' (held: --lever-only)'}"
            + (f" at {fit.speed_ref_kmh:.1f} km/h, {fit.delay_ms_per_kmh:+.2f} ms per km/h "
               "(into the fall-time table)" if fit.delay_ms_per_kmh else "")
            + ", outlets "
            f"{fit.behind_m * 1000:+.1f} mm behind, {fit.right_m * 1000:+.1f} mm right "
            f"(speed spread {fit.speed_spread_kmh:.1f} km/h, {fit.outliers} seeds "
            "down-weighted as outliers)"
        )
        for w in fit.coverage_warnings:
            con.print(f"[yellow]warning:[/yellow] {escape(w)}")
        bad = fit.problems()
        if bad and not getattr(args, "accept_poor_fit", False):
            for p in bad:
                con.print(f"[red]refused:[/red] {escape(p)}")
            con.print("nothing saved (--accept-poor-fit saves it anyway)")
            return EXIT_FAILED
        entry = to_entry(
            {
                "delay_correction_ms": new.delay_correction_ms,
                "outlet_behind_antenna_m": new.outlet_behind_antenna_m,
                "row_lateral_m": new.lateral_offsets(),
                "outlets_behind_hitch_m": (
                    None if new.hitch is None else new.hitch.outlets_behind_hitch_m
                ),
                "fall_time_table": [list(x) for x in new.fall_time_table],
                "fitted": {"delay_ms": fit.delay_ms, "behind_m": fit.behind_m,
                           "right_m": fit.right_m, "delay_fitted": fit.delay_fitted,
                           "delay_ms_per_kmh": fit.delay_ms_per_kmh,
                           "speed_ref_kmh": fit.speed_ref_kmh},
                "before": fit.before.__dict__,
                "after": fit.after.__dict__,
            },
            survey=str(args.survey),
            seeds=fit.after.n,
        )
        CalibrationStore(state or state_dir()).save(CALIBRATION_KEY, entry)
    except ConfigError as exc:
        con.print(f"[red]config error:[/red]\n{escape(str(exc))}")
        return EXIT_FAILED
    except (SurveyError, CalibrationError, StoreError, GatewayError, OSError) as exc:
        con.print(f"[red]calibration refused:[/red] {escape(str(exc))}")
        return EXIT_FAILED
    con.print(
        f"saved {CALIBRATION_KEY}: outlets {new.outlet_behind_antenna_m:.3f} m behind the "
        f"antenna, delay correction {new.delay_correction_ms:+.1f} ms. A running daemon "
        "positions new seeds with it within a few seconds (it watches the calibration file; "
        "no restart), a stopped one from its next start; "
        "`sowgate export --reposition` re-positions the stored ones; "
        f"`sowgate calibrate undo --key {CALIBRATION_KEY}` restores the values it replaced."
    )
    return EXIT_OK


@dataclass
class Repositioner:
    """Re-positions records for export, in stored order (a trailed implement's heading is
    followed along the records' antenna track: ``ImplementTrack``); counts those that keep
    no raw data (left as stored)."""

    settings: Settings
    kept_as_stored: int = 0

    def __call__(self, records: Iterable[SeedRecord]) -> Iterator[SeedRecord]:
        positioning = self.settings.positioning
        # where the track restarts, the implement is read back from the records as made with
        # these settings (the ones a calibration left, or centimetres from them)
        track = ImplementTrack(positioning, made_with=positioning)
        # the attitude each record keeps, estimated again with the records after it
        for r in smooth_attitude(records, positioning, self.settings.gnss.heading_offset_deg):
            implement = track.heading(r)
            if not repositionable(r):
                self.kept_as_stored += 1
                yield r
                continue
            lat, lon = reposition(r, positioning, implement)
            update: dict[str, Any] = {"lat": lat, "lon": lon}
            yield r.model_copy(update=update)
