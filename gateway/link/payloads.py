"""Every MQTT payload as a pydantic model: the contract dashboard authors code against.

Topics live under ``<topic_prefix>/<machine_id>/`` (see docs/mqtt.md). The JSON Schemas in
docs/schemas/ are generated from these models (``python -m gateway.link.payloads --write
docs/schemas``) and a test fails when they are stale, so the documentation cannot drift from
what the daemon sends.

``status`` is the one payload that is *not* JSON: it is the bare string ``online`` or
``offline`` (retained), because that is what MQTT last-will conventions and most dashboard
tools (Home Assistant availability, Node-RED) expect. ``StatusPayload`` documents the allowed
values; its schema describes the string, not a JSON document.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    JsonValue,
    RootModel,
    ValidationInfo,
    field_validator,
)

from gateway.control.work_state import WorkState
from gateway.core.records import AlarmEvent, AlarmSeverity, FixQuality, SeedRecord

__all__ = [
    "SCHEMA_MODELS",
    "AckAlarmCommand",
    "ActiveAlarmInfo",
    "AlarmEvent",
    "CommandAck",
    "EmptyCommand",
    "HopperInfo",
    "RateCommand",
    "RejectedInput",
    "SeedBatch",
    "SeedLotCommand",
    "SpeedCalCommand",
    "StatePayload",
    "StatusPayload",
    "render_schemas",
    "write_schemas",
]

REQUEST_ID_MAX_CHARS = 128
WORK_STATES: list[JsonValue] = [w.value for w in WorkState]
SPEED_SOURCES: list[JsonValue] = ["radar", "gnss", "isobus", "agopengps", "none"]


class _Payload(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StatusPayload(RootModel[Literal["online", "offline"]]):
    """Retained on ``status``; sent as the bare string (not JSON-quoted)."""


class ActiveAlarmInfo(_Payload):
    code: str
    severity: AlarmSeverity
    message: str
    since: datetime


class RejectedInput(_Payload):
    """Input received and not used since the daemon started, per device and reason.

    Keys appear once a reason has occurred; a device that is not configured stays empty."""

    gnss: dict[str, int] = Field(
        default_factory=dict,
        description="GNSS lines per reason: checksum, truncated, missing_field, bad_field, "
        "unknown_sentence (well-framed, not used), malformed, garbage, overlong (a line of "
        "more than 1 024 bytes, e.g. binary output; its head was dropped)",
    )
    gnss_discarded_bytes: int = Field(
        0, ge=0, description="bytes dropped from overlong GNSS lines (binary output on the port)"
    )
    hmi: dict[str, int] = Field(
        default_factory=dict,
        description="touchscreen input per reason: garbage, bad_trailer, incomplete_frame, "
        "unknown_function, bad_field",
    )
    seed_sensors: dict[str, int] = Field(
        default_factory=dict,
        description="seed sensor input per reason: overlong, malformed, bad_row (serial lines), "
        "unknown_line (GPIO), implausible_rate (edges faster than "
        "seed_sensors.max_seeds_per_s_per_row: not stored as seeds)",
    )


class RowStatusInfo(_Payload):
    """One seed row as the row monitor last judged it (``gateway.recording.row_monitor``)."""

    state: Literal["ok", "blocked", "skipping", "chattering", "unknown"] = Field(
        description="ok | blocked (at most row_monitor.blocked_pct % of the median row) | "
        "skipping (below row_monitor.skip_pct %) | chattering (its sensor sends edges faster "
        "than a row can drop seeds: not stored) | unknown (not judged yet)",
    )
    seeds_per_s: float | None = Field(
        None, ge=0, description="seeds a second over the window last judged (0.01)")
    pct_of_reference: float | None = Field(
        None, ge=0, description="its seeds as % of the median row (or of the spacing's count "
        "on 1-2 row planters) over that window (0.1)")
    implausible_edges: int = Field(
        0, ge=0, description="edges of this row dropped as implausible since start (counted, "
        "never stored or published as seeds)")


class RowMonitorInfo(_Payload):
    """The row monitor (``[row_monitor]``, on wherever seeds are recorded)."""

    judging: bool = Field(
        description="working above row_monitor.min_speed_kmh: rows are being judged now")
    all_rows_silent: bool = Field(
        description="no seed on any row while the meter turns (alarm "
        "seed_sensors.all_rows_silent)")
    expected_seeds_per_s: float | None = Field(
        None, ge=0, description="seeds a second one row should drop at the current speed "
        "(positioning.target_spacing_m); null without a spacing or while not judging")
    rows: dict[str, RowStatusInfo] = Field(
        default_factory=dict, description="row number (1-based) -> its state")


class HopperInfo(_Payload):
    """The hopper scale and the discharge correction it found (only with ``[hopper_scale]``).

    ``discharge_correction`` = true / model discharge, the factor the rate model is corrected
    by; 1.0 until the evidence is enough (``correction_applied``). Its confidence is
    ``correction_standard_error``; it is kept across restarts and while the scale is silent,
    and starts again at 1.0 after a rotation test or with another seed lot."""

    mass_kg: float | None = Field(
        None, description="hopper mass, median of the last readings, 0.1 kg; null while the "
        "scale does not answer")
    time_to_empty_min: float | None = Field(
        None, ge=0, description="minutes until the hopper is empty at the current discharge; "
        "null when not discharging or no mass")
    discharge_correction: float = Field(
        1.0, gt=0, description="applied factor true / model discharge (4 decimals)")
    correction_estimate: float | None = Field(
        None, description="pooled scale estimate of true / model before the confidence "
        "weighting and the max_correction_pct clamp")
    correction_standard_error: float | None = Field(
        None, ge=0, description="standard error of correction_estimate (0.01 = 1 %)")
    correction_applied: bool = Field(
        False, description="the evidence was enough (standard error below 3 %) to apply it")
    scale_sigma_kg: float | None = Field(
        None, ge=0, description="scale noise (vibration) seen in the regression residuals")
    windows: int = Field(0, ge=0, description="regression windows pooled since start or reset")
    refills: int = Field(0, ge=0, description="refills (weight jumps) seen since start")


# Decimals each state value is published with: its sensor's (or actuator's) resolution. A
# dashboard gets 6.0, not the 5.999999999999997 the arithmetic gives; docs/mqtt.md lists them.
STATE_DECIMALS = {
    "speed_kmh": 2,  # 0.01 km/h, the radar's register resolution
    "tilt_deg": 2,  # 0.01 degree
    "target_rate_kg_ha": 2,
    "commanded_rate_kg_ha": 2,
    "motor_duty_pct": 1,  # 0.1 %, the PWM module's duty register
    "fan_duty_pct": 1,
    "area_ha": 4,  # 0.0001 ha = 1 m2
    # 1 g: at 10 g a dashboard needed 0.1 ha of rapeseed (6 kg/ha) to draw one applied rate
    "seed_mass_kg": 3,
}


class StatePayload(_Payload):
    """Retained on ``state`` at ``state_hz``, and at once when the work state, the crop or
    target rate, or the alarms change: what the cab screen shows."""

    machine_id: str
    utc: datetime
    # The daemon only sends these values (the schema lists them for dashboard authors); the
    # model itself stays a plain string so an older or newer box never fails validation.
    work_state: str = Field(
        description="stopped | pre_seed (lowered; standing or speed unknown) | seeding | "
        "turning (raised, moving) | paused (raised; standing or speed unknown) | emptying",
        json_schema_extra={"enum": WORK_STATES},
    )
    speed_kmh: float | None = Field(None, ge=0, description="null when no source is valid")
    speed_source: str = Field(
        "none", description="the source speed_kmh came from", json_schema_extra={
            "enum": SPEED_SOURCES}
    )
    tilt_deg: float | None = None
    raised: bool | None = None
    crop: str | None = None
    target_rate_kg_ha: float | None = Field(None, ge=0)
    commanded_rate_kg_ha: float | None = Field(None, ge=0)
    motor_duty_pct: float | None = Field(None, ge=0, le=100)
    fan_duty_pct: float | None = Field(None, ge=0, le=100)
    devices: dict[str, bool] = Field(
        default_factory=dict,
        description="device name -> answering: radar, inclinometer, pwm (RS485), hmi, "
        "and gnss, seed_sensors when enabled",
    )
    gnss_fix: FixQuality = "none"
    alarms: list[ActiveAlarmInfo] = Field(default_factory=list)
    unacknowledged: list[str] = Field(
        default_factory=list,
        description="codes of the critical alarms raised and not acknowledged yet (command "
        "ack_alarm), whether still active or cleared since, oldest first",
    )
    area_ha: float = Field(0.0, ge=0, description="area worked since the counters were reset")
    seed_mass_kg: float = Field(0.0, ge=0, description="seed applied since the counters were reset")
    records_held: int = Field(
        0, ge=0, description="seed records the record store cannot write yet (disk full), "
        "held in memory and written when space returns; 0 when the store is healthy",
    )
    records_lost: int = Field(
        0, ge=0, description="seed records lost since the daemon started because the store "
        "could not write them and its memory for held records was full",
    )
    rejected: RejectedInput = Field(
        default_factory=RejectedInput,
        description="input received and not used, per device and reason (totals since start; "
        "published at state_hz, a new count alone does not trigger a message)",
    )
    hopper: HopperInfo | None = Field(
        None, description="hopper scale and discharge correction; null without [hopper_scale]"
    )
    row_monitor: RowMonitorInfo | None = Field(
        None, description="per-row blocked / skipping / chattering states; null without seed "
        "recording or with [row_monitor] enabled = false",
    )

    seed_lot: str = Field(
        "default", description="the active seed lot of `crop`: whose rotation-test fits are "
        "applied (`cmd/seed_lot`)",
    )
    seed_lots: dict[str, str] = Field(
        default_factory=dict, description="crop -> active seed lot, for each crop whose lot "
        "was chosen (a crop not listed sows with its `default` lot)",
    )

    @field_validator(*STATE_DECIMALS, mode="after")
    @classmethod
    def _to_resolution(cls, value: float | None, info: ValidationInfo) -> float | None:
        assert info.field_name is not None
        return None if value is None else round(value, STATE_DECIMALS[info.field_name])

    def _urgent_part(self) -> tuple[object, ...]:
        alarms = tuple((a.code, a.severity) for a in self.alarms)
        return (self.work_state, self.crop, self.target_rate_kg_ha, alarms,
                tuple(self.unacknowledged), self.seed_lot)

    def same_as(self, other: StatePayload | None) -> bool:
        """Whether ``other`` differs in nothing that must be published at once: the work
        state, the crop, the target rate, which alarms are active (code and severity) and the
        seed lot.

        Everything else (speed, tilt, duties, counters, a live value in an alarm's text)
        changes on nearly every control tick while seeding: publishing each change sent the
        state 3 times a second instead of the documented ``state_hz``. Those values ride along
        at ``state_hz``."""
        if other is None:
            return False
        return self._urgent_part() == other._urgent_part()


class SeedBatch(_Payload):
    """One message on ``seeds``: consumers dedupe by record ``id`` (delivery is at-least-once)."""

    machine_id: str
    records: list[SeedRecord]
    pending_from: int | None = Field(
        None, ge=1,
        description="the lowest id the box had not seen delivered when it sent this batch: it "
        "will send no id below it again (those are confirmed by the farm server, or "
        "acknowledged by the broker without farm_server_ack, or were never used: ids skipped "
        "after an unclean stop). The farm server counts the ones it lacks as never to come.",
    )


class _Command(_Payload):
    """Strict, unlike the payloads the box sends: a command moves a machine, so a string is
    not read as a number (``"200"``), nor a boolean as one, and NaN/Infinity are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    request_id: str | None = Field(
        None, max_length=REQUEST_ID_MAX_CHARS, description="echoed in the ack when given"
    )


class RateCommand(_Command):
    """``cmd/rate``: set crop and target rate (ranges checked like HMI input by the controller)."""

    crop: str = Field(min_length=1, max_length=64)
    rate_kg_ha: float = Field(gt=0)


class ChannelRateCommand(_Command):
    """``cmd/channel_rate``: a metering channel's target rate, e.g. ``{"channel": "deep",
    "rate_kg_ha": 280}`` (outside a prescription map, or without one)."""

    channel: str = Field(min_length=1, max_length=32)
    rate_kg_ha: float = Field(gt=0, le=2000)


class SpeedCalCommand(_Command):
    """``cmd/speed_cal``: ``{"action": "start"}`` at the first marker, then
    ``{"action": "finish", "distance_m": 50}`` at the second (or ``"cancel"``)."""

    action: Literal["start", "finish", "cancel"]
    distance_m: float | None = Field(None, gt=0, le=10_000)


class AckAlarmCommand(_Command):
    """``cmd/ack_alarm``: ``{"code": "pwm.unavailable"}`` acknowledges that critical alarm;
    ``{}`` every critical alarm waiting (``state.unacknowledged``)."""

    code: str | None = Field(None, min_length=1, max_length=128)


class SeedLotCommand(_Command):
    """``cmd/seed_lot``: ``{"crop": "wheat", "lot": "2026-B"}`` makes that seed lot's
    rotation-test fits the ones applied for the crop, at once (``default``: the config's, or
    the rotation test saved without ``--seed-lot``). A lot without a rotation test of that
    crop is refused, naming the lots there are."""

    crop: str = Field(min_length=1, max_length=64)
    lot: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9_.-]+$")


class EmptyCommand(_Command):
    """``cmd/start``, ``cmd/stop``, ``cmd/zero_tilt``: an empty object (or empty payload)."""


class CommandAck(_Payload):
    """On ``cmd/<name>/ack``: ``{"ok": true, "message": "…"}`` or ``{"ok": false, "error": "…"}``.

    ``message`` is the executed command's result text, the confirmation a touchscreen command
    shows on the cab screen (e.g. a speed calibration's ``radar 48.7 m -> x1.0267``): without
    it a remote operator calibrating from the farm office never learns the factor. It is
    omitted when the command gave no text, so a bare ``{"ok": true}`` stays a valid ack;
    refused commands carry ``error`` instead.
    """

    ok: bool
    message: str | None = None
    error: str | None = None
    request_id: str | None = None

    def to_json(self) -> bytes:
        return self.model_dump_json(exclude_none=True).encode()


SCHEMA_MODELS: dict[str, type[BaseModel]] = {
    "status": StatusPayload,
    "state": StatePayload,
    "seed_batch": SeedBatch,
    "seed_record": SeedRecord,
    "alarm_event": AlarmEvent,
    "rate_command": RateCommand,
    "empty_command": EmptyCommand,
    "speed_cal_command": SpeedCalCommand,
    "channel_rate_command": ChannelRateCommand,
    "seed_lot_command": SeedLotCommand,
    "command_ack": CommandAck,
    "ack_alarm_command": AckAlarmCommand,
}


def render_schemas() -> dict[str, str]:
    """File name -> JSON Schema text, deterministic so the staleness test can compare."""
    out: dict[str, str] = {}
    for name, model in SCHEMA_MODELS.items():
        schema: dict[str, Any] = model.model_json_schema(mode="serialization")
        schema["$id"] = f"https://sowgate.invalid/schemas/{name}.json"
        out[f"{name}.json"] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return out


def write_schemas(directory: Path) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for fname, text in render_schemas().items():
        target = directory / fname
        target.write_text(text, encoding="utf-8")
        written.append(target)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gateway.link.payloads")
    parser.add_argument("--write", metavar="DIR", required=True, help="write JSON Schemas here")
    args = parser.parse_args(argv)
    for path in write_schemas(Path(args.write)):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
