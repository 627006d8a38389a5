"""The dashboard's alarm history ends an alarm that was still active when the box went
offline (sowgate stopped) there, instead of listing it as active across the stop and
clearing it only at the next start."""

from __future__ import annotations

from gateway.dashboard.model import Fleet
from tests.gateway.dashboard.test_model import alarm, state

BASE = "sowgate/seeder-01"


def test_an_alarm_active_at_a_stop_ends_at_the_last_state_before_it() -> None:
    fleet = Fleet()
    fleet.handle(f"{BASE}/status", b"online")
    fleet.handle(f"{BASE}/alarms", alarm(1, "pwm.unavailable", True, "critical"))
    fleet.handle(f"{BASE}/state", state(utc="2026-04-20T08:05:00Z", alarms=[{
        "code": "pwm.unavailable", "severity": "critical", "message": "no answer",
        "since": "2026-04-20T08:00:00Z"}]))
    fleet.handle(f"{BASE}/status", b"offline")  # sowgate stopped (or its last will)
    (entry,) = fleet.machines["seeder-01"].alarm_list()
    assert (entry["active"], entry["ended"]) == (False, "offline")
    assert entry["cleared"].startswith("2026-04-20T08:05:00")
    # the next run starts clean: its first state does not move the end to its start
    fleet.handle(f"{BASE}/status", b"online")
    fleet.handle(f"{BASE}/state", state(utc="2026-04-20T09:30:00Z"))
    (entry,) = fleet.machines["seeder-01"].alarm_list()
    assert entry["cleared"].startswith("2026-04-20T08:05:00") and not entry["active"]


def test_a_dashboard_started_after_the_stop_does_not_show_the_old_alarm_active() -> None:
    """Retained messages come in any order: an old state listing the alarm after the
    retained "offline" does not make it active again."""
    fleet = Fleet()
    fleet.handle(f"{BASE}/status", b"offline")
    fleet.handle(f"{BASE}/state", state(utc="2026-04-20T08:05:00Z", alarms=[{
        "code": "pwm.unavailable", "severity": "critical", "message": "no answer",
        "since": "2026-04-20T08:00:00Z"}]))
    (entry,) = fleet.machines["seeder-01"].alarm_list()
    assert (entry["active"], entry["ended"]) == (False, "offline")


def test_a_box_back_online_with_the_alarm_still_active_lists_it_again() -> None:
    """Only the link broke: the box's next state still lists the alarm."""
    fleet = Fleet()
    fleet.handle(f"{BASE}/alarms", alarm(1, "radar.unavailable", True))
    fleet.handle(f"{BASE}/status", b"offline")
    fleet.handle(f"{BASE}/status", b"online")
    fleet.handle(f"{BASE}/state", state(utc="2026-04-20T08:10:00Z", alarms=[{
        "code": "radar.unavailable", "severity": "warning", "message": "no answer",
        "since": "2026-04-20T08:00:00Z"}]))
    (entry,) = fleet.machines["seeder-01"].alarm_list()
    assert entry["active"] and entry["ended"] is None
