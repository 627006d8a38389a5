"""The work-state machine: two tables, one for the operator mode and one for what to drive.

``MODE_TABLE`` (used through ``next_mode``) is every way the operator mode changes: the
operator's start, stop and "empty residual seed", and the two ways an emptying ends by
itself (the machine rolls off or loses its speed; ``control.emptying_timeout_s`` runs out).
The controller only says which event happened; this table says where it leads:

    mode      START    STOP     EMPTY     EMPTY_WHILE_MOVING  NOT_STANDING  EMPTYING_TIMED_OUT
    stopped   working  stopped  emptying  refused             stopped       stopped
    working   working  stopped  emptying  refused             working       working
    emptying  working  stopped  emptying  refused             stopped       stopped

EMPTY is the operator's request while the machine is not known to be moving (standing, or
no valid speed: that emptying then ends at the next tick by NOT_STANDING); on a machine
known to be moving it is EMPTY_WHILE_MOVING and refused, the mode stays. EMPTY while already
emptying starts the job over (the controller restarts its clock).

``TABLE`` (used through ``decide``) maps (operator mode, motion, attitude) to the state, fan
and motor. Paper A, Table 6, is the heart of it (the four rows under ``Mode.WORKING``); the
operator's stop and the emptying are rows here too, so every combination the controller can
meet is written down in one place and tested row by row.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple

from gateway.core.errors import CommandError


class Mode(StrEnum):
    """What the operator asked for on the HMI (or over MQTT); changed only by ``next_mode``."""

    STOPPED = "stopped"
    WORKING = "working"
    EMPTYING = "emptying"


class ModeEvent(StrEnum):
    """What can change the operator mode: an operator command or what the machine did."""

    START = "start"  # operator: start work
    STOP = "stop"  # operator: stop
    EMPTY = "empty"  # operator: empty residual seed, machine not known to be moving
    EMPTY_WHILE_MOVING = "empty_while_moving"  # the same on a machine known to be moving
    NOT_STANDING = "not_standing"  # a tick: moving, or no valid speed
    EMPTYING_TIMED_OUT = "emptying_timed_out"  # a tick: emptying ran control.emptying_timeout_s


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


class Refused(NamedTuple):
    """An operator request turned down: the mode stays, ``reason`` is shown to the operator."""

    reason: str


_W, _S, _E = Mode.WORKING, Mode.STOPPED, Mode.EMPTYING
_ONLY_STANDING = Refused("empty residual seed only while standing")

_START, _STOP, _EMPTY = ModeEvent.START, ModeEvent.STOP, ModeEvent.EMPTY
_EMPTY_MOVING, _NOT_STANDING = ModeEvent.EMPTY_WHILE_MOVING, ModeEvent.NOT_STANDING
_TIMED_OUT = ModeEvent.EMPTYING_TIMED_OUT

MODE_TABLE: dict[tuple[Mode, ModeEvent], Mode | Refused] = {
    # the operator's start and stop apply whatever the mode
    (_S, _START): _W, (_W, _START): _W, (_E, _START): _W,
    (_S, _STOP): _S, (_W, _STOP): _S, (_E, _STOP): _S,
    # emptying may start from any mode (from emptying: the job starts over), never rolling
    (_S, _EMPTY): _E, (_W, _EMPTY): _E, (_E, _EMPTY): _E,
    (_S, _EMPTY_MOVING): _ONLY_STANDING,
    (_W, _EMPTY_MOVING): _ONLY_STANDING,
    (_E, _EMPTY_MOVING): _ONLY_STANDING,
    # emptying is a standing job: rolling off (or losing the speed) or its timeout ends it;
    # work and stop are the operator's to end
    (_S, _NOT_STANDING): _S, (_W, _NOT_STANDING): _W, (_E, _NOT_STANDING): _S,
    (_S, _TIMED_OUT): _S, (_W, _TIMED_OUT): _W, (_E, _TIMED_OUT): _S,
}


def next_mode(mode: Mode, event: ModeEvent) -> Mode:
    """The operator mode after ``event``; raises ``CommandError`` with the reason if refused."""
    then = MODE_TABLE[(mode, event)]
    if isinstance(then, Refused):
        raise CommandError(then.reason)
    return then


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
    # emptying the hopper is a standing job; rolling off ends it (MODE_TABLE, NOT_STANDING,
    # applied before ``decide`` on the same tick), so the four rows off standstill are never
    # met by the controller: they say what would be safe
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
