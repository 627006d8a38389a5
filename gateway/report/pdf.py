"""The field report as a PDF to print: A4 portrait pages throughout, laid out like a document.

Why a layout of its own: the report's plots have the sizes a screen wants (11 inches wide, a
histogram figure as tall as its rows), and saved one per page they made a PDF of mixed page
sizes (A4, then 720 x 1123 pt, then strips of 792 x 216 pt) that no printer takes, with each
caption drawn over the plot's x-axis labels and a first page half empty.

Here every page is an A4 matplotlib figure (``PdfPages``). The content flows down the pages
as a word processor would: blocks (the title, the summary, each plot with its heading and
caption above it, the tables) are placed one below the other, and a block that does not fit
in what is left of a page starts the next one. The seed map is stretchable: it fills what
page 1 leaves below the summary. Tables (the per-row quality, the alarm events) continue on
the next page with their header repeated; the per-row histograms go a page-full of rows at a
time. Each block is a ``SubFigure`` of the page at a fixed place, and the page's constrained
layout arranges the axes inside each block, so nothing of one block can reach into another:
a caption sits above its plot, never over its axis labels.

Text is wrapped here by an estimate of the characters a line holds (``CHAR_EM``: DejaVu Sans,
matplotlib's font, averages under 0.6 em a character), since matplotlib does not wrap text to
a given width; the PDF test checks on the rendered pages that no two words overlap and that
everything is inside the page.
"""

from __future__ import annotations

import io
import math
import textwrap
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import matplotlib
import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure, FigureBase, SubFigure
from matplotlib.layout_engine import ConstrainedLayoutEngine
from matplotlib.lines import Line2D

from gateway.report import figures
from gateway.report.document import (
    ALARM_ROWS_SHOWN,
    ALARM_TABLE_HEAD,
    HISTOGRAM_CAPTION,
    QUALITY_NOTE,
    TIMELINE_CAPTION,
    FieldReport,
    alarm_table,
    quality_table,
)

A4_IN = (8.27, 11.69)
MARGIN_X_IN = 0.6
MARGIN_TOP_IN = 0.55
FOOTER_IN = 0.55  # the page's bottom margin, with the page number in it
CONTENT_W_IN = A4_IN[0] - 2 * MARGIN_X_IN
CONTENT_H_IN = A4_IN[1] - MARGIN_TOP_IN - FOOTER_IN
CHAR_EM = 0.56  # mean character width of DejaVu Sans text in em, rounded up
DIGIT_EM = 0.64  # a digit's width (numbers do not wrap: their columns must hold them)
BOLD_EM = 0.72  # widest bold lowercase and digits (a header's longest word)
LINE_SPACING = 1.3  # line height in em
GAP_IN = 0.12  # between blocks
TEXT_PT = 8.5
CAPTION_PT = 8.0
HEADING_PT = 12.0
TABLE_PT = 7.5
MAP_MIN_IN = 4.5  # the seed map shrinks to what page 1 leaves, but not below this
HIST_PANEL_IN = 1.75  # height of one line of per-row histograms
GREY = "#555555"


def _chars(width_in: float, pt: float) -> int:
    """Characters of ``pt`` text that fit in ``width_in`` (by the ``CHAR_EM`` estimate)."""
    return max(1, int(width_in * 72 / (pt * CHAR_EM)))


def _text_in(text: str, pt: float) -> float:
    """Estimated width of ``text`` in inches: digits are wider than the mean character."""
    digits = sum(c.isdigit() for c in text)
    return (digits * DIGIT_EM + (len(text) - digits) * CHAR_EM) * pt / 72


def _line_in(pt: float) -> float:
    return pt * LINE_SPACING / 72


def _wrap(text: str, width_in: float, pt: float) -> list[str]:
    return textwrap.wrap(text, _chars(width_in, pt), break_long_words=True) or [""]


@dataclass
class Block:
    """A piece of a page: ``draw`` fills a part of the page ``height_in`` tall. A block with
    ``min_in`` may be given any height from it up to ``height_in`` (the seed map)."""

    height_in: float
    draw: Callable[[SubFigure, float], None]  # (part of the page, the height it got)
    min_in: float | None = None


@dataclass
class Table:
    """Rows under a header, split across pages when they do not fit (header repeated)."""

    title: str
    note: str
    head: list[str]
    rows: list[list[str]]
    widths_in: list[float]
    right: list[bool]  # right-aligned columns (numbers)
    emphasis: list[bool] = field(default_factory=list)  # rows drawn red and bold
    pt: float = TABLE_PT

    def cell_lines(self, cells: Sequence[str], head: bool = False) -> list[list[str]]:
        """Each cell's lines: text wraps to its column; numbers do not (their column is as
        wide as the widest), a header's words do."""
        return [
            _wrap(c, w - 0.08, self.pt) if head or not r else [c]
            for c, w, r in zip(cells, self.widths_in, self.right, strict=True)
        ]

    def row_in(self, cells: Sequence[str], head: bool = False) -> float:
        lines = self.cell_lines(cells, head)
        return max(len(c) for c in lines) * _line_in(self.pt) + 0.04


def _heading_lines(heading: str, caption: str) -> tuple[list[str], float]:
    lines = _wrap(caption, CONTENT_W_IN, CAPTION_PT) if caption else []
    return lines, _line_in(HEADING_PT) + 0.06 + len(lines) * _line_in(CAPTION_PT) + 0.06


def _draw_heading(part: SubFigure, height_in: float, heading: str, lines: list[str]) -> None:
    part.text(0, 1, heading, fontsize=HEADING_PT, fontweight="bold", va="top",
              transform=part.transSubfigure)
    if lines:
        y = 1 - (_line_in(HEADING_PT) + 0.06) / height_in
        part.text(0, y, "\n".join(lines), fontsize=CAPTION_PT, color=GREY, va="top",
                  linespacing=LINE_SPACING, transform=part.transSubfigure)


def plot_block(
    heading: str, caption: str, plot_in: float,
    draw: Callable[[FigureBase], object], min_in: float | None = None,
) -> Block:
    """A plot under its heading and caption (above it: a caption never covers axis labels)."""
    lines, text_in = _heading_lines(heading, caption)

    def place(part: SubFigure, height_in: float) -> None:
        top, bottom = _split(part.subfigures(2, 1, height_ratios=(text_in, height_in - text_in)))
        _draw_heading(top, text_in, heading, lines)
        draw(bottom)

    return Block(text_in + plot_in, place, None if min_in is None else text_in + min_in)


def text_block(heading: str, pairs: Sequence[tuple[str, str]], title: bool = False) -> Block:
    """A heading and ``key: value`` lines (the summary), values wrapped beside their keys."""
    key_in = 1.35
    wrapped = [(k, _wrap(v, CONTENT_W_IN - key_in, TEXT_PT)) for k, v in pairs]
    head_pt = 16.0 if title else HEADING_PT
    head_in = _line_in(head_pt) + 0.08
    rows_in = [len(lines) * _line_in(TEXT_PT) + 0.03 for _k, lines in wrapped]

    def place(part: SubFigure, height_in: float) -> None:
        def y(inches: float) -> float:
            return 1 - inches / height_in

        part.text(0, 1, heading, fontsize=head_pt, fontweight="bold", va="top",
                  transform=part.transSubfigure)
        at = head_in
        for (key, lines), row_in in zip(wrapped, rows_in, strict=True):
            part.text(0, y(at), key, fontsize=TEXT_PT, fontweight="bold", va="top",
                      transform=part.transSubfigure)
            part.text(key_in / CONTENT_W_IN, y(at), "\n".join(lines), fontsize=TEXT_PT,
                      va="top", linespacing=LINE_SPACING, transform=part.transSubfigure)
            at += row_in

    return Block(head_in + sum(rows_in), place)


def _table_block(table: Table, rows: Sequence[int], first: bool) -> Block:
    """The header and ``rows`` (indices into ``table.rows``) as one block."""
    title_lines = _wrap(table.note, CONTENT_W_IN, CAPTION_PT) if first and table.note else []
    title_in = _line_in(HEADING_PT) + 0.06 + len(title_lines) * _line_in(CAPTION_PT) + 0.06
    head_in = table.row_in(table.head, head=True)
    heights = [table.row_in(table.rows[i]) for i in rows]
    xs = [sum(table.widths_in[:k]) for k in range(len(table.widths_in) + 1)]

    def place(part: SubFigure, height_in: float) -> None:
        def y(inches: float) -> float:
            return 1 - inches / height_in

        _draw_heading(part, height_in, table.title if first else f"{table.title} (continued)",
                      title_lines)
        at = title_in
        for cells, row_in, style in [(table.head, head_in, "head")] + [
            (table.rows[i], h, "bad" if table.emphasis and table.emphasis[i] else "")
            for i, h in zip(rows, heights, strict=True)
        ]:
            for k, lines in enumerate(table.cell_lines(cells, style == "head")):
                right = table.right[k]
                x = (xs[k + 1] - 0.08 if right else xs[k]) / CONTENT_W_IN
                bad = style == "bad" and k == 2
                part.text(x, y(at + 0.02), "\n".join(lines), fontsize=table.pt,
                          ha="right" if right else "left", va="top",
                          linespacing=LINE_SPACING, transform=part.transSubfigure,
                          fontweight="bold" if style == "head" or bad else "normal",
                          color="#d62728" if bad else "black")
            at += row_in
            part.add_artist(_rule(part, y(at - 0.01), style == "head"))

    return Block(title_in + head_in + sum(heights), place)


def _rule(part: SubFigure, y: float, strong: bool) -> Line2D:
    return Line2D([0, 1], [y, y], transform=part.transSubfigure,
                  color="#888888" if strong else "#dddddd", lw=0.8 if strong else 0.5)


def _column_widths(head: Sequence[str], rows: Sequence[Sequence[str]], pt: float,
                   wrap_last: bool) -> list[float]:
    """Each column as wide as its longest cell (or the longest word of its header); with
    ``wrap_last`` the last column takes what is left (its text wraps)."""
    widths = []
    for k, h in enumerate(head):
        cells = max(_text_in(r[k], pt) for r in rows)
        word = max((len(w) for w in h.split()), default=0) * pt * BOLD_EM / 72
        widths.append(max(cells, word) + 0.2)
    if wrap_last:
        widths[-1] = max(1.5, CONTENT_W_IN - sum(widths[:-1]))
    scale = min(1.0, CONTENT_W_IN / sum(widths))
    return [w * scale for w in widths]


def quality_block_table(report: FieldReport) -> Table:
    head, body = quality_table(report)
    body = body or [["–"] * len(head)]
    return Table("Spacing quality per row (ISO 7256-1)", QUALITY_NOTE, head, body,
                 _column_widths(head, body, TABLE_PT, False), [True] * len(head))


def alarm_block_table(report: FieldReport) -> Table:
    rows = alarm_table(report)
    note = (f"The first {ALARM_ROWS_SHOWN} of {report.alarms_total} events; all are in the "
            "timeline." if report.alarms_total > ALARM_ROWS_SHOWN else "")
    if not report.alarms:
        note = "No alarm was raised or cleared in this window."
    cells = [c for c, _bad in rows]
    return Table("Alarm events", note, ALARM_TABLE_HEAD, cells,
                 _column_widths(ALARM_TABLE_HEAD, cells or [[""] * 5], TABLE_PT, True),
                 [False] * len(ALARM_TABLE_HEAD), [bad for _c, bad in rows])


def histogram_blocks(report: FieldReport) -> list[Block]:
    """The per-row histograms, a page-full of rows at a time."""
    rows = report.shown_rows()
    s = report.summary
    cols = 3 if len(rows) <= 9 else 4
    _lines, text_in = _heading_lines("Spacing per row", HISTOGRAM_CAPTION)
    label_in = 0.75  # the shared x label's two lines
    lines_per_page = max(1, int((CONTENT_H_IN - text_in - label_in) / HIST_PANEL_IN))
    per_page = cols * lines_per_page
    blocks = []
    for k in range(0, max(1, len(rows)), per_page):
        chunk = rows[k:k + per_page]
        heading = "Spacing per row" if k == 0 else (
            f"Spacing per row (continued: rows {chunk[0]}–{chunk[-1]})")
        panel_lines = math.ceil(len(chunk) / cols)

        def draw(part: FigureBase, chunk: list[int] = chunk) -> None:
            figures.spacing_histograms(s, chunk, part, cols=cols, title_pt=8.5)

        blocks.append(plot_block(heading, HISTOGRAM_CAPTION if k == 0 else "",
                                 panel_lines * HIST_PANEL_IN + label_in, draw))
    return blocks


def report_blocks(report: FieldReport) -> list[Block | Table]:
    m = report.seed_map
    x0, x1, y0, y1 = m.extent_m
    aspect = min(max((y1 - y0) / max(x1 - x0, 1.0), 0.4), 1.6)
    plots = {heading: (caption, draw) for heading, caption, draw in report.plots()}
    codes = len({i.code for i in report.intervals})

    def plot(heading: str, plot_in: float, min_in: float | None = None) -> Block:
        caption, draw = plots[heading]
        return plot_block(heading, caption, plot_in, draw, min_in)

    return [
        text_block(report.title, [("made", f"by sowgate report on "
                                            f"{report.created:%Y-%m-%d %H:%M UTC}")],
                   title=True),
        text_block("Summary", report.summary_lines()),
        plot("Seed map", CONTENT_W_IN * aspect * 0.9 + 1.2, MAP_MIN_IN),
        quality_block_table(report),
        *histogram_blocks(report),
        plot("Applied rate along the drive", 4.8),
        plot("Applied rate against speed", 3.3),
        plot_block("Alarm timeline", TIMELINE_CAPTION, min(8.0, 1.9 + 0.3 * max(1, codes)),
                   lambda part: figures.alarm_timeline(
                       report.intervals, *report.timeline_span(), stops=report.stops(),
                       fig=part, most_ticks=7)),
        alarm_block_table(report),
    ]


def paginate(items: Sequence[Block | Table]) -> list[list[tuple[Block, float]]]:
    """The blocks placed on pages: (block, height it gets) per page, in order."""
    pages: list[list[tuple[Block, float]]] = [[]]
    left = CONTENT_H_IN

    def new_page() -> None:
        nonlocal left
        pages.append([])
        left = CONTENT_H_IN

    def place(block: Block) -> None:
        nonlocal left
        gap = GAP_IN if pages[-1] else 0.0
        height = block.height_in
        if block.min_in is not None and left - gap >= block.min_in:
            height = min(height, left - gap)
        elif height > left - gap and pages[-1]:
            new_page()
            gap = 0.0
        height = min(height, CONTENT_H_IN)
        pages[-1].append((block, height))
        left -= gap + height

    for item in items:
        if isinstance(item, Block):
            place(item)
            continue
        indices = list(range(len(item.rows)))
        row_in = [item.row_in(r) for r in item.rows]
        first = True
        while True:  # as many rows as fit, the rest on the next page
            taken: list[int] = []
            height = _table_block(item, [], first).height_in  # its heading and header
            for i in indices:
                height += row_in[i]
                if height > left - (GAP_IN if pages[-1] else 0.0) and (taken or pages[-1]):
                    break
                taken.append(i)
            if not taken and indices:
                new_page()
                continue
            place(_table_block(item, taken, first))
            indices = indices[len(taken):]
            first = False
            if not indices:
                break
            new_page()
    return [p for p in pages if p]


def _page(blocks: list[tuple[Block, float]], footer: str) -> Figure:
    fig = Figure(figsize=A4_IN, layout=ConstrainedLayoutEngine(
        w_pad=2 / 72, h_pad=2 / 72, wspace=0.0, hspace=0.0))
    _l, column, _r = _split(fig.subfigures(
        1, 3, width_ratios=(MARGIN_X_IN, CONTENT_W_IN, MARGIN_X_IN), wspace=0))
    heights: list[float] = [MARGIN_TOP_IN]
    for k, (_block, h) in enumerate(blocks):
        heights += ([GAP_IN] if k else []) + [h]
    used = sum(heights)
    heights += [max(1e-3, A4_IN[1] - used)]  # the rest of the page and its bottom margin
    parts = _split(column.subfigures(len(heights), 1, height_ratios=heights, hspace=0))
    k = 1
    for n, (block, h) in enumerate(blocks):
        if n:
            k += 1  # the gap
        block.draw(parts[k], h)
        k += 1
    fig.text(0.5, 0.3 / A4_IN[1], footer, ha="center", va="bottom", fontsize=7, color=GREY)
    return fig


def _split(parts: SubFigure | np.ndarray[Any, Any]) -> list[SubFigure]:
    """``subfigures`` as a list (it returns a lone SubFigure for one part)."""
    return [parts] if isinstance(parts, SubFigure) else list(parts.ravel())


def to_pdf(report: FieldReport) -> bytes:
    pages = paginate(report_blocks(report))
    buf = io.BytesIO()
    # TrueType (Type 42) fonts: text a PDF reader can select and search, with its real
    # metrics (a Type 3 font gives every word the font's whole bounding box)
    with matplotlib.rc_context({"pdf.fonttype": 42}), PdfPages(buf) as pdf:
        for n, blocks in enumerate(pages, 1):
            fig = _page(blocks, f"{report.title} · page {n} of {len(pages)}")
            pdf.savefig(fig)
        info = pdf.infodict()
        info["Title"] = report.title
        info["Creator"] = "sowgate report"
    return buf.getvalue()
