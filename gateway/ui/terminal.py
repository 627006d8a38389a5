"""The live terminal view for ``sowgate demo`` and ``sowgate run --tui``.

The view must fit the terminal it is shown in: rich's live display cuts off whatever is taller
than the screen, and what falls off the bottom (the channels, the seed quality) is exactly what
a fitter watches. So :func:`render` returns a renderable that, each time it is drawn, takes the
most detailed of a few layouts that fits the console's height, summarising the long tables
(one line per device, per seed row) into single lines before anything is left out.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Iterable, Mapping, Sequence
from typing import Any

from rich.console import Console, ConsoleOptions, Group, RenderableType, RenderResult
from rich.markup import escape
from rich.panel import Panel
from rich.table import Table

from gateway.state import (
    ActiveAlarmState,
    ChannelStatus,
    MachineState,
    PwmChannelState,
    RecorderState,
)

MISSING = "–"  # shown for a value not known or not measured yet
MAX_ALARM_LINES = 3  # in the compact layouts; the rest are counted ("+2 more")
_ALARM_COLOURS = {"critical": "red", "warning": "yellow"}  # the rest (info) white


def _fmt(value: Any, spec: str = "", unit: str = "") -> str:
    """A value as markup-safe text, :data:`MISSING` when there is none."""
    if value is None:
        return MISSING
    if isinstance(value, float) and spec:
        return f"{value:{spec}}{unit}"
    return escape(f"{value}{unit}")


def render(state: MachineState, truth: dict[str, Any] | None = None) -> FittedView:
    """One screen: machine state, rates, devices and alarms (and simulator truth if given),
    in the most detailed layout that fits the console it is printed on."""
    return FittedView(state, truth)


class FittedView:
    """The view at the first detail level, from full to most compact, that fits the height.

    Level 0: devices, alarms, per-row seed quality and channels as tables. Level 1: devices
    and alarms as one line each. Level 2: the seed quality summarised over all rows in one
    line. Level 3: the channels in one line and one alarm line. Every label stays at every level.
    """

    LEVELS = 4

    def __init__(self, state: MachineState, truth: dict[str, Any] | None = None) -> None:
        self.state = state
        self.truth = truth

    def at_level(self, level: int) -> Panel:
        return _panel(self.state, self.truth, level)

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        limit = options.height or options.size.height
        panel = self.at_level(0)
        for level in range(self.LEVELS):
            panel = self.at_level(level)
            lines = console.render_lines(panel, options.update(height=None), pad=False)
            if len(lines) <= limit:
                break
        yield panel


def _panel(state: MachineState, truth: dict[str, Any] | None, level: int) -> Panel:
    main = _main_grid(state, truth)
    lines = Table.grid(padding=(0, 2))  # label + text lines of the compact layouts
    lines.add_column(style="bold cyan", justify="right", min_width=15)
    lines.add_column()
    parts: list[RenderableType] = [main]
    devices = state.devices
    alarms = state.alarms
    if level == 0:
        parts += [_devices_table(devices), _alarms_table(alarms)]
    else:
        lines.add_row("devices", _devices_line(devices) or "none")
        shown = 1 if level >= 3 else MAX_ALARM_LINES
        lines.add_row("alarms", "\n".join(_alarm_lines(alarms, shown)) or "none")
        parts.append(lines)
    seeds = state.seeds
    if seeds is not None:
        if level <= 1:
            parts.append(_seed_table(seeds))
        else:
            lines.add_row("seeds", _seed_line(seeds))
    metering, pwm = state.metering, state.pwm_channel
    if metering is not None or pwm is not None:
        channels = metering.channels if metering is not None else {}
        if level <= 2:
            parts.append(_metering_table(channels, pwm))
        else:
            lines.add_row("channels", _metering_line(channels, pwm))
    return Panel(Group(*parts), title=f"sowgate · {escape(state.machine_id)}")


def _main_grid(state: MachineState, truth: dict[str, Any] | None) -> Table:
    main = Table.grid(padding=(0, 2))
    main.add_column(style="bold cyan", justify="right", min_width=15)
    main.add_column()
    main.add_column(style="bold cyan", justify="right")
    main.add_column()
    work_state = escape(state.work_state.upper())
    main.add_row(
        "state",
        f"[bold]{work_state}[/] ({_fmt(state.mode)})",
        "crop",
        f"{_fmt(state.crop)} @ {state.target_rate_kg_ha:g} kg/ha",
    )
    source = state.speed_source
    main.add_row(
        "speed",
        # "[radar]" would be read as a markup tag and vanish: escaped
        _fmt(state.speed_kmh, ".2f", " km/h")
        + ("" if source is None else escape(f" [{source}]")),
        "commanded",
        _fmt(state.commanded_rate_kg_ha, ".2f", " kg/ha"),
    )
    main.add_row(
        "tilt",
        _fmt(state.tilt_deg, "+.2f", "°") + (" raised" if state.raised else " lowered"),
        "motor / fan",
        f"{state.motor_duty_pct:.1f} % / {state.fan_duty_pct:.1f} %",
    )
    main.add_row("GNSS", _fmt(state.gnss_fix), "speed source", _fmt(source))
    main.add_row(
        "area", f"{state.area_ha:.4f} ha", "seed", f"{state.seed_mass_kg:.3f} kg"
    )
    hopper = state.hopper
    if hopper is not None:
        se = hopper.correction_standard_error
        tte = hopper.time_to_empty_min
        main.add_row(
            "hopper",
            _fmt(hopper.mass_kg, ".1f", " kg") + ("" if tte is None else f", {tte:.0f} min left"),
            "correction",
            f"x{hopper.discharge_correction:.4f}"
            + ("" if se is None else f" (SE {se * 100:.2f} %)")
            + ("" if hopper.correction_applied else " not applied yet"),
        )
    if truth:
        sown = truth.get("sown_m")
        applied = truth.get("applied_kg_ha")
        main.add_row(
            "actually applied",
            _fmt(applied, ".2f", " kg/ha")
            + ("" if sown is None or applied is None else f" over {sown:.1f} m"),
            "rate error",
            _fmt(truth.get("rate_error_pct"), "+.2f", " %"),
        )
        if "settled_rate_error_pct" in truth:
            # the whole-run figure is dominated by start-up from standstill in a short run
            main.add_row(
                "after start-up",
                _fmt(truth.get("settled_kg_ha"), ".2f", " kg/ha"),
                "rate error",
                _fmt(truth.get("settled_rate_error_pct"), "+.2f", " %"),
            )
    return main


def _devices_table(devices: Mapping[str, bool]) -> Table:
    t = Table(title="devices", show_header=False, box=None)
    for name, ok in devices.items():
        t.add_row(escape(name), "[green]ok[/]" if ok else "[red]lost[/]")
    return t


def _devices_line(devices: Mapping[str, bool]) -> str:
    return " · ".join(
        f"{escape(name)} " + ("[green]ok[/]" if ok else "[red]lost[/]")
        for name, ok in devices.items()
    )


def _alarm_markup(alarm: ActiveAlarmState) -> str:
    return _coloured(alarm.message, _ALARM_COLOURS.get(alarm.severity, "white"))


def _coloured(text: str, colour: str) -> str:
    return f"[{colour}]{escape(text)}[/]"


def _alarms_table(alarms: Sequence[ActiveAlarmState]) -> Table:
    t = Table(title="alarms", show_header=False, box=None)
    for a in alarms:
        t.add_row(_alarm_markup(a))
    if not alarms:
        t.add_row(_coloured("none", "white"))
    return t


def _alarm_lines(alarms: Sequence[ActiveAlarmState], shown: int) -> list[str]:
    """At most ``shown`` lines; what does not fit is counted on the last one."""
    if len(alarms) <= shown:
        return [_alarm_markup(a) for a in alarms]
    return [_alarm_markup(a) for a in alarms[: shown - 1]] + [
        _alarm_markup(alarms[shown - 1]) + f" (+{len(alarms) - shown} more)"
    ]


def _figure(value: float | None, spec: str = ".1f") -> str:
    return MISSING if value is None else f"{value:{spec}}"


def _seed_table(seeds: RecorderState) -> Table:
    """Per-row spacing quality (ISO 7256-1 indices) of the seeds recorded so far."""
    t = Table(
        title=f"seeds recorded: {seeds.records_stored} ({escape(seeds.method)})",
        box=None,
    )
    for col in ("row", "seeds", "mean spacing", "multiples %", "misses %", "feed %", "CV %"):
        t.add_column(col, justify="right")
    for row, info in sorted(seeds.rows.items()):
        q = info.quality
        t.add_row(
            str(row), str(info.seeds), _figure(q.mean_spacing_m, ".3f") + " m",
            _figure(q.multiples_index), _figure(q.miss_index), _figure(q.quality_of_feed_index),
            _figure(q.precision),
        )
    return t


def _span(values: Iterable[Any], spec: str) -> str:
    """``lo–hi`` over the rows that have the figure (one value if all agree)."""
    known = [float(v) for v in values if v is not None]
    if not known:
        return MISSING
    lo, hi = min(known), max(known)
    return f"{lo:{spec}}" if f"{lo:{spec}}" == f"{hi:{spec}}" else f"{lo:{spec}}–{hi:{spec}}"


def _seed_line(seeds: RecorderState) -> str:
    """The seed table in one line: the range of each index over the rows."""
    rows = seeds.rows
    qualities = [info.quality for info in rows.values()]
    spacing = _span((q.mean_spacing_m for q in qualities), ".3f")
    misses = _span((q.miss_index for q in qualities), ".1f")
    multiples = _span((q.multiples_index for q in qualities), ".1f")
    cv = _span((q.precision for q in qualities), ".1f")
    return (
        f"{seeds.records_stored} recorded ({escape(seeds.method)}) "
        f"over {len(rows)} rows · spacing {spacing} m"
        f" · misses {misses} % · multiples {multiples} %"
        f" · CV {cv} %"
    )


def _metering_table(
    channels: Mapping[str, ChannelStatus], pwm: PwmChannelState | None = None
) -> Table:
    """Every ``[[channel]]`` in one table, the ``can_pid`` ones and paper A's ``pwm_modbus``
    motor alike, so a fitter checks all of them in one place.

    A CAN channel is commanded a shaft speed and reports the one it measures; paper A's motor
    is commanded a PWM duty (with the rate the crop model says it gives) and has no feedback.
    """
    t = Table(title="metering channels", box=None)
    for col in ("channel", "product", "target kg/ha", "command", "feedback", "alarms"):
        t.add_column(col, justify="right")
    for name, ch in channels.items():
        t.add_row(
            escape(name), _fmt(ch.product or "-"), f"{ch.target_rate_kg_ha:g}",
            f"{ch.target_rpm:.1f} r/min",
            _fmt(ch.measured_rpm, ".1f", " r/min"),
            escape(", ".join(ch.alarms) or "-"),
        )
    if pwm is not None:
        duty, commanded = pwm.duty_pct, pwm.commanded_rate_kg_ha
        command = _fmt(duty, ".1f", " %")
        if duty is not None and commanded is not None:
            command += f" ({commanded:.2f} kg/ha)"
        t.add_row(
            _fmt(pwm.name), _fmt(pwm.product or "-"),
            _fmt(pwm.target_rate_kg_ha, "g"), command, "open loop",
            escape(", ".join(pwm.alarms) or "-"),
        )
    return t


def _metering_line(
    channels: Mapping[str, ChannelStatus], pwm: PwmChannelState | None
) -> str:
    """The channel table in one line: command → feedback per channel, and any alarms."""
    parts = []
    for name, ch in channels.items():
        alarms = ", ".join(ch.alarms)
        parts.append(
            f"{escape(name)} {ch.target_rpm:.1f}→"
            f"{_fmt(ch.measured_rpm, '.1f')} r/min"
            + (f" [yellow]{escape(alarms)}[/]" if alarms else "")
        )
    if pwm is not None:
        alarms = ", ".join(pwm.alarms)
        parts.append(
            f"{_fmt(pwm.name)} {_fmt(pwm.duty_pct, '.1f', ' %')}"
            + (f" [yellow]{escape(alarms)}[/]" if alarms else "")
        )
    return " · ".join(parts) or "none"


Renderer = Callable[[], FittedView]


async def run_with_live_view(
    state: Callable[[], MachineState],
    work: Awaitable[Any],
    truth: Callable[[], dict[str, Any]] | None = None,
) -> None:
    """Run ``work`` (the daemon) under a live view redrawn from ``state`` four times a second;
    ``truth`` adds the simulator's ground truth in the demo."""
    from rich.live import Live

    task = asyncio.ensure_future(work)
    with Live(render(state()), refresh_per_second=4, screen=False) as live:
        while not task.done():
            live.update(render(state(), truth() if truth else None))
            await asyncio.wait({task}, timeout=0.25)
    await task
