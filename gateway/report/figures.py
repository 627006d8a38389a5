"""The report's plots, drawn with matplotlib's Agg backend (no display, no network).

Each function takes the streamed results (``FieldSummary``, ``MapResult``) and returns a
``Figure``; the document puts them in the HTML as PNG or on PDF pages. Colours stay the same
across the report: good seeds green, multiples purple, misses red, target lines black dashed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from datetime import UTC, datetime

import matplotlib

matplotlib.use("Agg")

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure, FigureBase
from matplotlib.patches import Patch
from matplotlib.ticker import FixedLocator, FuncFormatter

from gateway.recording.field_stats import (
    CLASS_NAMES,
    GOOD,
    MISS,
    MULTIPLE,
    UNRATED,
    AlarmInterval,
    FieldSummary,
    MapResult,
)
from gateway.recording.spacing_quality import MISS_LIMIT, MULTIPLE_LIMIT

CLASS_COLOURS = {GOOD: "#2e9e44", MULTIPLE: "#7b3fbf", MISS: "#d62728", UNRATED: "#9e9e9e"}
SEVERITY_COLOURS = {"critical": "#d62728", "warning": "#ff9f1c", "info": "#4a90d9"}
MIN_CELL_SEEDS = 30  # a raster square with fewer rated seeds is not coloured
DRIVE_POINTS = 400  # points along the drive (each a stretch of equal distance)
# A point of the rate along the drive is the mean of at least this many spacings: 10 % CV
# per spacing gives ±1.4 % per point. The first and last second of a drive hold a handful of
# seeds, and drawn alone they showed a 25 % spike a farmer would read as a failing meter.
MIN_STRETCH_SPACINGS = 50


def _us_to_dt(us: float) -> datetime:
    return datetime.fromtimestamp(us / 1e6, UTC)


def seed_map(
    m: MapResult, title: str, fig: FigureBase | None = None, *, stacked: bool | None = None
) -> FigureBase:
    """Every seed as a dot coloured by its class, or (a raster, for many seeds) three maps
    of the same squares: singles %, misses %, multiples %, side by side for a field taller
    than wide, else stacked (``stacked`` forces one, e.g. on a portrait page).

    Drawn into ``fig`` (a part of a PDF page) when given, else into a figure of its own
    (the HTML's PNG); so for every plot here."""
    x0, x1, y0, y1 = m.extent_m
    w, h = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
    total = max(1, sum(m.class_counts))
    legend = [
        f"{CLASS_NAMES[c]}: {m.class_counts[c]:,} ({100 * m.class_counts[c] / total:.1f} %)"
        for c in (GOOD, MULTIPLE, MISS, UNRATED)
        if m.class_counts[c]
    ]
    if m.points is not None:
        aspect = min(max(h / w, 0.4), 1.6)
        if fig is None:
            fig = Figure(figsize=(10, 10 * aspect * 0.9 + 1.2), layout="constrained")
        ax = fig.add_subplot()
        x, y, cls = m.points
        size = float(np.clip(20_000 / max(1, x.size), 0.3, 12))
        # good seeds first, so the rarer multiples and misses are drawn on top of them
        for c in (GOOD, UNRATED, MULTIPLE, MISS):
            sel = cls == c
            if sel.any():
                ax.scatter(x[sel], y[sel], s=size * (1 if c == GOOD else 2.5),
                           c=CLASS_COLOURS[c], linewidths=0, rasterized=True)
        handles = [Patch(color=CLASS_COLOURS[c], label=text) for c, text in zip(
            [c for c in (GOOD, MULTIPLE, MISS, UNRATED) if m.class_counts[c]], legend,
            strict=True)]
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=9,
                  title="seed by its spacing")
        _map_axes(ax, f"every seed drawn ({x.size:,})", adjustable="datalim")
        ax.set_title(title)
        return fig
    assert m.raster is not None
    counts = m.raster.astype(float)
    rated = counts[GOOD] + counts[MULTIPLE] + counts[MISS]
    rated[rated < MIN_CELL_SEEDS] = 0  # the field's edges: a share of a handful means nothing
    cell = (x1 - x0) / max(1, counts.shape[2] - 1)
    side_by_side = h >= w if stacked is None else not stacked
    if fig is None:
        fig = Figure(figsize=(13, 9) if side_by_side else (11, 13), layout="constrained")
    axes = (fig.subplots(1, 3, sharey=True) if side_by_side
            else fig.subplots(3, 1, sharex=True))
    panels = [
        (GOOD, "singles (quality of feed) %", "RdYlGn", (80, 100)),
        (MISS, "misses %", "Reds", (0, 20)),
        (MULTIPLE, "multiples %", "Purples", (0, 20)),
    ]
    for ax, (c, label, cmap, (lo, hi)) in zip(axes, panels, strict=True):
        with np.errstate(divide="ignore", invalid="ignore"):
            share = np.where(rated > 0, 100.0 * counts[c] / rated, np.nan)
        im = ax.imshow(share, origin="lower", extent=(x0, x1, y0, y1), cmap=cmap,
                       vmin=lo, vmax=hi, interpolation="nearest")
        fig.colorbar(im, ax=ax, label=label, shrink=0.8,
                     extend="min" if c == GOOD else "max")
        ax.set_title(label)
        _map_axes(ax, "")
    fig.suptitle(f"{title}: {total:,} seeds in {cell:.1f} m squares,\neach coloured by the "
                 f"share of its seeds in a class (squares with under {MIN_CELL_SEEDS} seeds "
                 f"left blank)\n" + ";  ".join(legend), fontsize=10)
    return fig


def _map_axes(ax: Axes, how: str, adjustable: str = "box") -> None:
    """Metres east and north at one scale. ``datalim``: the axes keep the size they were
    given and show more ground around a narrow field (a 2 m strip 90 m long drew an axes a
    few millimetres wide, its tick labels on top of each other)."""
    ax.set_aspect("equal", adjustable=adjustable)  # type: ignore[arg-type]
    ax.set_xlabel("east (m from the field's centre)" + (f"\n{how}" if how else ""), fontsize=9)
    ax.set_ylabel("north (m)", fontsize=9)
    ax.grid(alpha=0.3)


def histogram_columns(rows: int) -> int:
    """Panels per line: 3 up to 9 rows (each panel wide enough to read its ticks on a
    laptop screen; 6 in one line were 2.6 inches and their labels 7 px), 4 up to 24, then 6."""
    return max(1, min(rows, 3 if rows <= 9 else 4 if rows <= 24 else 6))


def spacing_histograms(
    s: FieldSummary, rows: Sequence[int], fig: FigureBase | None = None,
    cols: int | None = None, title_pt: float | None = None,
) -> FigureBase:
    """A histogram per row; ``cols`` panels a line (default ``histogram_columns``);
    ``title_pt``: the panels' title size (a printed page's panels are narrower)."""
    cols = cols or histogram_columns(len(rows))
    nrows = math.ceil(len(rows) / cols)
    if fig is None:
        width = 11.0 if cols <= 4 else 2.6 * cols + 0.6
        panel_h = 2.6 if cols <= 4 else 2.0
        height = panel_h * nrows + 1.2
        fig = Figure(figsize=(width, height))
        # laid out by hand: constrained layout over 48 axes costs seconds (a PDF page holds
        # fewer, and its page's constrained layout places them)
        fig.subplots_adjust(left=0.7 / width, right=0.99, top=1 - 0.4 / height,
                            bottom=0.75 / height, hspace=0.5, wspace=0.2)
    axes = fig.subplots(nrows, cols, squeeze=False, sharex=True)
    edges_cm = s.hist_edges_m * 100
    for k, row in enumerate(rows):
        ax = axes[k // cols][k % cols]
        counts = s.hist_by_row.get(row)
        q = s.quality.get(row)
        ref = q.x_ref_m if q is not None else None
        if counts is not None and counts.sum() > 0:
            share = 100.0 * counts[:-1] / counts.sum()
            ax.stairs(share, edges_cm, fill=True, color="#4a7fb5")
        if ref is not None:
            r = ref * 100
            ax.axvspan(0, MULTIPLE_LIMIT * r, color=CLASS_COLOURS[MULTIPLE], alpha=0.12)
            ax.axvspan(MISS_LIMIT * r, edges_cm[-1], color=CLASS_COLOURS[MISS], alpha=0.10)
            ax.axvline(r, color="black", ls="--", lw=1)
        a = "–" if q is None or q.quality_of_feed_index is None else (
            f"{q.quality_of_feed_index:.1f} %")
        ax.set_title(f"row {row}: singles {a}",
                     fontsize=title_pt or (10 if cols <= 4 else 9))
        ax.tick_params(labelsize=9 if cols <= 4 else 7, labelbottom=True)
    for k in range(len(rows), nrows * cols):
        axes[k // cols][k % cols].set_visible(False)
    fig.supxlabel("spacing to the previous seed in the row (cm)\ndashed: target "
                  "(or the row's median); purple: multiples, red: misses", fontsize=9)
    fig.supylabel("% of the row's spacings", fontsize=10)
    return fig


def _drive_stretches(s: FieldSummary) -> dict[str, np.ndarray]:
    """The per-second sums grouped into ``DRIVE_POINTS`` stretches of equal distance."""
    d = s.drive
    seconds = np.where(d["seeds"] > 0, s.time_bin_s, 0.0)
    speed = np.divide(d["speed_sum"], d["seeds"], out=np.zeros_like(d["seeds"]),
                      where=d["seeds"] > 0)
    dist = speed / 3.6 * seconds  # metres driven in each bin while sowing
    cum = np.cumsum(dist)
    total = cum[-1] if cum.size else 0.0
    if cum.size == 0 or total <= 0:
        return {"km": np.zeros(0), "n": np.zeros(0), "pop": np.zeros(0),
                "speed": np.zeros(0), "t": np.zeros(0)}
    bounds = np.searchsorted(cum, np.linspace(0, total, DRIVE_POINTS + 1)[:-1])
    starts = _merge_thin(np.unique(np.clip(bounds, 0, cum.size - 1)), d["sp_n"])

    def grouped(a: np.ndarray) -> np.ndarray:
        return np.add.reduceat(a, starts)

    sp_n, sp_sum = grouped(d["sp_n"]), grouped(d["sp_sum"])
    seeds, sp_speed = grouped(d["seeds"]), grouped(d["speed_sum"])
    mid = (cum[starts] - dist[starts] / 2 + np.append(cum[starts[1:] - 1], total)) / 2
    return {
        "km": mid / 1000,
        "n": sp_n,
        "pop": s.population_per_ha(sp_n, sp_sum),
        "speed": np.divide(sp_speed, seeds, out=np.full_like(seeds, np.nan), where=seeds > 0),
        "t": d["start_us"][starts],
    }


def _merge_thin(starts: np.ndarray, sp_n: np.ndarray) -> np.ndarray:
    """The group starts (indices into the time bins) with every group holding at least
    ``MIN_STRETCH_SPACINGS`` spacings: a thin group joins the next; a thin last one the one
    before (a drive shorter than that is one point)."""
    counts = np.add.reduceat(sp_n, starts) if starts.size else np.zeros(0)
    keep: list[int] = []
    held = 0.0
    for start, n in zip(starts.tolist(), counts.tolist(), strict=True):
        if not keep or held >= MIN_STRETCH_SPACINGS:
            keep.append(start)
            held = 0.0
        held += n
    if len(keep) > 1 and held < MIN_STRETCH_SPACINGS:
        keep.pop()
    return np.asarray(keep, dtype=starts.dtype)


def _rate_axis(ax: Axes, pop: np.ndarray, target: float | None) -> None:
    """Seeds/ha in thousands, the target ±5 % shaded, and a range of at least ±15 % around
    the target, so ordinary noise does not look like a failing meter."""
    ax.set_ylabel("seeds/ha (thousands)")
    finite = pop[np.isfinite(pop)] / 1000
    if target is None:
        return
    t = target / 1000
    ax.axhspan(0.95 * t, 1.05 * t, color="#2e9e44", alpha=0.08, label="target ± 5 %")
    lo = min(0.85 * t, float(finite.min()) if finite.size else t)
    hi = max(1.15 * t, float(finite.max()) if finite.size else t)
    pad = 0.03 * (hi - lo)
    ax.set_ylim(lo - pad, hi + pad)


def rate_along_drive(
    s: FieldSummary, tsw_g: float | None, fig: FigureBase | None = None
) -> FigureBase:
    if fig is None:
        fig = Figure(figsize=(11, 6.5), layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    st = _drive_stretches(s)
    x, unit = st["km"], "km"
    if x.size and x[-1] < 2.0:  # a short drive in metres
        x, unit = x * 1000, "m"
    top.plot(x, st["pop"] / 1000, color="#1f5f99", lw=1.2,
             label="applied (measured by the seed sensors)")
    target = s.target_population_per_ha
    if target is not None:
        top.axhline(target / 1000, color="black", ls="--", lw=1.2,
                    label=f"target ({target / 1000:,.1f} k seeds/ha)")
    _rate_axis(top, st["pop"], target)
    top.set_title("Applied rate against target along the drive")
    top.grid(alpha=0.3)
    top.legend(loc="lower right", fontsize=9)
    if tsw_g is not None:
        k = tsw_g / 1000.0  # k seeds/ha x g per seed = kg/ha
        sec = top.secondary_yaxis("right", functions=(lambda v: v * k, lambda v: v / k))
        sec.set_ylabel("kg/ha")
    bottom.plot(x, st["speed"], color="#555", lw=1)
    bottom.set_ylabel("speed (km/h)")
    bottom.set_xlabel(f"distance driven while sowing ({unit}; headland turns and stops left out)")
    bottom.grid(alpha=0.3)
    return fig


def rate_against_speed(
    s: FieldSummary, tsw_g: float | None, fig: FigureBase | None = None
) -> FigureBase:
    if fig is None:
        fig = Figure(figsize=(11, 4.5), layout="constrained")
    ax = fig.add_subplot()
    v = s.by_speed
    total = v["sp_n"].sum()
    # speed classes holding at least 0.2 % of the spacings: the rest are a handful of seeds
    keep = v["sp_n"] >= max(20.0, 0.002 * total)
    kmh = v["kmh"][keep] + 0.25
    pop = s.population_per_ha(v["sp_n"][keep], v["sp_sum"][keep]) / 1000
    share = 100.0 * v["sp_n"][keep] / max(total, 1.0)
    ax.plot(kmh, pop, "o-", color="#1f5f99", label="applied, per 0.5 km/h speed class")
    target = s.target_population_per_ha
    if target is not None:
        ax.axhline(target / 1000, color="black", ls="--", lw=1.2, label="target")
    _rate_axis(ax, pop * 1000, target)
    ax.set_xlabel("speed (km/h)")
    ax.set_title("Applied rate against speed (does the meter keep up when driving faster?)")
    ax.grid(alpha=0.3)
    twin = ax.twinx()
    twin.bar(kmh, share, width=0.45, color="#bbb", alpha=0.5, zorder=0)
    twin.set_ylabel("% of seeds sown at that speed", color="#777")
    ax.set_zorder(twin.get_zorder() + 1)
    ax.patch.set_visible(False)
    ax.legend(loc="lower left", fontsize=9)
    if tsw_g is not None:
        k = tsw_g / 1000.0
        ax.text(0.99, 0.02, f"k seeds/ha × {k:g} = kg/ha (thousand-seed mass {tsw_g:g} g)",
                transform=ax.transAxes, ha="right", fontsize=8, color="#555")
    return fig


TICK_STEPS_S = (1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800, 21600)


def clock_ticks_h(start_us: int, span_h: float, most: int = 12) -> list[float]:
    """Ticks (hours from ``start_us``) on round clock times: every 10 s, 5 min, 1 h...,
    the smallest step that gives at most ``most`` ticks."""
    span_s = span_h * 3600
    step = next((s for s in TICK_STEPS_S if span_s / s <= most), 3600 * math.ceil(
        span_s / most / 3600))
    start_s = start_us / 1e6
    first = math.ceil(start_s / step) * step
    return [(t - start_s) / 3600 for t in np.arange(first, start_s + span_s + 1e-9, step)]


def time_tick_formatter(start_us: int, span_h: float) -> Callable[[float, object], str]:
    """Tick labels for an axis in hours from ``start_us``: HH:MM, with seconds when the
    window is under 20 minutes (a 90 s window labelled 10:57 ten times said nothing)."""
    fmt = "%H:%M:%S" if span_h < 1 / 3 else "%H:%M"

    def label(h: float, _pos: object) -> str:
        return _us_to_dt(start_us + h * 3.6e9).strftime(fmt)

    return label


def alarm_timeline(
    intervals: Sequence[AlarmInterval], start_us: int, end_us: int,
    stops: Sequence[int] = (),
    fig: FigureBase | None = None,
    most_ticks: int = 12,
) -> FigureBase:
    """A bar per alarm period; a period still active when the daemon stopped ends at that
    stop (hatched), and each daemon stop in the window is a dotted line."""
    codes = sorted({i.code for i in intervals})
    if fig is None:
        fig = Figure(figsize=(11, 1.6 + 0.35 * max(1, len(codes))), layout="constrained")
    ax = fig.add_subplot()
    span_h = max((end_us - start_us) / 3.6e9, 1 / 60)

    def hours(us: int) -> float:
        return (us - start_us) / 3.6e9

    if not codes:
        ax.text(0.5, 0.5, "no alarms in this window", ha="center", va="center",
                transform=ax.transAxes, fontsize=12)
        ax.set_yticks([])
    for iv in intervals:
        y = codes.index(iv.code)
        width = max(hours(iv.to_us) - hours(iv.from_us), span_h / 400)  # a blip still shows
        ax.barh(y, width, left=hours(iv.from_us), height=0.6,
                color=SEVERITY_COLOURS.get(iv.severity, "#888"),
                edgecolor="none" if iv.end == "cleared" else "black",
                hatch="///" if iv.end == "stop" else None)
    for stop in stops:
        if start_us <= stop <= end_us:
            ax.axvline(hours(stop), color="#555", ls=":", lw=1.2)
    if codes:
        ax.set_yticks(range(len(codes)), codes, fontsize=9)
        ax.invert_yaxis()
        ax.legend(handles=[Patch(color=c, label=k) for k, c in SEVERITY_COLOURS.items()],
                  loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8, title="severity")
    ax.set_xlim(0, span_h)
    ax.xaxis.set_major_locator(FixedLocator(clock_ticks_h(start_us, span_h, most_ticks)))
    ax.xaxis.set_major_formatter(FuncFormatter(time_tick_formatter(start_us, span_h)))
    ax.set_xlabel("time (UTC); a bar runs from raised to cleared, outlined if still active;\n"
                  "hatched: ended by a daemon stop (dotted line)")
    ax.set_title("Alarms")
    ax.grid(alpha=0.3, axis="x")
    return fig
