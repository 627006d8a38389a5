"""The live view renders every part of a snapshot without crashing, including missing values."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from gateway.view import render

SNAPSHOT = {
    "machine_id": "m1",
    "work_state": "seeding",
    "mode": "working",
    "speed_kmh": None,
    "speed_source": None,
    "tilt_deg": None,
    "raised": True,
    "crop": "wheat",
    "target_rate_kg_ha": 225.0,
    "commanded_rate_kg_ha": 0.0,
    "motor_duty_pct": 0.0,
    "fan_duty_pct": 0.0,
    "devices": {"radar": False},
    "alarms": [{"code": "speed.lost", "severity": "critical", "message": "no valid ground speed"}],
    "area_ha": 0.0,
    "seed_mass_kg": 0.0,
    "gnss_fix": "rtk_float",
    "seeds": {
        "records_stored": 3,
        "method": "interpolated",
        "rows": {1: {"seeds": 3, "quality": {"mean_spacing_m": 0.2, "miss_index": 0.0}}},
    },
}


def test_view_shows_state_alarms_devices_and_seed_quality() -> None:
    console = Console(width=100, record=True)
    console.print(render(SNAPSHOT, {"applied_kg_ha": None, "rate_error_pct": None}))
    text = console.export_text()
    for expected in ("SEEDING", "no valid ground speed", "lost", "rtk_float", "0.200 m", "--"):
        assert expected in text


def _row(text: str, first_cell: str) -> str:
    """The one line of the rendered text whose first cell is ``first_cell``."""
    rows = [line for line in text.splitlines() if line.strip("│ ").split()[:1] == [first_cell]]
    assert len(rows) == 1, text
    return rows[0]


def test_channels_table_shows_the_can_channels_and_paper_a_pwm_channel_together() -> None:
    snapshot = {
        **SNAPSHOT,
        "metering": {"channels": {"deep": {
            "product": "fertiliser", "target_rate_kg_ha": 300.0, "target_rpm": 42.5,
            "measured_rpm": 41.8, "alarms": ["off_target"],
        }}},
        "pwm_channel": {
            "name": "seed", "product": "wheat", "prescription": False,
            "target_rate_kg_ha": 225.0, "commanded_rate_kg_ha": 219.4, "duty_pct": 47.3,
            "alarms": ["rate.too_fast"],
        },
    }
    console = Console(width=120, record=True)
    console.print(render(snapshot))
    text = console.export_text()
    deep = _row(text, "deep")
    for expected in ("fertiliser", "300", "42.5 r/min", "41.8 r/min", "off_target"):
        assert expected in deep
    seed = _row(text, "seed")
    for expected in ("wheat", "225", "47.3 %", "219.40 kg/ha", "open loop", "rate.too_fast"):
        assert expected in seed


def test_a_daemon_with_only_a_pwm_channel_shows_it_with_duty_and_its_own_alarms(
    tmp_path: Path,
) -> None:
    """Through the daemon's real snapshot: no CAN channels, paper A's motor still listed."""
    from gateway.config import parse_config
    from gateway.controller import ControlOutputs
    from gateway.daemon import Daemon
    from gateway.work_state import WorkState

    settings = parse_config({
        "hmi": {"enabled": False},
        "channel": [{"name": "seed", "drive": "pwm_modbus", "product": "wheat",
                     "target_rate_kg_ha": 200.0}],
    })
    daemon = Daemon(settings, tmp_path / "state")
    daemon.alarms.raise_("rate.outside_calibration", "below the calibrated range")
    daemon.alarms.raise_("gnss.lost", "no GNSS")  # not about the motor: not on its row
    daemon.components["pwm_channel"].on_tick(ControlOutputs(
        state=WorkState.PRE_SEED, motor_pct=38.6, fan_pct=0.0, speed_kmh=None,
        speed_source=None, tilt_deg=None, raised=False, commanded_rate_kg_ha=195.25,
        target_rate_kg_ha=200.0,
    ))
    console = Console(width=120, record=True)
    console.print(render(daemon.snapshot()))
    seed = _row(console.export_text(), "seed")
    for expected in ("wheat", "200", "38.6 %", "195.25 kg/ha", "rate.outside_calibration"):
        assert expected in seed
    assert "gnss" not in seed
