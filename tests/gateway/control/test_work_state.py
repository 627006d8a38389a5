"""Every row of the work-state table, written out as the operator would describe it."""

from __future__ import annotations

import itertools

import pytest

from gateway.control.work_state import TABLE, Attitude, Fan, Mode, Motion, Motor, WorkState, decide

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
