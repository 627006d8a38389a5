"""The work-state machine: one table from (operator mode, motion, attitude) to what to drive.

Paper A, Table 6, is the heart of it (the four rows under ``Mode.WORKING``); the operator's
stop and the "empty residual seed" function are rows here too, so every combination the
controller can meet is written down in one place and tested row by row.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple


class Mode(StrEnum):
    """What the operator asked for on the HMI (or over MQTT)."""

    STOPPED = "stopped"
    WORKING = "working"
    EMPTYING = "emptying"


class Motion(StrEnum):
    MOVING = "moving"
    STANDING = "standing"
    UNKNOWN = "unknown"  # no valid speed: never meter on a guess


class Attitude(StrEnum):
    LOWERED = "lowered"
    RAISED = "raised"  # also what a lost inclinometer counts as


class WorkState(StrEnum):
    STOPPED = "stopped"
    PRE_SEED = "pre_seed"
    SEEDING = "seeding"
    TURNING = "turning"
    PAUSED = "paused"
    EMPTYING = "emptying"


class Fan(StrEnum):
    OFF = "off"
    LOW = "low"
    HIGH = "high"


class Motor(StrEnum):
    STOP = "stop"
    FOLLOW = "follow"  # duty from the rate model at the current speed
    EMPTY = "empty"  # fixed emptying duty


class Outputs(NamedTuple):
    state: WorkState
    fan: Fan
    motor: Motor


_W, _S, _E = Mode.WORKING, Mode.STOPPED, Mode.EMPTYING
_MOV, _STD, _UNK = Motion.MOVING, Motion.STANDING, Motion.UNKNOWN
_LOW, _RAI = Attitude.LOWERED, Attitude.RAISED

TABLE: dict[tuple[Mode, Motion, Attitude], Outputs] = {
    # paper A, Table 6
    (_W, _MOV, _RAI): Outputs(WorkState.TURNING, Fan.HIGH, Motor.STOP),
    (_W, _MOV, _LOW): Outputs(WorkState.SEEDING, Fan.HIGH, Motor.FOLLOW),
    (_W, _STD, _RAI): Outputs(WorkState.PAUSED, Fan.LOW, Motor.STOP),
    (_W, _STD, _LOW): Outputs(WorkState.PRE_SEED, Fan.HIGH, Motor.STOP),
    # speed unknown: the machine may be rolling, so keep air up but never meter on a guess
    (_W, _UNK, _RAI): Outputs(WorkState.PAUSED, Fan.HIGH, Motor.STOP),
    (_W, _UNK, _LOW): Outputs(WorkState.PRE_SEED, Fan.HIGH, Motor.STOP),
    # emptying the hopper is a standing job; rolling off ends it (the controller drops the mode)
    (_E, _STD, _RAI): Outputs(WorkState.EMPTYING, Fan.HIGH, Motor.EMPTY),
    (_E, _STD, _LOW): Outputs(WorkState.EMPTYING, Fan.HIGH, Motor.EMPTY),
    (_E, _MOV, _RAI): Outputs(WorkState.STOPPED, Fan.OFF, Motor.STOP),
    (_E, _MOV, _LOW): Outputs(WorkState.STOPPED, Fan.OFF, Motor.STOP),
    (_E, _UNK, _RAI): Outputs(WorkState.STOPPED, Fan.OFF, Motor.STOP),
    (_E, _UNK, _LOW): Outputs(WorkState.STOPPED, Fan.OFF, Motor.STOP),
    # operator stop: everything off whatever the machine does
    **{
        (_S, m, a): Outputs(WorkState.STOPPED, Fan.OFF, Motor.STOP)
        for m in Motion
        for a in Attitude
    },
}


def decide(mode: Mode, motion: Motion, attitude: Attitude) -> Outputs:
    return TABLE[(mode, motion, attitude)]
