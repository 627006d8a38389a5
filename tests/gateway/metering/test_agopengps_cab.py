"""AgOpenGPS's frames as the machine understands them: work state, sections per channel and
row, and the controller's fallback when AgOpenGPS goes quiet."""

from __future__ import annotations

from gateway.config import parse_config
from gateway.control.controller import Controller
from gateway.control.work_state import WorkState
from gateway.core.alarms import AlarmBoard
from gateway.metering.agopengps import CabInputs
from protocol import agopengps as aog

CHANNELS = [
    {"name": n, "product": "wheat", "target_rate_kg_ha": 100.0, "node_id": i}
    for i, n in ((1, "left"), (2, "right"), (3, "fert"))
]
SETTINGS = parse_config({
    "machine": {"rows": 6},
    "channel": CHANNELS,
    "control": {"start_working": True},
    "speed": {"source": "agopengps_then_radar"},
    "isobus": {"enabled": False, "work_state_source": "agopengps_then_inclinometer"},
    "agopengps": {"sections": [{"channel": "left", "rows": [1, 2, 3]},
                               {"channel": "right", "rows": [4, 5, 6]}]},
})


def sections(*on: int) -> tuple[bool, ...]:
    return tuple(i + 1 in on for i in range(16))


def test_a_section_off_stops_its_channel_and_marks_its_rows() -> None:
    cab = CabInputs(SETTINGS.agopengps)
    cab.on_message(aog.SteerData(6.0, sections(1)), 10.0)
    assert cab.working
    assert cab.channel_on("left", 10.0) and not cab.channel_on("right", 10.0)
    assert cab.channel_on("fert", 10.0)  # not mapped: follows the work state alone
    assert cab.rows_off(10.0) == {4, 5, 6}
    # stale: channels follow the work state (whose priority list says what AgOpenGPS lost is)
    assert cab.channel_on("right", 14.5) and cab.rows_off(14.5) == set()


def test_all_sections_off_lift_up_or_geo_stop_is_not_working() -> None:
    cab = CabInputs(SETTINGS.agopengps)
    cab.on_message(aog.SteerData(6.0, sections()), 1.0)
    assert not cab.working
    cab.on_message(aog.MachineData(0, 0.6, aog.HYD_LIFT_RAISE, 0, False, sections(1)), 1.1)
    assert not cab.working
    cab.on_message(aog.MachineData(0, 0.6, aog.HYD_LIFT_LOWER, 0, True, sections(1)), 1.2)
    assert not cab.working
    cab.on_message(aog.MachineData(0, 0.6, aog.HYD_LIFT_LOWER, 0, False, sections(1)), 1.3)
    assert cab.working


def test_pgn_229_sets_all_64_sections_and_the_tool_speeds() -> None:
    cab = CabInputs(SETTINGS.agopengps)
    cab.on_message(aog.Sections64((False,) * 63 + (True,), 1.2, 2.4), 1.0)
    assert cab.sections[63] and cab.working and cab.tool_speeds_mps == (1.2, 2.4)


def test_controller_follows_agopengps_then_falls_back() -> None:
    c = Controller(SETTINGS, AlarmBoard("m1"))
    for k in range(10):
        t = k * 0.1
        c.on_speed("agopengps", 6.0, t)
        c.on_agopengps_work(True, t)
        c.on_speed("radar", 0.0, t)
        c.on_tilt(-6.0, t)  # inclinometer: lowered
        out = c.tick(t)
    assert out.speed_source == "agopengps" and out.state is WorkState.SEEDING
    c.on_agopengps_work(False, 1.0)  # AgOpenGPS: all sections off
    c.on_speed("agopengps", 6.0, 1.0)
    assert c.tick(1.0).state is WorkState.TURNING
    # AgOpenGPS quiet for longer than agopengps.stale_after_s (4 s): radar and inclinometer
    for k in range(20):
        t = 1.1 + k * 0.3
        c.on_speed("radar", 0.0, t)
        c.on_tilt(-6.0, t)
        out = c.tick(t)
    assert out.speed_source == "radar" and out.state is WorkState.PRE_SEED
    assert c.alarms.is_active("agopengps.lost")


def test_curve_compensation_meters_each_half_at_its_own_speed() -> None:
    settings = parse_config({
        "channel": CHANNELS,
        "agopengps": {"channel_sides": {"left": "left", "right": "right"}},
    })
    cab = CabInputs(settings.agopengps)
    assert cab.speed_factor("left", 1.0) == 1.0  # no 229 yet
    # a left-hand curve: far-left edge 1.0 m/s, far-right 3.0 m/s, centre 2.0
    cab.on_message(aog.Sections64((True,) * 64, 1.0, 3.0), 1.0)
    assert cab.speed_factor("left", 1.0) == 0.75  # left half's mean (1.0 + 2.0) / 2 = 1.5
    assert cab.speed_factor("right", 1.0) == 1.25
    assert cab.speed_factor("fert", 1.0) == 1.0  # feeds the whole width
    assert cab.speed_factor("left", 6.0) == 1.0  # stale
    cab.on_message(aog.Sections64((True,) * 64, 0.1, 0.1), 7.0)
    assert cab.speed_factor("left", 7.0) == 1.0  # standing: no ratio


def test_channel_sides_name_existing_channels() -> None:
    import pytest

    from gateway.config import ConfigError

    with pytest.raises(ConfigError) as info:
        parse_config({"agopengps": {"channel_sides": {"seed": "left"}}})
    assert info.value.problems == [
        "agopengps.channel_sides.seed: no such channel (channels: none) (got 'seed')"
    ]


def test_going_quiet_is_counted_once_per_spell() -> None:
    cab = CabInputs(SETTINGS.agopengps)
    assert not cab.watch_staleness(0.0) and cab.stale_spells == 0  # never heard: no spell
    cab.on_message(aog.SteerData(6.0, sections(1)), 1.0)
    assert cab.watch_staleness(1.5)
    assert not cab.watch_staleness(5.5) and cab.stale_spells == 1
    assert not cab.watch_staleness(6.0) and cab.stale_spells == 1
    cab.on_message(aog.SteerData(6.0, sections(1)), 7.0)
    assert cab.watch_staleness(7.0) and not cab.watch_staleness(12.0) and cab.stale_spells == 2
