"""Alarm events: one per raise, severity change and clear, never one per control tick."""

from __future__ import annotations

from collections import Counter

from gateway.control.controller import OUTSIDE_CALIBRATION_HOLD_S, Controller
from gateway.control.rate_model import plan_duty
from gateway.core import commands as cmd
from gateway.core.alarms import AlarmBoard
from gateway.core.records import AlarmEvent
from tests.gateway.control.test_controller import feed, make


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


def _pull_away(
    c: Controller, t0: float, until_t: float, accel_kmh_s: float, top_kmh: float
) -> None:
    """Ticks at 3 Hz (rs485.poll_hz) while the radar reports a pull-away from standstill."""
    t = t0
    while t < until_t:
        t += 1 / 3
        feed(c, t, kmh=min(top_kmh, max(0.0, (t - t0 - 1.0) * accel_kmh_s)))
        c.tick(t)


def test_pulling_away_from_standstill_raises_no_outside_calibration_alarm() -> None:
    """Every pull-away crossed the low end of the calibrated shaft speed in about a second
    (wheat: 7 -> 20 r/min at the simulator's 0.6 m/s^2): raised and cleared each time."""
    c, events = make()
    c.execute(cmd.Start(), "test")
    _pull_away(c, 0.0, 20.0, accel_kmh_s=0.6 * 3.6, top_kmh=5.0)
    assert c.tick(20.0).motor_pct > 0
    assert [e for e in events if e.code == "rate.outside_calibration"] == []


def test_staying_outside_the_calibrated_range_longer_than_the_hold_raises_it() -> None:
    c, events = make()
    c.execute(cmd.Start(), "test")
    t, crawling_since = 0.0, None
    while crawling_since is None or t < crawling_since + OUTSIDE_CALIBRATION_HOLD_S - 0.01:
        assert not c.alarms.is_active("rate.outside_calibration"), f"raised at {t:.2f} s"
        t += 1 / 3
        feed(c, t, kmh=1.0)  # crawling: shaft speed far below wheat's 20 r/min
        if c.tick(t).motor_pct > 0 and crawling_since is None:
            crawling_since = t
    t += 1 / 3
    feed(c, t, kmh=1.0)
    c.tick(t)
    assert c.alarms.is_active("rate.outside_calibration")
    assert [(e.code, e.active) for e in events] == [("rate.outside_calibration", True)]


def test_back_in_the_calibrated_range_clears_the_alarm_at_once() -> None:
    c, events = make()
    c.execute(cmd.Start(), "test")
    t = 0.0
    while not c.alarms.is_active("rate.outside_calibration"):
        assert t < 10.0, "never raised"
        t += 1 / 3
        feed(c, t, kmh=1.0)
        c.tick(t)
    while c.alarms.is_active("rate.outside_calibration"):
        assert t < 20.0, "never cleared"
        t += 1 / 3
        feed(c, t, kmh=5.0)
        out = c.tick(t)
        assert out.speed_kmh is not None
        plan = plan_duty(225.0, c.settings.machine.working_width_m, out.speed_kmh, c.crop_model)
        # active exactly as long as the shaft speed this tick is outside: no hold on the way out
        assert c.alarms.is_active("rate.outside_calibration") == (plan.problem is not None)
    assert [(e.code, e.active) for e in events] == [
        ("rate.outside_calibration", True), ("rate.outside_calibration", False)
    ]


def test_a_critical_alarm_waits_for_acknowledgement_even_after_it_cleared() -> None:
    """As on commercial terminals: a critical fault that came and went while nobody looked
    is still shown until the operator acknowledges it; warnings need no acknowledgement."""
    board = AlarmBoard("m")
    board.raise_("pwm.unavailable", "PWM module not answering", "critical")
    board.raise_("radar.unavailable", "radar not answering", "warning")
    assert [a.code for a in board.unacknowledged] == ["pwm.unavailable"]
    board.clear("pwm.unavailable")
    assert not board.is_active("pwm.unavailable")
    assert [a.code for a in board.unacknowledged] == ["pwm.unavailable"]
    try:
        board.acknowledge("radar.unavailable")
    except Exception as exc:
        assert "waiting: pwm.unavailable" in str(exc)
    else:
        raise AssertionError("a warning cannot be acknowledged: it never waits")
    assert board.acknowledge("pwm.unavailable") == "acknowledged: pwm.unavailable"
    assert board.unacknowledged == []


def test_acknowledging_an_active_critical_alarm_leaves_it_active_until_it_clears() -> None:
    board = AlarmBoard("m")
    board.raise_("speed.lost", "no speed", "critical")
    board.raise_("records.lost", "seeds lost", "critical")
    assert board.acknowledge(None) == "acknowledged: speed.lost, records.lost"
    assert board.is_active("speed.lost") and board.unacknowledged == []
    board.raise_("speed.lost", "no speed (new text)", "critical")  # same alarm: no new wait
    assert board.unacknowledged == []
    board.clear("speed.lost")
    board.raise_("speed.lost", "no speed again", "critical")  # raised anew: waits again
    assert [a.message for a in board.unacknowledged] == ["no speed again"]
    assert board.acknowledge(None) == "acknowledged: speed.lost"
    assert board.acknowledge(None) == "no critical alarm to acknowledge"
