"""The machine's state at one moment, typed: what the cab screens and the farm are shown.

The daemon builds one :class:`MachineState` per call (``Daemon.state()``); the terminal view
(``gateway.ui.terminal``), the touchscreen (``gateway.ui.touchscreen``) and the MQTT ``state``
payload (``gateway.app.wiring.state_payload``) read it by attribute, so mypy sees every field
they use (it used to be a ``dict[str, Any]`` read back by string key, where a renamed key was
a ``KeyError`` at run time, or silently a default).

It sits in its own layer, above the domains and below ``link`` and ``ui``: it is made of the
domains' own typed states (the recorder's, the store's, the CAN channels', paper A's motor
channel's), which stay beside the code that fills them, and ``link`` and ``ui`` may not import
``app``, where it is built. Everything is frozen: a state is a copy, never a view into the
live parts, so a screen drawn from it cannot change what it shows half-way through.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime

from gateway.control.hopper_loop import HopperState
from gateway.core.records import AlarmSeverity, FixQuality
from gateway.metering.channels import ChannelStatus, MeteringStatus
from gateway.metering.pwm_channel import PwmChannelState
from gateway.recording.recorder import RecorderState, RowState
from gateway.recording.row_monitor import RowMonitorReport
from gateway.recording.spacing_quality import SpacingQuality
from gateway.recording.store import StoreState

__all__ = [
    "ActiveAlarmState",
    "ChannelStatus",
    "HopperState",
    "MachineState",
    "MeteringStatus",
    "PwmChannelState",
    "RecorderState",
    "RejectedCounts",
    "RowState",
    "SpacingQuality",
    "StoreState",
]


@dataclass(frozen=True, slots=True)
class ActiveAlarmState:
    """One active alarm as it stands (``AlarmBoard.active`` updates its message in place)."""

    code: str
    severity: AlarmSeverity
    message: str
    since: datetime


@dataclass(frozen=True, slots=True)
class RejectedCounts:
    """Input received and not used since start, per device and reason (``state.rejected``):
    GNSS lines and the bytes of overlong ones dropped, touchscreen frames, seed-sensor lines
    and implausible edges. A device not configured has no reasons."""

    gnss: Mapping[str, int] = field(default_factory=dict)
    gnss_discarded_bytes: int = 0
    hmi: Mapping[str, int] = field(default_factory=dict)
    seed_sensors: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class MachineState:
    """The whole machine at ``utc``: work state, speed, rates, duties, devices, alarms,
    counters, and the state of each optional part (None when the config leaves it off)."""

    machine_id: str
    utc: datetime
    work_state: str  # a ``WorkState`` value: "stopped" until the first control tick
    mode: str  # the controller's ``Mode`` value
    speed_kmh: float | None
    speed_source: str | None  # "radar", "gnss", "isobus", "agopengps"; None: no valid source
    tilt_deg: float | None
    raised: bool
    crop: str
    target_rate_kg_ha: float  # the rate aimed at (map or operator)
    commanded_rate_kg_ha: float
    motor_duty_pct: float
    fan_duty_pct: float
    # device -> answering, in the order shown: the RS485 devices, then gnss, hmi, seed_sensors
    devices: Mapping[str, bool]
    alarms: tuple[ActiveAlarmState, ...]  # oldest first
    area_ha: float
    seed_mass_kg: float
    gnss_fix: FixQuality = "none"
    store: StoreState | None = None
    seeds: RecorderState | None = None
    metering: MeteringStatus | None = None
    pwm_channel: PwmChannelState | None = None
    rejected: RejectedCounts | None = None  # None without a device that can reject input
    hopper: HopperState | None = None  # None without [hopper_scale]
    # critical alarms not acknowledged yet (active or cleared), oldest first: code -> message
    unacknowledged: tuple[tuple[str, str], ...] = ()
    seed_lot: str = "default"  # the active seed lot of ``crop`` (gateway.calibration.lots)
    seed_lots: Mapping[str, str] = field(default_factory=dict)  # crop -> lot, when not default
    row_monitor: RowMonitorReport | None = None  # None without seed recording or [row_monitor]
