"""Speed and work-state sources: priority lists with fallback, and ISOBUS's 300 ms staleness
honoured all the way into the controller (not only inside the ISOBUS listener)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import can
import pytest

from drivers.can_bus import IsobusListener
from gateway.app.wiring import isobus_pump_step
from gateway.config import ConfigError, parse_config
from gateway.control.controller import Controller
from gateway.core import commands as cmd
from gateway.core.alarms import AlarmBoard
from gateway.metering.isobus import TractorInputs
from protocol import isobus as ib

LOWERED_RAW = -6.25
RAISED_RAW = 8.75


def make(**sections: Any) -> Controller:
    settings = parse_config({"control": {"crop": "wheat", "rate_kg_ha": 225.0}, **sections})
    c = Controller(settings, AlarmBoard("m1"))
    c.execute(cmd.Start(), "test")
    return c


# ---- config ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("given", "order"),
    [
        ("radar", ["radar"]),
        ("radar_then_gnss", ["radar", "gnss"]),
        ("isobus_then_radar", ["isobus", "radar"]),
        ("isobus_then_gnss_then_radar", ["isobus", "gnss", "radar"]),
        (["gnss", "isobus"], ["gnss", "isobus"]),
    ],
)
def test_speed_source_is_a_priority_list(given: object, order: list[str]) -> None:
    # a chain naming gnss needs the receiver configured ([gnss] table)
    assert parse_config({"speed": {"source": given}, "gnss": {}}).speed.source == order


@pytest.mark.parametrize(
    ("given", "order"),
    [
        ("inclinometer", ["inclinometer"]),
        ("hitch_then_inclinometer", ["hitch", "inclinometer"]),
        ("inclinometer_then_hitch", ["inclinometer", "hitch"]),
        (["hitch"], ["hitch"]),
    ],
)
def test_work_state_source_is_a_priority_list(given: object, order: list[str]) -> None:
    assert parse_config({"isobus": {"work_state_source": given}}).isobus.work_state_source == order


@pytest.mark.parametrize(
    ("section", "given", "problem"),
    [
        ("speed", "radar_then_sonar",
         "speed.source[1]: Input should be 'radar', 'gnss', 'isobus' or"),
        ("speed", ["gnss", "gnss"], "speed.source: each source may appear once"),
        ("speed", [], "speed.source: List should have at least 1 item"),
        ("isobus", "hitch_then_radar", "isobus.work_state_source[1]: Input should be"),
    ],
)
def test_bad_source_lists_name_the_key_and_the_allowed_values(
    section: str, given: object, problem: str
) -> None:
    key = "source" if section == "speed" else "work_state_source"
    with pytest.raises(ConfigError) as info:
        parse_config({section: {key: given}})
    assert any(p.startswith(problem) for p in info.value.problems), info.value.problems


def test_a_plain_environment_override_still_works(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SOWGATE_SPEED__SOURCE", "gnss_then_radar")
    monkeypatch.setenv("SOWGATE_GNSS__ENABLED", "true")
    monkeypatch.setenv("SOWGATE_ISOBUS__WORK_STATE_SOURCE", "hitch")
    s = parse_config({})
    assert s.speed.source == ["gnss", "radar"] and s.isobus.work_state_source == ["hitch"]


# ---- speed ----------------------------------------------------------------------------------


def test_isobus_then_gnss_then_radar_falls_back_in_order() -> None:
    c = make(speed={"source": "isobus_then_gnss_then_radar"}, gnss={})
    for t in (0.0, 0.1, 0.2):
        c.on_speed("isobus", 6.0, t)
        c.on_speed("gnss", 5.5, t)
        c.on_speed("radar", 5.0, t)
    assert c.speed(0.25)[1] == "isobus"
    for t in (0.3, 0.4, 0.5, 0.6):  # the tractor goes quiet
        c.on_speed("gnss", 5.5, t)
        c.on_speed("radar", 5.0, t)
    assert c.speed(0.6) == (pytest.approx(5.5), "gnss")


def test_isobus_speed_is_stale_after_300_ms_in_the_controller() -> None:
    """[speed] stale_after_s (2 s) is for the radar; ISO 11783-7 speed lasts 300 ms."""
    c = make(speed={"source": "isobus_then_radar", "stale_after_s": 2.0})
    c.on_speed("isobus", 6.0, 0.0)
    c.on_speed("radar", 5.0, 0.0)
    assert c.speed(0.29)[1] == "isobus"
    assert c.speed(0.31)[1] == "radar"


# ---- work state ------------------------------------------------------------------------------


def test_hitch_only_never_falls_back_to_the_inclinometer_silently() -> None:
    c = make(isobus={"work_state_source": "hitch"})
    c.on_hitch(True, 0.0)
    c.on_tilt(RAISED_RAW, 0.0)  # ignored: not a configured source
    assert not c.tick(0.1).raised
    assert not c.alarms.is_active("inclinometer.lost")
    c.on_tilt(LOWERED_RAW, 0.5)
    out = c.tick(0.5)  # hitch older than 300 ms
    assert out.raised
    assert c.alarms.is_active("hitch.lost")
    alarm = next(a for a in c.alarms.active if a.code == "hitch.lost")
    assert alarm.severity == "critical" and "treated as raised" in alarm.message


def test_hitch_then_inclinometer_falls_back_after_300_ms_with_a_warning() -> None:
    c = make(isobus={"work_state_source": "hitch_then_inclinometer"})
    c.on_hitch(False, 0.0)  # out of work
    c.on_tilt(LOWERED_RAW, 0.0)
    assert c.tick(0.2).raised
    c.on_tilt(LOWERED_RAW, 0.4)
    assert not c.tick(0.4).raised  # the inclinometer says lowered
    alarm = next(a for a in c.alarms.active if a.code == "hitch.lost")
    assert alarm.severity == "warning" and "from inclinometer" in alarm.message
    c.on_hitch(True, 0.5)
    assert not c.tick(0.5).raised
    assert not c.alarms.is_active("hitch.lost")


def test_inclinometer_then_hitch_uses_the_hitch_when_the_inclinometer_is_lost() -> None:
    c = make(isobus={"work_state_source": "inclinometer_then_hitch"})
    c.on_tilt(RAISED_RAW, 0.0)
    c.on_hitch(True, 0.0)
    assert c.tick(0.1).raised  # inclinometer first
    c.on_hitch(True, 2.5)
    assert not c.tick(2.5).raised  # tilt older than 2 s: the hitch decides
    assert c.alarms.is_active("inclinometer.lost")


# ---- the daemon's ISOBUS pump ----------------------------------------------------------------


def _speed_frame(kmh: float) -> can.Message:
    data = ib.encode_speed(ib.PGN_MACHINE_SELECTED_SPEED, kmh / 3.6)
    cid = ib.build_can_id(ib.PGN_MACHINE_SELECTED_SPEED, 0xF0)
    return can.Message(arbitration_id=cid, data=data, is_extended_id=True)


def _hitch_frame(in_work: ib.InWork) -> can.Message:
    cid = ib.build_can_id(ib.PGN_REAR_HITCH, 0xF0)
    return can.Message(arbitration_id=cid, data=ib.encode_hitch(20.0, in_work), is_extended_id=True)


def test_pump_stamps_values_with_their_frame_time_so_they_expire_300_ms_after_it() -> None:
    """The pump runs every 50 ms; a frame it passes on must still expire 300 ms after it
    arrived, not 300 ms (or 2 s) after the pump last ran."""
    now = [0.0]
    c = make(
        speed={"source": "isobus_then_radar"},
        isobus={"work_state_source": "hitch_then_inclinometer"},
    )
    daemon = SimpleNamespace(clock=lambda: now[0], controller=c)
    listener = IsobusListener(clock=lambda: now[0])
    tractor = TractorInputs(listener)
    fed: dict[str, float] = {}
    listener.feed(_speed_frame(7.2))
    listener.feed(_hitch_frame(ib.InWork.IN_WORK))
    for step in range(6):  # pump at 0, 50, ..., 250 ms; no new frames after t = 0
        now[0] = step * 0.05
        isobus_pump_step(daemon, tractor, fed)  # type: ignore[arg-type]
    assert c.speed(0.25) == (pytest.approx(7.2), "isobus")
    assert len(c.sources["isobus"].filter) == 1  # fed once, not once per pump
    c.on_tilt(RAISED_RAW, 0.31)
    assert c.speed(0.31) == (None, None)
    assert c.tick(0.31).raised  # hitch expired too: the inclinometer (raised) decides
