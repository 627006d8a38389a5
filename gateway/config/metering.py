"""Sections for paper B: metering channels on CAN, ISOBUS tractor inputs, prescriptions."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import NoDecode

from gateway.config._base import FieldProblem, OptionalPart, Section, check_unique, source_chain
from gateway.core.monotone import MonotoneCurve

# the most any product is sown or spread at (a channel's target, a prescription's rate): a
# map's 1e308 kg/ha is a broken export, not a rate
MAX_RATE_KG_HA = 2000.0


class CanSection(OptionalPart):
    enabled: bool = False
    interface: str = "socketcan"  # python-can interface: socketcan | virtual | ...
    channel: str = "can0"
    bitrate: int = Field(250_000, ge=10_000, le=1_000_000)
    command_hz: float = Field(10.0, ge=1, le=100)  # target-speed frames per node
    feedback_timeout_s: float = Field(1.0, gt=0, le=30)  # no status for longer -> channel alarm
    off_target_pct: float = Field(5.0, gt=0, le=100)  # |measured-target|/target above this ...
    off_target_s: float = Field(3.0, gt=0, le=60)  # ... for longer than this -> rate alarm
    min_target_rpm: float = Field(1.0, ge=0, le=100)  # below: channel commanded off (no alarm)


class ChannelSection(Section):
    name: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9_-]+$")
    product: str = "seed"
    target_rate_kg_ha: float = Field(gt=0, le=MAX_RATE_KG_HA)
    drive: Literal["pwm_modbus", "can_pid"] = "can_pid"
    node_id: int = Field(1, ge=0, le=15)  # CAN controller address
    grams_per_rev: float = Field(10.0, gt=0, le=10000)  # paper B per-revolution displacement
    max_shaft_rpm: float = Field(60.0, gt=0, le=1000)
    prescription_attribute: str | None = None
    outlets: int = Field(1, ge=1, le=128)  # m_total = grams_per_rev * outlets
    # g/rev as a function of shaft speed (issue 25): [r/min, g/rev per outlet] points from
    # paper B's runs at 10..60 r/min, used instead of grams_per_rev when given (a rotation
    # test at >= 5 speeds sets it); r/min rising and the delivered g/min (r/min x g/rev)
    # rising with it, else exit 78
    grams_per_rev_curve: list[tuple[float, float]] | None = None
    outlet_behind_m: float = Field(0.0, ge=-50, le=50)  # outlets behind the GNSS antenna
    outlet_lateral_m: float = Field(0.0, ge=-50, le=50)  # to the right of the antenna

    @model_validator(mode="after")
    def _can_node(self) -> ChannelSection:
        if self.grams_per_rev_curve is not None:
            pts = self.grams_per_rev_curve
            if len(pts) < 2 or any(n <= 0 or g <= 0 for n, g in pts):
                raise FieldProblem("grams_per_rev_curve",
                                   "needs at least 2 [r/min, g/rev] points, both above 0", pts)
            try:
                MonotoneCurve.through([(0.0, 0.0), *((n, n * g) for n, g in pts)])
            except ValueError as exc:
                raise FieldProblem("grams_per_rev_curve",
                                   f"as r/min -> g/min (r/min x g/rev): {exc}", pts) from None
        if self.drive == "can_pid" and not 1 <= self.node_id <= 15:
            raise FieldProblem(
                "node_id", "a can_pid channel needs node_id 1..15 (0 is not addressable)",
                self.node_id,
            )
        return self


SpeedSource = Literal["machine_selected", "ground", "wheel"]


def _default_priority() -> list[SpeedSource]:
    return ["machine_selected", "ground", "wheel"]


WorkStateSourceName = Literal["inclinometer", "hitch", "agopengps"]


def _inclinometer_only() -> list[WorkStateSourceName]:
    return ["inclinometer"]


class IsobusSection(OptionalPart):
    enabled: bool = False
    interface: str = "socketcan"
    channel: str = "can1"
    # priority order, first fresh source decides raised/working: ["hitch", "inclinometer"]
    # or "hitch_then_inclinometer"; none fresh -> raised (every channel stops)
    work_state_source: Annotated[list[WorkStateSourceName], NoDecode] = Field(
        default_factory=_inclinometer_only, min_length=1
    )
    hitch_in_work_below_pct: float | None = Field(None, ge=0, le=100)
    speed_priority: list[SpeedSource] = Field(default_factory=_default_priority, min_length=1)
    stale_after_s: float = Field(0.3, gt=0, le=5)  # ISO 11783-7 sends at 100 ms

    _chain = field_validator("work_state_source", mode="before")(source_chain)
    _unique = field_validator("work_state_source", "speed_priority")(check_unique)


class PrescriptionSection(OptionalPart):
    enabled: bool = False
    path: str | None = None
    lookahead_s: float = Field(1.0, ge=0, le=30)
    as_applied_path: str | None = None  # CSV/GeoJSON log of applied rates; None -> state dir
