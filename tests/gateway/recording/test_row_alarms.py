"""The row monitor's verdicts become registered alarms on the board the screen, MQTT and the
report read, with the severities the operator needs."""

from __future__ import annotations

from gateway.config import parse_config
from gateway.core.alarm_codes import lookup
from gateway.core.alarms import AlarmBoard
from gateway.recording.row_alarms import RowAlarms


class Recorder:
    """What RowAlarms reads of the seed recorder: seeds per row and the chattering rows."""

    def __init__(self, rows: int) -> None:
        self.edges_per_row = dict.fromkeys(range(1, rows + 1), 0)
        self.chattering: list[int] = []

    def implausible_rows(self, within_s: float) -> list[int]:
        return self.chattering


def sow(rows: RowAlarms, recorder: Recorder, clock: list[float], seconds: float,
        silent: frozenset[int] | set[int] = frozenset()) -> None:
    """``seconds`` of sowing at 8 km/h, a tick every 0.5 s, the ``silent`` rows sending
    nothing."""
    for _ in range(int(seconds / 0.5)):
        clock[0] += 0.5
        for row in recorder.edges_per_row:
            if row not in silent:
                recorder.edges_per_row[row] += 6  # 12 seeds/s: 8 km/h at 0.185 m
        rows.check(working=True, speed_kmh=8.0, meter_turning=True)


def setup(**config: object) -> tuple[RowAlarms, Recorder, AlarmBoard, list[float]]:
    settings = parse_config({"machine": {"rows": 6}, **config})
    board, recorder, clock = AlarmBoard(), Recorder(6), [0.0]
    return RowAlarms(settings, board, recorder, lambda: clock[0]), recorder, board, clock


def active(board: AlarmBoard) -> dict[str, str]:
    return {a.code: a.severity for a in board.active}


def test_a_blocked_row_is_a_critical_alarm_naming_the_row_and_it_clears() -> None:
    rows, recorder, board, clock = setup()
    sow(rows, recorder, clock, 10.0)
    assert active(board) == {}
    sow(rows, recorder, clock, 6.0, silent={5})
    assert active(board) == {"row.5.blocked": "critical"}
    assert "row 5 blocked" in board.active[0].message
    sow(rows, recorder, clock, 10.0)
    assert active(board) == {}
    assert [a.code for a in board.unacknowledged] == ["row.5.blocked"]  # seen on the screen


def test_all_rows_silent_is_one_critical_alarm_not_six_blocked_rows() -> None:
    rows, recorder, board, clock = setup()
    sow(rows, recorder, clock, 10.0)
    sow(rows, recorder, clock, 6.0, silent=set(range(1, 7)))
    assert active(board) == {"seed_sensors.all_rows_silent": "critical"}


def test_a_chattering_row_is_a_warning() -> None:
    rows, recorder, board, clock = setup()
    recorder.chattering = [2]
    sow(rows, recorder, clock, 1.0)
    assert active(board) == {"row.2.chattering": "warning"}
    recorder.chattering = []
    sow(rows, recorder, clock, 1.0)
    assert active(board) == {}


def test_every_code_raised_is_registered() -> None:
    for code in ("row.12.blocked", "row.1.skipping", "row.3.chattering",
                 "seed_sensors.all_rows_silent"):
        assert lookup(code) is not None, code


def test_the_configured_limits_are_used() -> None:
    rows, recorder, board, clock = setup(row_monitor={"delay_s": 20})
    sow(rows, recorder, clock, 10.0)
    sow(rows, recorder, clock, 10.0, silent={5})
    assert active(board) == {}  # 10 s of silence: within a 20 s delay the row still sowed
    sow(rows, recorder, clock, 12.0, silent={5})
    assert "row.5.blocked" in active(board)
