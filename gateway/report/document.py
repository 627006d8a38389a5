"""The field report as one self-contained HTML file, or as a PDF with the same content.

HTML: inline CSS, every plot a base64 PNG in an ``<img src="data:...">``, no script run, no
external reference of any kind, so it opens offline on the cab box, a laptop or a phone and
can be mailed as one file. The numbers it shows are also embedded as JSON
(``<script type="application/json" id="report-data">``) for scripts that want them.
The PDF (same content, A4 pages to print) is laid out by ``gateway.report.pdf``.
"""

from __future__ import annotations

import base64
import html
import io
import json
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from matplotlib.figure import Figure, FigureBase

from gateway.core.records import (
    EXTRAPOLATED_EXTRA_M,
    AlarmEvent,
    stated_accuracy_m,
    us_to_utc,
    utc_to_us,
)
from gateway.recording.export import quality_json
from gateway.recording.field_stats import CLASS_NAMES, AlarmInterval, FieldSummary, MapResult
from gateway.recording.runs import Run
from gateway.report import figures

PNG_DPI = 90
ALARM_ROWS_SHOWN = 200  # alarm events listed in the HTML table (all are in the timeline)


@dataclass
class FieldReport:
    """What one report shows: built by ``gateway.report.command``, written here."""

    machine_id: str
    machine_rows: int
    working_width_m: float
    crop: str
    summary: FieldSummary
    seed_map: MapResult
    alarms: list[AlarmEvent]
    alarms_total: int
    intervals: list[AlarmInterval]
    since: datetime | None
    until: datetime | None
    rows: list[int] | None
    tsw_g: float | None
    runs: list[Run] = field(default_factory=list)  # daemon starts and stops (recording.runs)
    source: str = "the record store"  # or "the farm database" (sowgate report --database)
    created: datetime = field(default_factory=lambda: datetime.now(UTC))

    @property
    def title(self) -> str:
        return f"Field report: {self.machine_id}, {_day(self.summary.first_us)}"

    def shown_rows(self) -> list[int]:
        return sorted(self.summary.seeds_by_row)

    def summary_lines(self) -> list[tuple[str, str]]:
        s = self.summary
        fixes = ", ".join(f"{k} {100 * v / s.seeds:.1f} %" for k, v in s.fixes.items())
        mass = (
            f"{s.seeds * self.tsw_g / 1e6:,.1f} kg (seeds × thousand-seed mass "
            f"{self.tsw_g:g} g)"
            if self.tsw_g is not None
            else "not stored (give --tsw GRAMS, the thousand-seed mass, to compute it)"
        )
        pop = s.population_mean_per_ha
        target = s.target_population_per_ha
        rate = "–" if pop is None else f"{pop:,.0f} seeds/ha"
        if pop is not None and self.tsw_g is not None:
            rate += f" ({pop * self.tsw_g / 1e6:.1f} kg/ha)"
        if target is not None:
            rate += f", target {target:,.0f} seeds/ha"
            if pop is not None:
                rate += f" ({signed_pct(100 * (pop / target - 1))})"
        window = (
            f"{_when(self.since) if self.since else 'start of the store'} to "
            f"{_when(self.until) if self.until else 'end of the store'}"
        )
        return [
            ("machine", f"{self.machine_id}: {self.machine_rows} rows, "
                        f"{self.working_width_m:g} m working width "
                        f"({s.row_spacing_m * 100:.1f} cm rows), crop {self.crop}"),
            ("time", f"{_when_us(s.first_us)} to {_when_us(s.last_us)} "
                     f"({_duration(s.seeding_s)} sowing)"),
            ("window asked", window + (f", rows {_rows_text(self.rows)}" if self.rows else "")),
            ("seeds", f"{s.seeds:,}"),
            ("area sown", f"{s.area_ha:,.{2 if s.area_ha >= 10 else 4}f} ha "
                          f"({s.sown_length_m / 1000:,.{1 if s.sown_length_m >= 1e4 else 3}f} "
                          f"km of row × {s.row_spacing_m * 100:.1f} cm row spacing)"),
            ("seed mass", mass),
            ("applied rate", rate),
            ("mean speed", f"{s.speed_mean_kmh:.1f} km/h"),
            ("position quality", f"RTK fixed {100 * s.rtk_fixed_share:.1f} % of the seeds; "
                                 f"extrapolated {100 * s.extrapolated_share:.2f} % "
                                 f"({fixes})"),
            ("float/dropout seeds", self._degraded_text()),
            ("alarms", f"{self.alarms_total} events, {len(self.intervals)} alarm periods"),
        ]

    def _degraded_text(self) -> str:
        """Seeds not sown on an RTK-fixed position, apart from the others, with the
        receiver's stated accuracy for them (records' ``accuracy_m``)."""
        s = self.summary
        not_fixed = {k: v for k, v in s.fixes.items() if k != "rtk_fixed" and v}
        n = sum(not_fixed.values())
        if not n and not s.extrapolated:
            return "none: every seed on RTK fixed, none extrapolated"
        parts = []
        for k, v in sorted(not_fixed.items()):
            acc = stated_accuracy_m(k, False)
            parts.append(f"{k} {v:,} (stated accuracy "
                         f"{'unknown' if acc is None else f'{acc:g} m'})")
        return (f"{n:,} seeds not RTK-fixed: " + ", ".join(parts) if n else "all RTK-fixed") + (
            f"; {s.extrapolated:,} extrapolated over dropouts (+{EXTRAPOLATED_EXTRA_M:g} m); "
            "the export's accuracy_m gives each seed's")

    def data(self) -> dict[str, Any]:
        s = self.summary
        return {
            "machine_id": self.machine_id,
            "seeds": s.seeds,
            "first_utc": _iso_us(s.first_us),
            "last_utc": _iso_us(s.last_us),
            "area_ha": s.area_ha,
            "seeds_by_row": {str(k): v for k, v in s.seeds_by_row.items()},
            "fixes": s.fixes,
            "extrapolated": s.extrapolated,
            "rtk_fixed_share": s.rtk_fixed_share,
            "extrapolated_share": s.extrapolated_share,
            "population_per_ha": s.population_mean_per_ha,
            "target_population_per_ha": s.target_population_per_ha,
            "seed_mass_kg": None if self.tsw_g is None else s.seeds * self.tsw_g / 1e6,
            "quality": quality_json(s.quality),
            "map_classes": dict(zip(CLASS_NAMES, self.seed_map.class_counts,
                                    strict=True)),
            "alarm_events": self.alarms_total,
            "alarm_periods": [
                {"code": i.code, "severity": i.severity, "from_utc": _iso_us(i.from_us),
                 "to_utc": _iso_us(i.to_us), "end": i.end}
                for i in self.intervals
            ],
            "daemon_runs": [
                {"start_utc": _iso_us(r.start_us),
                 "stop_utc": None if r.stop_us is None else _iso_us(r.stop_us),
                 "clean_stop": r.clean}
                for r in self.runs
            ],
        }

    def plots(self) -> list[tuple[str, str, Callable[[FigureBase | None], FigureBase]]]:
        """(heading, caption, draw) in the report's order: ``draw(None)`` makes a figure of
        its own (the HTML's PNG), ``draw(part)`` draws into a part of a PDF page."""
        s = self.summary
        return [
            ("Seed map", MAP_CAPTION,
             lambda fig: figures.seed_map(self.seed_map, "Seed map by spacing class", fig)),
            ("Spacing per row", HISTOGRAM_CAPTION,
             lambda fig: figures.spacing_histograms(s, self.shown_rows(), fig)),
            ("Applied rate along the drive", rate_note(s),
             lambda fig: figures.rate_along_drive(s, self.tsw_g, fig)),
            ("Applied rate against speed", SPEED_CAPTION,
             lambda fig: figures.rate_against_speed(s, self.tsw_g, fig)),
            ("Alarm timeline", TIMELINE_CAPTION,
             lambda fig: figures.alarm_timeline(self.intervals, *self.timeline_span(),
                                                stops=self.stops(), fig=fig)),
        ]

    def figures(self) -> Iterator[tuple[str, str, Figure]]:
        """(heading, caption, figure) in the report's order, drawn one at a time."""
        for heading, caption, draw in self.plots():
            fig = draw(None)
            assert isinstance(fig, Figure)
            yield heading, caption, fig

    def stops(self) -> list[int]:
        return [r.stop_us for r in self.runs if r.stop_us is not None]

    def timeline_span(self) -> tuple[int, int]:
        """The seeds' time span, widened to alarms of the window outside it (raised before
        the first seed or after the last), so every period shows."""
        start, end = self.summary.first_us, self.summary.last_us
        for i in self.intervals:
            start, end = min(start, i.from_us), max(end, i.to_us)
        return start, end


MAP_CAPTION = (
    "Each seed where it landed, coloured by the spacing to the previous seed of its row "
    "(ISO 7256-1: a multiple at ≤ 0.5 × the target, a miss at > 1.5 ×).")
HISTOGRAM_CAPTION = "How far apart the seeds of each row fell, against the target spacing."
SPEED_CAPTION = ("The same measured rate grouped by speed: a line falling at high speed means "
                 "the meter could not keep up.")
TIMELINE_CAPTION = ("Every alarm raised or cleared in the window; an alarm still active when "
                    "sowgate stopped ends at that stop.")
QUALITY_NOTE = (
    "Multiples: spacings ≤ 0.5 × the reference; misses: > 1.5 ×; quality of feed = 100 − "
    "multiples − misses (the singles); precision: the spread of the singles relative to the "
    "reference (lower is better). The reference is the target spacing, or each row's median "
    "spacing without one. The same figures as sowgate export.")


def rate_note(s: FieldSummary) -> str:
    note = ("The applied rate is the population the seed sensors counted: seeds per metre "
            "of row (from the stored spacings) over the row spacing. The controller's "
            "commanded rate is not in the record store.")
    if s.target_population_per_ha is None:
        note += (" No target spacing is configured ([positioning] target_spacing_m), so "
                 "there is no target line.")
    return note


def _day(us: int) -> str:
    return us_to_utc(us).strftime("%Y-%m-%d")


def _when(t: datetime) -> str:
    return t.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _when_us(us: int) -> str:
    return _when(us_to_utc(us))


def _iso_us(us: int) -> str:
    return us_to_utc(us).isoformat().replace("+00:00", "Z")


def _duration(seconds: float) -> str:
    h, rest = divmod(round(seconds), 3600)
    return f"{h} h {rest // 60:02d} min" if h else f"{rest // 60} min {rest % 60:02d} s"


def _rows_text(rows: Sequence[int]) -> str:
    return ",".join(str(r) for r in rows)


def signed_pct(v: float) -> str:
    """``+1.2 %``, ``-1.2 %``, and ``0.0 %`` for anything that rounds to zero (``:+.1f``
    wrote ``-0.0 %`` for a rate a hair under the target)."""
    text = f"{v:+.1f}"
    return "0.0 %" if float(text) == 0 else f"{text} %"


def _pct(v: float | None, digits: int = 1) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def quality_table(report: FieldReport) -> tuple[list[str], list[list[str]]]:
    head = ["row", "spacings", "multiples %", "misses %", "quality of feed %",
            "precision %", "mean spacing cm", "reference cm"]
    body = []
    for row, q in sorted(report.summary.quality.items()):
        body.append([
            str(row), f"{q.n:,}", _pct(q.multiples_index), _pct(q.miss_index),
            _pct(q.quality_of_feed_index), _pct(q.precision),
            _pct(None if q.mean_spacing_m is None else q.mean_spacing_m * 100),
            _pct(None if q.x_ref_m is None else q.x_ref_m * 100),
        ])
    return head, body


def _png(fig: Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI)
    return base64.b64encode(buf.getvalue()).decode("ascii")


CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0 auto;
max-width:1100px;padding:1em 1.5em;color:#222;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{margin-top:1.6em;border-bottom:2px solid #2e9e44}
table{border-collapse:collapse;margin:.5em 0}td,th{padding:.25em .7em;border-bottom:1px solid #ddd}
th{text-align:left;background:#f3f6f3}td.n{text-align:right;font-variant-numeric:tabular-nums}
table.summary th{width:11em;vertical-align:top}
img{max-width:100%;height:auto;border:1px solid #eee}.note{color:#555;font-size:.9em}
.bad{color:#d62728;font-weight:600}
"""


def to_html(report: FieldReport) -> bytes:
    e = html.escape
    parts = [
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">",
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">",
        f"<title>{e(report.title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{e(report.title)}</h1>",
        f"<p class=\"note\">Made by sowgate report on {_when(report.created)} from "
        f"{e(report.source)}. Opens offline: everything is in this one file.</p>",
        "<h2>Summary</h2><table class=\"summary\">",
    ]
    for k, v in report.summary_lines():
        parts.append(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>")
    parts.append("</table>")
    figs = report.figures()
    heading, caption, fig = next(figs)
    parts.append(_figure_html(heading, caption, fig))
    parts.append("<h2>Spacing quality per row (ISO 7256-1)</h2>")
    parts.append(f"<p class=\"note\">{html.escape(QUALITY_NOTE)}</p>")
    head, body = quality_table(report)
    parts.append("<table><tr>" + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>")
    for cells in body:
        parts.append("<tr>" + "".join(f"<td class=\"n\">{e(c)}</td>" for c in cells) + "</tr>")
    parts.append("</table>")
    for heading, caption, fig in figs:
        parts.append(_figure_html(heading, caption, fig))
    parts.append(_alarm_table(report))
    data = json.dumps(report.data()).replace("</", "<\\/")
    parts.append(f"<script type=\"application/json\" id=\"report-data\">{data}</script>")
    parts.append("</body></html>\n")
    return "\n".join(parts).encode("utf-8")


def _figure_html(heading: str, caption: str, fig: Figure) -> str:
    e = html.escape
    return (f"<h2>{e(heading)}</h2><p class=\"note\">{e(caption)}</p>"
            f"<img alt=\"{e(heading)}\" src=\"data:image/png;base64,{_png(fig)}\">")


ALARM_TABLE_HEAD = ["time (UTC)", "alarm", "severity", "", "message"]


def alarm_table(report: FieldReport) -> list[tuple[list[str], bool]]:
    """The alarm events shown (the first ``ALARM_ROWS_SHOWN``), with the daemon's starts and
    stops among them in time order: each row's cells and whether it is a critical raise.
    A stop names the alarms still active then, which end there (``gateway.recording.runs``)."""
    lo, hi = report.timeline_span()
    rows: list[tuple[int, int, list[str], bool]] = []
    for a in report.alarms[:ALARM_ROWS_SHOWN]:
        rows.append((utc_to_us(a.utc), 1, [
            a.utc.strftime("%Y-%m-%d %H:%M:%S"), a.code, a.severity,
            "raised" if a.active else "cleared", a.message,
        ], a.severity == "critical" and a.active))
    for r in report.runs:
        if lo <= r.start_us <= hi:
            rows.append((r.start_us, 0, [_when_us(r.start_us)[:-4], "daemon", "", "started",
                                         "sowgate started"], False))
        if r.stop_us is not None and lo <= r.stop_us <= hi:
            ended = sorted({i.code for i in report.intervals
                            if i.end == "stop" and i.to_us == r.stop_us})
            text = "sowgate stopped" if r.clean else (
                "sowgate stopped without marking it (power cut or killed): the time of its "
                "last record")
            if ended:
                text += "; alarms still active end here: " + ", ".join(ended)
            rows.append((r.stop_us, 2, [_when_us(r.stop_us)[:-4], "daemon", "", "stopped",
                                        text], False))
    rows.sort(key=lambda row: (row[0], row[1]))
    return [(cells, bad) for _us, _order, cells, bad in rows]


def _alarm_table(report: FieldReport) -> str:
    e = html.escape
    if not report.alarms:
        return "<h2>Alarm events</h2><p>No alarm was raised or cleared in this window.</p>"
    out = ["<h2>Alarm events</h2><table><tr>"
           + "".join(f"<th>{e(h)}</th>" for h in ALARM_TABLE_HEAD) + "</tr>"]
    for cells, bad in alarm_table(report):
        time, code, severity, what, message = cells
        cls = " class=\"bad\"" if bad else ""
        out.append(
            f"<tr><td>{e(time)}</td><td>{e(code)}</td><td{cls}>{e(severity)}</td>"
            f"<td>{e(what)}</td><td>{e(message)}</td></tr>"
        )
    out.append("</table>")
    if report.alarms_total > ALARM_ROWS_SHOWN:
        out.append(f"<p class=\"note\">The first {ALARM_ROWS_SHOWN} of "
                   f"{report.alarms_total} events; all are in the timeline.</p>")
    return "".join(out)
