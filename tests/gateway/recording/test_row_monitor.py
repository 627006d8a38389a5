"""The row monitor: blocked, skipping and chattering rows and all rows silent, judged against
the other rows and the expected seed rate, never at a headland or at a crawl."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from gateway.recording.row_monitor import (
    RowMonitor,
    RowMonitorLimits,
    reference_count,
    verdict,
)

SPACING_M = 0.2
TICK_S = 0.5


class Field:
    """A planter driven through ticks: each row drops seeds at ``share`` x the rate the
    spacing gives at the speed (fractions carried, as a real meter's)."""

    def __init__(self, monitor: RowMonitor) -> None:
        self.monitor = monitor
        self.t = 0.0
        self.seeds = dict.fromkeys(range(1, monitor.rows + 1), 0)
        self._carry = dict.fromkeys(self.seeds, 0.0)

    def drive(self, seconds: float, *, kmh: float = 8.0, working: bool = True,
              meter_turning: bool = True, share: Callable[[int], float] = lambda _row: 1.0,
              chattering: tuple[int, ...] = ()) -> None:
        for _ in range(round(seconds / TICK_S)):
            self.t += TICK_S
            if working and kmh > 0:
                per_s = kmh / 3.6 / SPACING_M
                for row in self.seeds:
                    self._carry[row] += per_s * TICK_S * share(row)
                    whole = int(self._carry[row])
                    self.seeds[row] += whole
                    self._carry[row] -= whole
            self.monitor.update(self.t, working=working, speed_kmh=kmh,
                                meter_turning=meter_turning, seeds=dict(self.seeds),
                                chattering=chattering)

    def verdicts(self) -> dict[int, str]:
        return {row: r.verdict for row, r in self.monitor.report().rows.items()}


def planter(rows: int = 8, spacing: float | None = SPACING_M, **limits: float) -> Field:
    return Field(RowMonitor(rows, RowMonitorLimits(**limits), target_spacing_m=spacing))  # type: ignore[arg-type]


def test_every_row_sowing_evenly_is_ok() -> None:
    f = planter()
    f.drive(30.0)
    assert set(f.verdicts().values()) == {"ok"}
    assert not f.monitor.report().all_rows_silent


def test_before_a_full_window_no_row_is_judged() -> None:
    f = planter()
    f.drive(4.5, share=lambda row: 0.0 if row == 3 else 1.0)  # delay_s is 5
    assert set(f.verdicts().values()) == {"unknown"}


def test_a_row_silent_for_the_delay_is_blocked_and_the_others_stay_ok() -> None:
    """Issue 20 item 2: one row silent for 15 s raised nothing."""
    f = planter()
    f.drive(10.0)
    f.drive(6.0, share=lambda row: 0.0 if row == 3 else 1.0)
    verdicts = f.verdicts()
    assert verdicts[3] == "blocked"
    assert {v for r, v in verdicts.items() if r != 3} == {"ok"}
    assert f.monitor.report().rows[3].pct_of_reference == pytest.approx(0.0, abs=10.0)


def test_a_row_at_half_the_rate_of_its_neighbours_is_skipping() -> None:
    f = planter()
    f.drive(20.0, share=lambda row: 0.5 if row == 5 else 1.0)
    assert f.verdicts()[5] == "skipping"
    assert f.monitor.report().rows[5].pct_of_reference == pytest.approx(50.0, abs=5.0)


def test_a_row_judged_against_its_neighbours_follows_a_rate_change_of_the_whole_planter() -> None:
    """Every row at 60 % of what the spacing asks (the operator sows thinner): no row is
    skipping, for rows are judged against the median row."""
    f = planter()
    f.drive(30.0, share=lambda _row: 0.6)
    assert set(f.verdicts().values()) == {"ok"}


def test_a_blocked_row_recovers_once_it_sows_again() -> None:
    f = planter()
    f.drive(10.0, share=lambda row: 0.0 if row == 2 else 1.0)
    assert f.verdicts()[2] == "blocked"
    f.drive(10.0)
    assert f.verdicts()[2] == "ok"


def test_headland_turns_and_low_speed_are_never_judged_and_a_verdict_holds_through_them() -> None:
    f = planter()
    f.drive(20.0)
    # raised at the headland, the rows stop: nothing changes
    f.drive(15.0, working=False, share=lambda _row: 0.0)
    assert set(f.verdicts().values()) == {"ok"}
    # creeping at 1 km/h (below min_speed_kmh 2): not judged either
    f.drive(20.0, kmh=1.0, share=lambda row: 0.0 if row == 1 else 1.0)
    assert f.verdicts()[1] == "ok"
    assert not f.monitor.report().judging
    # lowered again: the window restarts, so the turn's silence is not counted
    f.drive(4.5, share=lambda row: 0.0 if row == 1 else 1.0)
    assert f.verdicts()[1] == "ok"
    f.drive(1.0, share=lambda row: 0.0 if row == 1 else 1.0)
    assert f.verdicts()[1] == "blocked"
    # raised again: blocked stays until a pass shows its seeds
    f.drive(15.0, working=False)
    assert f.verdicts()[1] == "blocked"


def test_a_low_seed_rate_waits_for_enough_expected_seeds() -> None:
    """At 2 km/h and 1 m spacing a row drops 0.56 seeds a second: 5 s hold 2.8 seeds, too
    few to tell a blocked row; the window grows until the reference reaches 20."""
    f = Field(RowMonitor(8, RowMonitorLimits(), target_spacing_m=1.0))
    f.monitor.target_spacing_m = 1.0
    # seeds at 0.56/s: the Field helper's SPACING_M is 0.2, so a share of 0.2 gives 1 m
    f.drive(20.0, kmh=2.0, share=lambda row: 0.0 if row == 4 else 0.2)
    assert f.verdicts()[4] == "unknown"  # 11 seeds a row so far
    f.drive(20.0, kmh=2.0, share=lambda row: 0.0 if row == 4 else 0.2)
    assert f.verdicts()[4] == "blocked"
    assert f.monitor.report().window_s is not None and f.monitor.report().window_s > 30.0


def test_all_rows_silent_while_the_meter_turns_is_its_own_verdict() -> None:
    """Issue 20 item 2: every row silent for 15 s while sowing (~900 seeds) raised nothing."""
    f = planter(rows=12)
    f.drive(10.0)
    f.drive(6.0, share=lambda _row: 0.0)
    report = f.monitor.report()
    assert report.all_rows_silent
    # no row is blamed on its own: there is no healthy row to compare with
    assert set(f.verdicts().values()) == {"ok"}
    f.drive(1.0)  # seeds again
    assert not f.monitor.report().all_rows_silent


def test_all_rows_silent_needs_the_meter_turning_and_the_delay() -> None:
    f = planter(rows=12)
    f.drive(10.0, meter_turning=False, share=lambda _row: 0.0)  # e.g. the rate is 0
    assert not f.monitor.report().all_rows_silent
    f.drive(4.5, share=lambda _row: 0.0)
    assert not f.monitor.report().all_rows_silent
    f.drive(1.0, share=lambda _row: 0.0)
    assert f.monitor.report().all_rows_silent


def test_without_a_configured_spacing_rows_are_judged_against_the_median_row() -> None:
    f = planter(spacing=None)
    f.drive(20.0, share=lambda row: 0.0 if row == 6 else 1.0)
    assert f.verdicts()[6] == "blocked"
    assert f.monitor.report().expected_seeds_per_s is None


def test_a_two_row_planter_is_judged_against_the_spacing() -> None:
    f = planter(rows=2)
    f.drive(20.0, share=lambda row: 0.4 if row == 2 else 1.0)
    assert f.verdicts() == {1: "ok", 2: "skipping"}
    assert f.monitor.report().expected_seeds_per_s == pytest.approx(8 / 3.6 / SPACING_M)


def test_a_chattering_row_is_shown_as_such_and_left_out_of_the_reference() -> None:
    f = planter(rows=4)
    f.drive(20.0, share=lambda row: 0.0 if row == 4 else 1.0, chattering=(1, 2))
    verdicts = f.verdicts()
    assert verdicts[1] == verdicts[2] == "chattering"
    assert verdicts[3] == "ok" and verdicts[4] == "blocked"  # 2 rows left: the spacing decides
    f.drive(1.0)
    assert f.verdicts()[1] == "unknown"  # no window clear of its chatter yet


def test_a_row_is_not_judged_on_a_window_its_chatter_was_in() -> None:
    """While a row chatters, and for its quarantine after, its edges (real seeds among them)
    are dropped: it must not come out of the chatter as skipping."""
    f = planter(rows=6)
    f.drive(10.0)
    f.drive(5.0, chattering=(2,))
    f.drive(2.0, share=lambda row: 0.0 if row == 2 else 1.0)  # the quarantine
    f.drive(4.5)
    assert f.verdicts()[2] == "ok"
    f.drive(10.0, share=lambda row: 0.0 if row == 2 else 1.0)
    assert f.verdicts()[2] == "blocked"  # judged again once the window is clear of it


def test_the_thresholds_are_the_configured_ones() -> None:
    limits = RowMonitorLimits(blocked_pct=20.0, skip_pct=90.0)
    assert verdict(20, 100.0, limits) == "blocked"
    assert verdict(21, 100.0, limits) == "skipping"
    assert verdict(89, 100.0, limits) == "skipping"
    assert verdict(90, 100.0, limits) == "ok"
    assert reference_count({1: 10, 2: 50, 3: 60, 4: 70}, None) == 55.0
    assert reference_count({1: 10, 2: 50, 3: 60, 4: 70}, 80.0, excluded=[1, 2]) == 80.0
    assert reference_count({1: 10, 2: 50}, None) is None
