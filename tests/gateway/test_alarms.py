"""Alarm events: one per raise, severity change and clear, never one per control tick."""

from __future__ import annotations

from collections import Counter

from gateway import commands as cmd
from gateway.alarms import AlarmBoard
from gateway.records import AlarmEvent
from tests.gateway.test_controller import feed, make


def test_a_changing_message_updates_the_active_alarm_without_a_new_event() -> None:
    events: list[AlarmEvent] = []
    board = AlarmBoard("m1", events.append)
    board.raise_("rate.low_duty", "duty 3.1 % below start-up duty 5 %", "info")
    board.raise_("rate.low_duty", "duty 2.8 % below start-up duty 5 %", "info")
    assert [a.message for a in board.active] == ["duty 2.8 % below start-up duty 5 %"]
    board.raise_("rate.low_duty", "duty 0.5 % below start-up duty 5 %", "warning")  # escalates
    board.clear("rate.low_duty")
    assert [(e.active, e.severity) for e in events] == [
        (True, "info"), (True, "warning"), (False, "warning")
    ]
    assert events[-1].message == "duty 0.5 % below start-up duty 5 %"


def test_crawling_below_the_calibrated_range_raises_one_event_not_one_per_tick() -> None:
    """Used to emit a 'raised' event at every tick (the message carries the shaft speed):
    73 alarm records stored and published in 30 s of crawling, with no clear between."""
    c, events = make()
    c.execute(cmd.Start(), "test")
    t = 0.0
    for i in range(90):  # 30 s at 3 Hz, 0.6-0.9 km/h: shaft speed below wheat's 20 r/min
        t += 1 / 3
        feed(c, t, kmh=0.6 + 0.03 * ((i * 7) % 10))
        c.tick(t)
    assert c.alarms.is_active("rate.outside_calibration")
    assert Counter((e.code, e.active) for e in events) == {("rate.outside_calibration", True): 1}
    live = next(a for a in c.alarms.active if a.code == "rate.outside_calibration")
    assert live.message != events[0].message  # the screen and state show the current value
