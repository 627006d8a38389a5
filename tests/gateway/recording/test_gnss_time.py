"""GNSS time you can trust: bad stamps rejected without stalling the epoch history, a real time
step re-maps with an alarm's worth of evidence, week rollover corrected, leap seconds carried
through (gateway.recording.positioning.gnss_time and the positioner that uses it)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.core.alarms import AlarmBoard
from gateway.recording.health import TIME_EVENT_ALARM_S, RecordingHealth
from gateway.recording.positioning import Landing, SeedPositioner, TimeEvents
from gateway.recording.positioning.gnss_time import (
    EARLIEST_PLAUSIBLE_UTC,
    GPS_WEEK_ROLLOVER_S,
    LATE_MAX_S,
    STEP_CONFIRM_EPOCHS,
    GnssTimeGuard,
    correct_week_rollover,
)
from tests.gateway.recording.test_positioning import (
    FRAME,
    MONO0,
    UTC0,
    Epoch,
    arrivals,
    settings,
    straight,
)

T0 = UTC0.timestamp()
ROLLOVER = timedelta(weeks=1024)


def feed(guard: GnssTimeGuard, stamps: list[float], t_start: float = 0.0) -> list[str]:
    """Epochs 0.1 s apart on the host clock carrying ``stamps`` (offsets from T0)."""
    return [
        guard.judge(MONO0 + t_start + 0.1 * k + 0.04, T0 + s).verdict
        for k, s in enumerate(stamps)
    ]


# ---------------------------------------------------------------- the guard alone


def test_stamps_that_follow_the_host_clock_are_all_accepted() -> None:
    guard = GnssTimeGuard()
    assert feed(guard, [0.1 * k for k in range(30)]) == ["first"] + ["ok"] * 29
    assert guard.events.outliers == guard.events.steps == 0


def test_two_stamps_two_hours_ahead_are_outliers_and_the_next_good_one_is_ok() -> None:
    guard = GnssTimeGuard()
    stamps = [0.1 * k for k in range(20)]
    stamps[10] += 7200.0
    stamps[11] += 7200.0
    verdicts = feed(guard, stamps)
    assert verdicts[10:13] == ["outlier", "outlier", "ok"]
    assert verdicts.count("ok") == 17
    assert guard.events.outliers == 2 and guard.events.steps == 0


def test_a_stamp_in_the_past_is_an_outlier_a_repeated_one_is_not_news() -> None:
    guard = GnssTimeGuard()
    stamps = [0.1 * k for k in range(10)]
    stamps[5] = stamps[4]  # the same epoch again
    stamps[7] -= 3600.0
    verdicts = feed(guard, stamps)
    assert verdicts[5] == "repeat" and verdicts[7] == "outlier"
    assert verdicts[8:] == ["ok", "ok"]


def test_arrival_jitter_and_a_late_delivery_are_not_outliers() -> None:
    """Jitter only delays an arrival; a host stall delivers old epochs late: both keep the
    stamp, which is right."""
    guard = GnssTimeGuard()
    for k in range(10):
        assert guard.judge(MONO0 + 0.1 * k + 0.04 * (k % 3), T0 + 0.1 * k).usable
    # the loop stalled 3 s: 30 epochs arrive at once
    verdicts = {guard.judge(MONO0 + 4.0, T0 + 1.0 + 0.1 * k).verdict for k in range(30)}
    assert verdicts == {"ok"}


def test_a_stamp_far_behind_the_host_clock_is_an_outlier_even_after_a_silence() -> None:
    """After a silence, a stamp later than the last one can still be in the past: an epoch
    does not wait LATE_MAX_S in a serial buffer."""
    guard = GnssTimeGuard()
    feed(guard, [0.1 * k for k in range(10)])
    check = guard.judge(MONO0 + 3600.0, T0 + 1.0 + 1800.0)  # 1 h silent, stamp 30 min on
    assert check.verdict == "outlier" and -check.error_s > LATE_MAX_S


def test_a_persistent_step_is_taken_after_the_confirming_epochs_with_its_size() -> None:
    guard = GnssTimeGuard()
    stamps = [0.1 * k for k in range(10)] + [0.1 * k - 3600.0 for k in range(10, 30)]
    verdicts = feed(guard, stamps)
    step_at = 10 + STEP_CONFIRM_EPOCHS - 1
    assert verdicts[10:step_at] == ["outlier"] * (STEP_CONFIRM_EPOCHS - 1)
    assert verdicts[step_at] == "step"
    assert set(verdicts[step_at + 1:]) == {"ok"}
    assert guard.events.steps == 1
    assert guard.events.last_step_s == pytest.approx(-3600.0, abs=0.01)


def test_outliers_that_disagree_with_each_other_never_make_a_step() -> None:
    guard = GnssTimeGuard()
    feed(guard, [0.1 * k for k in range(10)])
    for k in range(20):  # garbage stamps, each somewhere else
        check = guard.judge(MONO0 + 1.0 + 0.1 * k, T0 + 1.0 + 0.1 * k + 100.0 * (k + 1))
        assert check.verdict == "outlier"
    assert guard.events.steps == 0


@given(st.integers(0, 20 * 365 * 86_400 - 1), st.integers(1, 3))
def test_a_date_1024_weeks_early_is_corrected_to_the_true_one(offset_s: int, eras: int) -> None:
    true = EARLIEST_PLAUSIBLE_UTC.timestamp() + offset_s
    if true >= EARLIEST_PLAUSIBLE_UTC.timestamp() + GPS_WEEK_ROLLOVER_S:
        return  # a date past the next rollover era is ambiguous by construction
    corrected, weeks = correct_week_rollover(true - eras * GPS_WEEK_ROLLOVER_S)
    assert corrected == pytest.approx(true) and weeks == 1024 * eras
    assert correct_week_rollover(true) == (true, 0)


def test_a_rolled_over_epoch_is_judged_on_its_corrected_date() -> None:
    guard = GnssTimeGuard()
    early = T0 - ROLLOVER.total_seconds()
    checks = [guard.judge(MONO0 + 0.1 * k, early + 0.1 * k) for k in range(5)]
    assert [c.verdict for c in checks] == ["first"] + ["ok"] * 4
    assert checks[0].gnss_s == pytest.approx(T0)
    assert checks[0].rollover_weeks == 1024 and guard.events.rollover_weeks == 1024
    assert checks[0].message is not None and checks[1].message is None  # logged once


@given(st.floats(-1e6, 1e6))
def test_without_a_leap_second_the_scale_is_posix_time(offset: float) -> None:
    assert GnssTimeGuard().posix_of(T0 + offset) == T0 + offset


# ---------------------------------------------------------------- through the positioner


@dataclass(frozen=True)
class LeapEpoch(Epoch):
    leap_second: bool = False


def sow(tamper: Callable[[int, LeapEpoch], LeapEpoch], until: float = 6.0) -> tuple[
    SeedPositioner, list[Landing]
]:
    """A straight 10 km/h pass, a seed every 50 ms on rows 1–3; ``tamper(k, epoch)`` changes
    epoch k's stamp as the faulty receiver would."""
    pos = SeedPositioner(settings())
    edges = [(1 + k % 3, 0.3 + 0.05 * k) for k in range(int((until - 0.8) / 0.05))]
    out: list[Landing] = []
    for t, kind, what in arrivals(straight(0.0), FRAME, edges, until=until):
        if kind == "epoch":
            assert isinstance(what, Epoch)
            k = round((what.utc - UTC0).total_seconds() / 0.1)
            epoch = tamper(k, LeapEpoch(**what.__dict__))
            out += pos.add_epoch(epoch)
        else:
            assert isinstance(what, int)
            out += pos.add_edge(what, t)
    out += pos.flush()
    assert len(out) == len(edges)
    return pos, out


def stamp_error_s(landing: Landing) -> float:
    """Record stamp minus the true UTC of its landing instant."""
    true = UTC0 + timedelta(seconds=landing.t_land - MONO0)
    return (landing.drop.utc - true).total_seconds()


def test_two_epochs_two_hours_ahead_do_not_stop_positioning() -> None:
    def ahead(k: int, e: LeapEpoch) -> LeapEpoch:
        return replace(e, utc=e.utc + timedelta(hours=2)) if k in (20, 21) else e

    pos, out = sow(ahead)
    assert not [la for la in out if la.drop.extrapolated]
    assert max(abs(stamp_error_s(la)) for la in out) < 0.01  # none stamped in the future
    assert pos.time.events.outliers == 2 and pos.stats.time_steps == 0


def test_receiver_time_stepping_back_an_hour_continues_on_the_new_time_line() -> None:
    def back(k: int, e: LeapEpoch) -> LeapEpoch:
        return replace(e, utc=e.utc - timedelta(hours=1)) if k >= 20 else e

    pos, out = sow(back)
    assert pos.stats.time_steps == 1
    extrapolated = [la for la in out if la.drop.extrapolated]
    # only the seeds of the confirming epochs (0.5 s) can miss their bracketing epoch
    assert len(extrapolated) <= (STEP_CONFIRM_EPOCHS * 0.1 + 0.2) / 0.05
    after = [la for la in out if la.t_land > MONO0 + 2.0 + STEP_CONFIRM_EPOCHS * 0.1 + 0.2]
    assert after and not [la for la in after if la.drop.extrapolated]
    assert all(abs(stamp_error_s(la) + 3600.0) < 0.01 for la in after)


def test_a_gps_week_rollover_is_corrected_and_positions_go_on() -> None:
    def rolled(k: int, e: LeapEpoch) -> LeapEpoch:
        return replace(e, utc=e.utc - ROLLOVER)

    pos, out = sow(rolled)
    assert not [la for la in out if la.drop.extrapolated]
    assert max(abs(stamp_error_s(la)) for la in out) < 0.01  # 2026, not 2006
    assert pos.time.events.rollover_weeks == 1024


def test_a_leap_second_keeps_every_seed_interpolated_and_stamps_in_order() -> None:
    """The receiver says 23:59:58, 23:59:59, 23:59:60, 00:00:00 for four real seconds."""
    midnight = datetime(2027, 1, 1, tzinfo=UTC)

    def leap(k: int, e: LeapEpoch) -> LeapEpoch:
        real = (e.utc - UTC0).total_seconds()  # true seconds since the pass began
        if real < 3.0:  # 23:59:57 .. 23:59:59.9
            return replace(e, utc=midnight - timedelta(seconds=3.0 - real))
        if real < 4.0:  # the leap second, sent as 23:59:60.x
            return replace(e, utc=midnight - timedelta(seconds=4.0 - real), leap_second=True)
        return replace(e, utc=midnight + timedelta(seconds=real - 4.0))

    pos, out = sow(leap)
    assert not [la for la in out if la.drop.extrapolated]
    assert pos.stats.epochs_ignored == 0 and pos.stats.time_steps == 0
    assert pos.time.events.outliers == 0 and pos.time.events.leap_seconds == 1
    for la in out:
        real = la.t_land - MONO0  # the landing instant, seconds into the pass
        if real < 2.99:
            expected = midnight - timedelta(seconds=3.0 - real)
        elif 3.01 < real < 3.99:
            expected = midnight - timedelta(microseconds=1)  # inside 23:59:60
        elif real > 4.01:
            expected = midnight + timedelta(seconds=real - 4.0)
        else:
            continue  # within the clock map's ms of a second's edge
        assert abs((la.drop.utc - expected).total_seconds()) < 0.01, (real, la.drop.utc)
    by_row: dict[int, list[datetime]] = {}
    for la in out:
        by_row.setdefault(la.drop.row, []).append(la.drop.utc)
    assert all(stamps == sorted(stamps) for stamps in by_row.values())


# ---------------------------------------------------------------- alarms


class _Recorder:
    """The part of SeedRecorder that RecordingHealth reads, around a real guard."""

    store_error = None
    records_lost = 0

    def __init__(self, guard: GnssTimeGuard) -> None:
        self.guard = guard

    @property
    def gnss_time(self) -> TimeEvents:
        return self.guard.events

    def implausible_rows(self, within_s: float) -> list[int]:
        return []


@pytest.mark.parametrize(
    ("code", "severity", "fault"),
    [
        ("gnss.time_outlier", "warning", lambda k, s: s + 7200.0 if k in (12, 13) else s),
        ("gnss.time_step", "warning", lambda k, s: s - 3600.0 if k >= 12 else s),
        ("gnss.week_rollover", "warning", lambda k, s: s - GPS_WEEK_ROLLOVER_S),
    ],
)
def test_each_kind_of_bad_time_raises_its_own_alarm_and_clears_a_minute_later(
    code: str, severity: str, fault: Callable[[int, float], float]
) -> None:
    guard = GnssTimeGuard()
    now = [MONO0]
    alarms = AlarmBoard()
    health = RecordingHealth(alarms, recorder=_Recorder(guard), clock=lambda: now[0])
    for k in range(30):
        now[0] = MONO0 + 0.1 * k + 0.04
        guard.judge(now[0], fault(k, T0 + 0.1 * k))
        health.check()
    active = {a.code: a.severity for a in alarms.active}
    assert active == {code: severity}
    now[0] += TIME_EVENT_ALARM_S + 1.0
    health.check()
    assert not alarms.active


def test_a_leap_second_raises_an_info_alarm() -> None:
    guard = GnssTimeGuard()
    now = [MONO0]
    alarms = AlarmBoard()
    health = RecordingHealth(alarms, recorder=_Recorder(guard), clock=lambda: now[0])
    midnight = datetime(2027, 1, 1, tzinfo=UTC).timestamp()
    for k in range(40):
        now[0] = MONO0 + 0.1 * k
        real = midnight - 2.0 + 0.1 * k
        if real < midnight:
            guard.judge(now[0], real)
        elif real < midnight + 1.0:
            guard.judge(now[0], real - 1.0, leap_second=True)
        else:
            guard.judge(now[0], real - 1.0)
        health.check()
    assert {a.code: a.severity for a in alarms.active} == {"gnss.leap_second": "info"}
    assert guard.events.outliers == guard.events.steps == 0


def test_each_bad_time_is_logged_once_not_once_per_epoch(caplog: pytest.LogCaptureFixture) -> None:
    """An outlier run, a step and a rollover each leave one line in the journal."""
    def faults(k: int, e: LeapEpoch) -> LeapEpoch:
        if k in (10, 11):
            return replace(e, utc=e.utc + timedelta(hours=2))
        if 20 <= k < 30:
            return replace(e, utc=e.utc - ROLLOVER)
        if k >= 40:
            return replace(e, utc=e.utc - timedelta(hours=1))
        return e

    with caplog.at_level("WARNING", logger="gateway.recording.positioning.positioner"):
        sow(faults)
    lines = [r.getMessage() for r in caplog.records]
    assert len([m for m in lines if "rejected: 7200.0 s ahead" in m]) == 1
    assert len([m for m in lines if "1024 weeks early" in m]) == 1
    assert len([m for m in lines if "GNSS time stepped by -3600.0 s" in m]) == 1
    assert len(lines) == 4  # and the first epoch of the step's run, rejected before it
