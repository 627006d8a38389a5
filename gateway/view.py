"""The live terminal view for ``sowgate demo`` and ``sowgate run --tui``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rich.console import Group
from rich.panel import Panel
from rich.table import Table


def _fmt(value: Any, spec: str = "", unit: str = "") -> str:
    if value is None:
        return "--"
    if isinstance(value, float) and spec:
        return f"{value:{spec}}{unit}"
    return f"{value}{unit}"


def render(snapshot: dict[str, Any], truth: dict[str, Any] | None = None) -> Group:
    """One screen: machine state, rates, devices and alarms (and simulator truth if given)."""
    main = Table.grid(padding=(0, 2))
    main.add_column(style="bold cyan", justify="right")
    main.add_column()
    main.add_column(style="bold cyan", justify="right")
    main.add_column()
    state = snapshot["work_state"].upper()
    main.add_row(
        "state",
        f"[bold]{state}[/] ({snapshot['mode']})",
        "crop",
        f"{snapshot['crop']} @ {snapshot['target_rate_kg_ha']:g} kg/ha",
    )
    main.add_row(
        "speed",
        _fmt(snapshot["speed_kmh"], ".2f", " km/h") + f" [{snapshot['speed_source']}]",
        "commanded",
        _fmt(snapshot["commanded_rate_kg_ha"], ".2f", " kg/ha"),
    )
    main.add_row(
        "tilt",
        _fmt(snapshot["tilt_deg"], "+.2f", "°") + (" raised" if snapshot["raised"] else " lowered"),
        "motor / fan",
        f"{snapshot['motor_duty_pct']:.1f} % / {snapshot['fan_duty_pct']:.1f} %",
    )
    main.add_row(
        "GNSS",
        str(snapshot.get("gnss_fix", "none")),
        "speed source",
        str(snapshot["speed_source"]),
    )
    main.add_row(
        "area",
        f"{snapshot['area_ha']:.4f} ha",
        "seed",
        f"{snapshot['seed_mass_kg']:.3f} kg",
    )
    if truth:
        sown = truth.get("sown_m")
        main.add_row(
            "applied (truth)",
            _fmt(truth.get("applied_kg_ha"), ".2f", " kg/ha")
            + ("" if sown is None else f" over {sown:.1f} m"),
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
    devices = Table(title="devices", show_header=False, box=None)
    for name, ok in snapshot["devices"].items():
        devices.add_row(name, "[green]ok[/]" if ok else "[red]lost[/]")
    alarms = Table(title="alarms", show_header=False, box=None)
    for a in snapshot["alarms"] or [{"severity": "", "message": "none"}]:
        colour = {"critical": "red", "warning": "yellow"}.get(a["severity"], "white")
        alarms.add_row(f"[{colour}]{a['message']}[/]")
    parts: list[Any] = [main, devices, alarms]
    seeds = snapshot.get("seeds")
    if isinstance(seeds, dict) and isinstance(seeds.get("rows"), dict):
        parts.append(_seed_table(seeds))
    metering = snapshot.get("metering")
    can_channels = metering.get("channels") if isinstance(metering, dict) else None
    pwm = snapshot.get("pwm_channel")
    if isinstance(can_channels, dict) or isinstance(pwm, dict):
        parts.append(
            _metering_table(
                can_channels if isinstance(can_channels, dict) else {},
                pwm if isinstance(pwm, dict) else None,
            )
        )
    return Group(Panel(Group(*parts), title=f"sowgate · {snapshot['machine_id']}"))


def _seed_table(seeds: dict[str, Any]) -> Table:
    """Per-row spacing quality (ISO 7256-1 indices) of the seeds recorded so far."""
    t = Table(
        title=f"seeds recorded: {seeds.get('records_stored', 0)} ({seeds.get('method')})",
        box=None,
    )
    for col in ("row", "seeds", "mean spacing", "multiples %", "misses %", "feed %", "CV %"):
        t.add_column(col, justify="right")
    for row, info in sorted(seeds["rows"].items(), key=lambda kv: int(kv[0])):
        q = info.get("quality") or {}

        def f(key: str, spec: str = ".1f", q: dict[str, Any] = q) -> str:
            v = q.get(key)
            return "--" if v is None else f"{v:{spec}}"

        t.add_row(
            str(row), str(info.get("seeds", 0)), f("mean_spacing_m", ".3f") + " m",
            f("multiples_index"), f("miss_index"), f("quality_of_feed_index"), f("precision"),
        )
    return t


def _metering_table(channels: dict[str, Any], pwm: dict[str, Any] | None = None) -> Table:
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
            name, str(ch.get("product") or "-"), f"{ch.get('target_rate_kg_ha', 0):g}",
            f"{ch.get('target_rpm', 0):.1f} r/min",
            _fmt(ch.get("measured_rpm"), ".1f", " r/min"),
            ", ".join(ch.get("alarms") or []) or "-",
        )
    if pwm is not None:
        duty, commanded = pwm.get("duty_pct"), pwm.get("commanded_rate_kg_ha")
        command = _fmt(duty, ".1f", " %")
        if duty is not None and commanded is not None:
            command += f" ({commanded:.2f} kg/ha)"
        t.add_row(
            str(pwm.get("name")), str(pwm.get("product") or "-"),
            _fmt(pwm.get("target_rate_kg_ha"), "g"), command, "open loop",
            ", ".join(pwm.get("alarms") or []) or "-",
        )
    return t


Renderer = Callable[[], Group]
