"""The live view renders every part of the machine state without crashing, missing values too."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

from rich.console import Console

from gateway.core.records import AlarmSeverity
from gateway.metering.channels import AlarmKind
from gateway.state import (
    ActiveAlarmState,
    ChannelStatus,
    HopperState,
    MachineState,
    MeteringStatus,
    PwmChannelState,
    RecorderState,
    RowState,
    SpacingQuality,
)
from gateway.ui.terminal import render

SINCE = datetime(2026, 4, 1, 8, 0, tzinfo=UTC)


def _alarm(code: str, severity: AlarmSeverity, message: str) -> ActiveAlarmState:
    return ActiveAlarmState(code, severity, message, SINCE)


def _seeds(records_stored: int, rows: dict[int, RowState]) -> RecorderState:
    return RecorderState(
        method="interpolated", records_stored=records_stored, pending=0, buffered=0, queued=0,
        unpositioned=0, extrapolated=0, bad_edges=0, store_errors=0, records_lost=0,
        implausible_edges=0, last_error=None, rows=rows,
    )


def _row(seeds: int, **quality: float) -> RowState:
    indices: dict[str, float | None] = dict.fromkeys(
        ("multiples_index", "miss_index", "quality_of_feed_index", "precision",
         "mean_spacing_m")
    )
    indices.update(quality)
    return RowState(seeds=seeds, last_spacing_m=None, implausible_edges=0,
                    quality=SpacingQuality(n=seeds, x_ref_m=None, **indices))


def _can_channel(product: str, rate: float, target_rpm: float, measured_rpm: float | None,
                 *alarms: AlarmKind) -> ChannelStatus:
    return ChannelStatus(
        product=product, node_id=1, target_rate_kg_ha=rate, target_rpm=target_rpm,
        measured_rpm=measured_rpm, applied_rate_kg_ha=None, fault=None, alarms=alarms,
    )


STATE = MachineState(
    machine_id="m1",
    utc=SINCE,
    work_state="seeding",
    mode="working",
    speed_kmh=None,
    speed_source=None,
    tilt_deg=None,
    raised=True,
    crop="wheat",
    target_rate_kg_ha=225.0,
    commanded_rate_kg_ha=0.0,
    motor_duty_pct=0.0,
    fan_duty_pct=0.0,
    devices={"radar": False},
    alarms=(_alarm("speed.lost", "critical", "no valid ground speed"),),
    area_ha=0.0,
    seed_mass_kg=0.0,
    gnss_fix="rtk_float",
    seeds=_seeds(3, {1: _row(3, mean_spacing_m=0.2, miss_index=0.0)}),
)


def test_view_shows_state_alarms_devices_and_seed_quality() -> None:
    console = Console(width=100, record=True)
    console.print(render(STATE, {"applied_kg_ha": None, "rate_error_pct": None}))
    text = console.export_text()
    for expected in ("SEEDING", "no valid ground speed", "lost", "rtk_float", "0.200 m", "–"):
        assert expected in text


def _line(text: str, first_cell: str) -> str:
    """The one line of the rendered text whose first cell is ``first_cell``."""
    rows = [line for line in text.splitlines() if line.strip("│ ").split()[:1] == [first_cell]]
    assert len(rows) == 1, text
    return rows[0]


def test_channels_table_shows_the_can_channels_and_paper_a_pwm_channel_together() -> None:
    state = replace(
        STATE,
        metering=MeteringStatus(working=True, speed_kmh=None, channels={
            "deep": _can_channel("fertiliser", 300.0, 42.5, 41.8, "off_target"),
        }),
        pwm_channel=PwmChannelState(
            name="seed", product="wheat", prescription=False, target_rate_kg_ha=225.0,
            commanded_rate_kg_ha=219.4, duty_pct=47.3, alarms=("rate.too_fast",),
        ),
    )
    console = Console(width=120, record=True)
    console.print(render(state))
    text = console.export_text()
    deep = _line(text, "deep")
    for expected in ("fertiliser", "300", "42.5 r/min", "41.8 r/min", "off_target"):
        assert expected in deep
    seed = _line(text, "seed")
    for expected in ("wheat", "225", "47.3 %", "219.40 kg/ha", "open loop", "rate.too_fast"):
        assert expected in seed


def test_a_daemon_with_only_a_pwm_channel_shows_it_with_duty_and_its_own_alarms(
    tmp_path: Path,
) -> None:
    """Through the daemon's real state: no CAN channels, paper A's motor still listed."""
    from gateway.app.daemon import Daemon
    from gateway.config import parse_config
    from gateway.control.controller import ControlOutputs
    from gateway.control.work_state import WorkState

    settings = parse_config({
        "hmi": {"enabled": False},
        "channel": [{"name": "seed", "drive": "pwm_modbus", "product": "wheat",
                     "target_rate_kg_ha": 200.0}],
    })
    daemon = Daemon(settings, tmp_path / "state")
    daemon.alarms.raise_("rate.outside_calibration", "below the calibrated range")
    daemon.alarms.raise_("gnss.lost", "no GNSS")  # not about the motor: not on its row
    outputs = ControlOutputs(
        state=WorkState.PRE_SEED, motor_pct=38.6, fan_pct=0.0, speed_kmh=None,
        speed_source=None, tilt_deg=None, raised=False, commanded_rate_kg_ha=195.25,
        target_rate_kg_ha=200.0,
    )
    for hook in daemon.tick_hooks:  # what the control loop does after a tick
        hook(outputs)
    console = Console(width=120, record=True)
    console.print(render(daemon.state()))
    seed = _line(console.export_text(), "seed")
    for expected in ("wheat", "200", "38.6 %", "195.25 kg/ha", "rate.outside_calibration"):
        assert expected in seed
    assert "gnss" not in seed


# ---------------------------------------------------------------- fitting the terminal

DEMO_STATE = replace(  # what `sowgate demo --channels` shows after ~10 s (trimmed, real figures)
    STATE,
    work_state="seeding",
    speed_kmh=3.02,
    speed_source="radar",
    tilt_deg=-6.14,
    raised=False,
    crop="rapeseed",
    target_rate_kg_ha=6.0,
    commanded_rate_kg_ha=6.0,
    motor_duty_pct=32.8,
    fan_duty_pct=70.0,
    devices={"pwm": True, "radar": True, "inclinometer": True, "gnss": True, "hmi": True,
             "seed_sensors": False},
    alarms=(
        _alarm("seed_sensors.unavailable", "warning", "seed sensors [ttyUSB2] not answering"),
        _alarm("gnss.not_rtk_fixed", "warning", "GNSS fix rtk_float"),
    ),
    area_ha=0.0013,
    seed_mass_kg=0.008,
    gnss_fix="rtk_fixed",
    seeds=_seeds(171, {
        row: _row(28, mean_spacing_m=0.19 + row / 1000, multiples_index=3.4,
                  miss_index=row * 1.0, quality_of_feed_index=96.6, precision=11.5)
        for row in range(1, 7)
    }),
    metering=MeteringStatus(working=True, speed_kmh=3.02, channels={
        name: _can_channel("fertiliser", 150.0, 8.88, 8.89)
        for name in ("shallow", "deep", "seed")
    }),
)
DEMO_TRUTH = {"sown_m": 6.25, "applied_kg_ha": 5.70, "rate_error_pct": -4.92,
              "settled_m": 2.65, "settled_kg_ha": 6.11, "settled_rate_error_pct": 1.78}
ROW_LABELS = ("state", "crop", "speed", "commanded", "tilt", "motor / fan", "GNSS",
              "speed source", "area", "seed", "actually applied", "rate error", "after start-up",
              "devices", "alarms", "seeds", "channels")


def _screen(width: int, height: int, state: MachineState,
            truth: dict[str, object] | None = None) -> list[str]:
    console = Console(width=width, height=height, record=True)
    console.print(render(state, truth))
    return console.export_text().splitlines()


def test_the_demo_screen_fits_80_by_24_with_every_label_and_nothing_cut() -> None:
    lines = _screen(80, 24, DEMO_STATE, DEMO_TRUTH)
    text = "\n".join(lines)
    assert len(lines) <= 24, text
    assert lines[0].startswith("╭") and lines[-1].startswith("╰"), text  # the whole panel
    assert "…" not in text and "..." not in text, text  # no cell cut short either
    for label in ROW_LABELS:
        assert label in text, f"{label!r} missing:\n{text}"
    # the detail is summarised, not dropped: every channel, the lost device, both alarms
    for expected in ("shallow", "deep", "seed_sensors lost", "rtk_float", "171 recorded"):
        assert expected in text, text
    assert "misses 1.0–6.0 %" in text, text  # the seed rows' range over the six rows


def test_a_tall_terminal_keeps_the_full_tables() -> None:
    text = "\n".join(_screen(120, 60, DEMO_STATE, DEMO_TRUTH))
    assert "metering channels" in text and "mean spacing" in text
    assert "seed_sensors" in text and "lost" in text


def test_the_speed_source_in_brackets_is_shown_not_taken_as_markup() -> None:
    text = "\n".join(_screen(100, 40, DEMO_STATE))
    assert "3.02 km/h [radar]" in text
    assert "seed sensors [ttyUSB2] not answering" in text  # alarm text is not markup either


def test_rate_error_is_a_dash_until_something_has_been_sown() -> None:
    """The first seconds used to read "rate error -100.00 %" over "0.0 m" sown."""
    from simulator.demo import truth_report
    from simulator.machine import Truth

    truth = Truth()
    truth.record(0.0, 0.004, 0.1, sowing=True, width_m=2.0)  # the first step off standstill
    text = "\n".join(_screen(100, 40, DEMO_STATE, truth_report(truth, 6.0)))
    applied = _line(text, "actually")
    assert "-100" not in applied and applied.count("–") == 2, applied


def test_the_hopper_scale_row_shows_mass_and_the_correction_with_its_confidence() -> None:
    hopper = HopperState(mass_kg=412.3, time_to_empty_min=131.5, discharge_correction=1.0791,
                         correction_estimate=1.08, correction_standard_error=0.0061,
                         correction_applied=True, scale_sigma_kg=2.0, windows=5, refills=1)
    console = Console(width=100, record=True)
    console.print(render(replace(STATE, hopper=hopper)))
    text = console.export_text()
    assert "412.3 kg, 132 min left" in text
    assert "x1.0791 (SE 0.61 %)" in text
    console = Console(width=100, record=True)
    console.print(render(STATE))
    assert "hopper" not in console.export_text()
