"""The live view renders every part of a snapshot without crashing, including missing values."""

from __future__ import annotations

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
