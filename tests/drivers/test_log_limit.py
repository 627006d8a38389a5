"""Rate-limited logging: first occurrence at once, then one line per interval with a count."""

from __future__ import annotations

import logging

import pytest

from drivers.log_limit import RateLimitedLog

LOGGER = logging.getLogger("tests.log_limit")


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def test_the_first_occurrence_is_logged_and_a_storm_costs_one_line_per_interval(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    limited = RateLimitedLog(LOGGER, 10.0, clock=clock)
    caplog.set_level(logging.INFO)
    for i in range(1000):  # 1 000 bad frames in 9.99 s
        limited.warning("garbage", "bad frame %d", i)
        clock.now += 0.00999
    assert _warnings(caplog) == ["bad frame 0"]
    clock.now = 1010.0
    limited.warning("garbage", "bad frame %d", 1000)
    assert _warnings(caplog) == ["bad frame 0", "bad frame 1000 (999 more in the last 10 s)"]


def test_keys_are_limited_independently(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    limited = RateLimitedLog(LOGGER, 10.0, clock=clock)
    for _ in range(5):
        limited.warning("checksum", "checksum")
        limited.warning("overlong", "overlong")
    assert _warnings(caplog) == ["checksum", "overlong"]


def test_an_occurrence_after_a_quiet_interval_is_logged_without_a_count(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    limited = RateLimitedLog(LOGGER, 10.0, clock=clock)
    assert limited.warning("k", "one")
    clock.now += 30.0
    assert limited.warning("k", "two")
    assert _warnings(caplog) == ["one", "two"]


def test_held_back_lines_go_to_debug_so_nothing_is_lost_for_who_wants_it(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    limited = RateLimitedLog(LOGGER, 10.0, clock=clock)
    caplog.set_level(logging.DEBUG, logger=LOGGER.name)
    limited.warning("k", "a")
    assert not limited.warning("k", "b")
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.WARNING, "a"), (logging.DEBUG, "b"),
    ]


def test_flush_reports_the_tail_of_a_storm_once_its_interval_is_over(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    limited = RateLimitedLog(LOGGER, 10.0, clock=clock)
    for i in range(4):
        limited.warning("k", "bad %d", i)
    limited.flush()  # interval not over yet: nothing
    assert _warnings(caplog) == ["bad 0"]
    clock.now += 12.0
    limited.flush()
    assert _warnings(caplog) == ["bad 0", "bad 3 (2 more in the last 12 s)"]
    limited.flush()  # nothing held any more
    assert len(_warnings(caplog)) == 2


def test_reset_logs_the_next_occurrence_at_once(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    limited = RateLimitedLog(LOGGER, 10.0, clock=clock)
    limited.warning("open", "cannot open")
    limited.reset("open")
    limited.warning("open", "cannot open")
    assert _warnings(caplog) == ["cannot open", "cannot open"]


def test_the_log_line_points_at_the_caller(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    limited = RateLimitedLog(LOGGER, 10.0, clock=clock)
    limited.warning("k", "x")
    clock.now += 20
    limited.warning("k", "x")
    limited.warning("k", "x")
    clock.now += 20
    limited.warning("k", "x")
    assert {r.funcName for r in caplog.records} == {"test_the_log_line_points_at_the_caller"}


def test_a_non_positive_interval_is_refused() -> None:
    with pytest.raises(ValueError, match="interval_s"):
        RateLimitedLog(LOGGER, 0.0)
