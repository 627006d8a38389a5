"""Every row of the work-state tables, written out as the operator would describe them."""

from __future__ import annotations

import itertools

import pytest

from gateway.control.work_state import (
    MODE_TABLE,
    TABLE,
    Attitude,
    Fan,
    Mode,
    ModeEvent,
    Motion,
    Motor,
    Refused,
    WorkState,
    decide,
    next_mode,
)
from gateway.core.errors import CommandError

W, S, E = Mode.WORKING, Mode.STOPPED, Mode.EMPTYING
MOV, STD, UNK = Motion.MOVING, Motion.STANDING, Motion.UNKNOWN
LOW, RAI = Attitude.LOWERED, Attitude.RAISED


@pytest.mark.parametrize(
    ("mode", "motion", "attitude", "state", "fan", "motor"),
    [
        # paper A, Table 6
        (W, MOV, RAI, WorkState.TURNING, Fan.HIGH, Motor.STOP),
        (W, MOV, LOW, WorkState.SEEDING, Fan.HIGH, Motor.FOLLOW),
        (W, STD, RAI, WorkState.PAUSED, Fan.LOW, Motor.STOP),
        (W, STD, LOW, WorkState.PRE_SEED, Fan.HIGH, Motor.STOP),
        # no valid speed: never meter
        (W, UNK, LOW, WorkState.PRE_SEED, Fan.HIGH, Motor.STOP),
        (W, UNK, RAI, WorkState.PAUSED, Fan.HIGH, Motor.STOP),
        # emptying only while standing
        (E, STD, LOW, WorkState.EMPTYING, Fan.HIGH, Motor.EMPTY),
        (E, STD, RAI, WorkState.EMPTYING, Fan.HIGH, Motor.EMPTY),
        (E, MOV, LOW, WorkState.STOPPED, Fan.OFF, Motor.STOP),
        (E, UNK, RAI, WorkState.STOPPED, Fan.OFF, Motor.STOP),
    ],
)
def test_row(
    mode: Mode, motion: Motion, attitude: Attitude, state: WorkState, fan: Fan, motor: Motor
) -> None:
    assert decide(mode, motion, attitude) == (state, fan, motor)


@pytest.mark.parametrize(("motion", "attitude"), list(itertools.product(Motion, Attitude)))
def test_operator_stop_turns_everything_off(motion: Motion, attitude: Attitude) -> None:
    assert decide(S, motion, attitude) == (WorkState.STOPPED, Fan.OFF, Motor.STOP)


def test_table_covers_every_combination_and_meters_only_when_seeding() -> None:
    assert set(TABLE) == set(itertools.product(Mode, Motion, Attitude))
    following = [k for k, v in TABLE.items() if v.motor is Motor.FOLLOW]
    assert following == [(W, MOV, LOW)]


# ---- the operator mode: what each event does in each mode --------------------------------
START, STOP, EMPTY = ModeEvent.START, ModeEvent.STOP, ModeEvent.EMPTY
EMPTY_MOVING = ModeEvent.EMPTY_WHILE_MOVING
NOT_STANDING, TIMED_OUT = ModeEvent.NOT_STANDING, ModeEvent.EMPTYING_TIMED_OUT
ONLY_STANDING = "empty residual seed only while standing"

MODE_ROWS: list[tuple[Mode, ModeEvent, Mode | str]] = [
    # the operator's start and stop apply whatever the mode
    (S, START, W),
    (W, START, W),
    (E, START, W),
    (S, STOP, S),
    (W, STOP, S),
    (E, STOP, S),
    # emptying may start (or start over) from any mode, but not on a rolling machine
    (S, EMPTY, E),
    (W, EMPTY, E),
    (E, EMPTY, E),
    (S, EMPTY_MOVING, ONLY_STANDING),
    (W, EMPTY_MOVING, ONLY_STANDING),
    (E, EMPTY_MOVING, ONLY_STANDING),
    # the machine ends an emptying by rolling off (or losing its speed) ...
    (S, NOT_STANDING, S),
    (W, NOT_STANDING, W),
    (E, NOT_STANDING, S),
    # ... and the clock ends it after control.emptying_timeout_s
    (S, TIMED_OUT, S),
    (W, TIMED_OUT, W),
    (E, TIMED_OUT, S),
]


@pytest.mark.parametrize(("mode", "event", "then"), MODE_ROWS)
def test_mode_change(mode: Mode, event: ModeEvent, then: Mode | str) -> None:
    if isinstance(then, Mode):
        assert next_mode(mode, event) is then
    else:  # refused: the reason goes back to the operator, the caller keeps its mode
        with pytest.raises(CommandError, match=f"^{then}$"):
            next_mode(mode, event)
        assert MODE_TABLE[(mode, event)] == Refused(then)


def test_mode_rows_cover_every_mode_and_event_once() -> None:
    pairs = [(mode, event) for mode, event, _ in MODE_ROWS]
    assert len(pairs) == len(set(pairs))
    assert set(pairs) == set(itertools.product(Mode, ModeEvent)) == set(MODE_TABLE)


def test_only_the_operator_starts_work_or_emptying() -> None:
    entered = {
        (event, then)
        for (mode, event), then in MODE_TABLE.items()
        if isinstance(then, Mode) and then is not mode and then is not Mode.STOPPED
    }
    assert entered == {(START, W), (EMPTY, E)}
