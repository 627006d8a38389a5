"""Sections for paper A's machine: the RS485 bus, its devices, the HMI and the crop models."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    ConfigDict,
    Field,
    ModelWrapValidatorHandler,
    PrivateAttr,
    field_validator,
    model_validator,
)
from pydantic_settings import NoDecode

from gateway.config._base import FieldProblem, OptionalPart, Section, check_unique, source_chain
from gateway.core.monotone import MonotoneCurve
from protocol.registers import PWM_COMM_TIMEOUT_REGISTER

MAX_WORKING_SPEED_KMH = 40.0  # as speed.max_plausible_kmh's upper bound


class MachineSection(Section):
    id: str = Field("seeder-01", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    working_width_m: float = Field(2.0, gt=0, le=60)
    rows: int = Field(6, ge=1, le=128)
    # The ground speeds the machine sows at (km/h, lo..hi). At start a calibration that would
    # make a channel's command 0 or saturate (shaft above max_shaft_rpm, duty above 100 %) at
    # its configured rate anywhere in this range is refused (alarm calibration.refused).
    working_speed_kmh: tuple[float, float] = (4.0, 12.0)

    @field_validator("working_speed_kmh")
    @classmethod
    def _speed_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        lo, hi = value
        if not 0 < lo < hi <= MAX_WORKING_SPEED_KMH:
            raise ValueError(
                f"must be [lo, hi] km/h with 0 < lo < hi <= {MAX_WORKING_SPEED_KMH:g}"
            )
        return value


class Rs485Section(OptionalPart):
    # false: no RS485 bus at all (a paper-B drill: speed from GNSS/ISOBUS, work state from the
    # hitch, CAN metering); radar, inclinometer and the PWM module are then not used
    enabled: bool = True
    port: str = "/dev/ttyUSB0"
    baudrate: int = Field(9600, ge=1200, le=921600)
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    poll_hz: float = Field(3.0, gt=0, le=50)
    timeout_s: float = Field(0.3, gt=0, le=5)
    retries: int = Field(0, ge=0, le=5)
    reconnect_max_s: float = Field(5.0, gt=0, le=300)


DataType = Literal["uint16", "int16", "uint32", "int32", "float32"]


class RadarSection(Section):
    model_config = ConfigDict(validate_by_name=True, validate_by_alias=True)

    device_id: int = Field(1, ge=1, le=247)
    # `register` in the file; renamed here because pydantic models already have .register
    address: int = Field(0, ge=0, le=65535, alias="register")
    data_type: DataType = "uint16"
    word_order: Literal["big", "little"] = "big"
    scale: float = 0.01
    unit: Literal["km/h", "m/s", "mm/s", "doppler_hz"] = "km/h"
    mount_angle_deg: float = Field(49.5, ge=0, lt=90)
    filter_samples: int = Field(12, ge=2, le=256)
    # "mean": paper A's moving average; "trend": least-squares line, no lag when accelerating
    filter: Literal["mean", "trend"] = "trend"


class InclinometerSection(Section):
    device_id: int = Field(0x50, ge=1, le=247)
    axis: Literal["roll", "pitch"] = "pitch"
    layout: Literal["witmotion16", "witmotion32"] = "witmotion16"
    zero_offset_deg: float = Field(0.0, ge=-180, le=180)
    critical_angle_deg: float = Field(0.0, ge=-90, le=90)
    hysteresis_deg: float = Field(0.5, ge=0, le=10)


class ActuatorsSection(Section):
    device_id: int = Field(3, ge=1, le=247)
    motor_register: int = Field(0, ge=0, le=65535)
    fan_register: int = Field(1, ge=0, le=65535)
    refresh_s: float = Field(2.0, gt=0, le=2.0)
    # The module's communication-loss watchdog: with no request from sowgate for this long
    # it sets motor and fan to 0 by itself, the only way the motor stops when the bus is
    # gone (sowgate cannot write then). Written at start and after every loss of the module,
    # and read back; a module that refuses it raises the critical alarm pwm.no_watchdog.
    # Absent: 2 s. 0 (watchdog off) is refused: such a module must not drive the motor.
    # Keep it at 3 control periods (1/rs485.poll_hz) or more; sowgate refreshes the duties
    # at least every comm_timeout_s / 2.
    comm_timeout_s: float = Field(2.0, ge=0.5, le=60)
    comm_timeout_register: int = Field(PWM_COMM_TIMEOUT_REGISTER, ge=0, le=65535)

    @model_validator(mode="after")
    def _distinct_registers(self) -> ActuatorsSection:
        if self.motor_register == self.fan_register:
            raise FieldProblem(
                "fan_register", "must differ from motor_register", self.fan_register
            )
        if self.comm_timeout_register in (self.motor_register, self.fan_register):
            raise FieldProblem(
                "comm_timeout_register",
                "must differ from motor_register and fan_register",
                self.comm_timeout_register,
            )
        return self


class HopperScaleSection(OptionalPart):
    """A Modbus weight transmitter under the seed hopper, on the RS485 bus with the radar.

    It is read once per poll, with the radar and the inclinometer. While the drill sows
    steadily, the mass that left the hopper is compared with the mass the discharge model
    predicted, and the model is corrected by the factor found
    (``gateway.control.hopper_correction``). ``scale`` is grams per count of the raw value.
    """

    model_config = ConfigDict(validate_by_name=True, validate_by_alias=True)

    device_id: int = Field(4, ge=1, le=247)
    # `register` in the file, as for the radar
    address: int = Field(0, ge=0, le=65535, alias="register")
    # int32 (two holding registers) is the common weight-transmitter format
    data_type: Literal["int32", "uint16", "int16", "float32"] = "int32"
    word_order: Literal["big", "little"] = "big"  # big: high word first
    scale: float = Field(1.0, gt=0, le=1e6)  # grams per count
    # a reading outside -5 % .. 120 % of this is a transmitter fault, not a mass
    capacity_kg: float = Field(3000.0, gt=0, le=100000)
    # seconds of steady seeding per regression window (evidence is pooled across windows)
    window_s: float = Field(120.0, ge=5, le=3600)
    # the correction is kept within 1 +/- this (alarm hopper_scale.at_bound when it is held,
    # hopper_scale.out_of_range when the drill is found beyond it: it sows off target)
    max_correction_pct: float = Field(20.0, gt=0, le=50)
    # a window whose scale-measured factor is this far from the applied one (and beyond its
    # own noise) raises hopper_scale.disagrees
    disagree_pct: float = Field(10.0, gt=0, le=100)
    # hopper_scale.low below this mass (time to empty is in the state payload)
    warn_below_kg: float = Field(50.0, ge=0, le=100000)


class HmiObjects(Section):
    """TJC/Nextion object names the daemon writes to (``obj.txt="..."``)."""

    speed: str = "t_speed"
    tilt: str = "t_tilt"
    state: str = "t_state"
    crop: str = "t_crop"
    rate: str = "t_rate"
    alarm: str = "t_alarm"
    message: str = "t_msg"
    # written only when [hopper_scale] is on: hopper mass, time to empty, correction
    hopper: str = "t_hopper"
    # the active seed lot of the crop shown ("1 2026-B"); None (default): not shown, as a
    # screen page without such an object would answer every update with an error
    lot: str | None = None


class HmiSection(OptionalPart):
    enabled: bool = True
    port: str = "/dev/ttyS1"
    baudrate: int = Field(9600, ge=1200, le=921600)
    encoding: str = "ascii"
    update_hz: float = Field(2.0, ge=1.0, le=20.0)
    objects: HmiObjects = Field(default_factory=HmiObjects)
    state_labels: dict[str, str] = Field(default_factory=dict)
    crop_labels: dict[str, str] = Field(default_factory=dict)
    # a screen update waits at most this long for the UART before the caller moves on
    write_timeout_s: float = Field(0.5, gt=0, le=5.0)
    reconnect_max_s: float = Field(5.0, gt=0, le=300)

    @field_validator("encoding")
    @classmethod
    def _encoding_exists(cls, encoding: str) -> str:
        """A misspelt codec would otherwise only fail when the first text is sent."""
        import codecs

        try:
            codecs.lookup(encoding)
        except LookupError:
            raise ValueError(
                "unknown text encoding (e.g. ascii, utf-8, gb2312 for Chinese TJC fonts)"
            ) from None
        return encoding

    @model_validator(mode="after")
    def _screen_can_show_it(self) -> HmiSection:
        """Object names are sent unquoted and labels must exist in the screen's font encoding;
        both mistakes would otherwise only show up as a blank or garbled screen in the cab."""
        from protocol.hmi import check_object_name

        for key, obj in self.objects.model_dump().items():
            if obj is None:
                continue
            try:
                check_object_name(obj)
            except ValueError:
                raise FieldProblem(
                    f"objects.{key}", "not a screen object name (letters, digits, _)", obj
                ) from None
        for table in ("state_labels", "crop_labels"):
            for key, label in getattr(self, table).items():
                try:
                    label.encode(self.encoding)
                except UnicodeEncodeError:
                    raise FieldProblem(
                        f"{table}.{key}", f"cannot be shown in encoding {self.encoding!r}", label
                    ) from None
        return self


SpeedSourceName = Literal["radar", "gnss", "isobus", "agopengps"]


def _radar_only() -> list[SpeedSourceName]:
    return ["radar"]


class RadarScaleSection(Section):
    """Learning the radar's scale against an RTK-fixed GNSS (``gateway.control.radar_scale``):
    on straight passes at steady speed, GNSS / raw radar over ``window_s`` of such driving
    (restarted within seconds when the scale steps: another surface) replaces the radar's
    calibrated factor; ``radar.scale_drift`` while it is more than
    ``alarm_pct`` from that factor. Needs ``[gnss]``; without an RTK-fixed fix it learns
    nothing and the calibrated factor stays."""

    enabled: bool = True
    window_s: float = Field(180.0, ge=20, le=3600)  # seconds of fair comparison kept
    alarm_pct: float = Field(2.0, gt=0, le=20)
    min_speed_kmh: float = Field(2.0, gt=0, le=20)
    max_turn_deg_s: float = Field(2.0, gt=0, le=30)  # course change counted as straight
    steady_span: float = Field(0.05, gt=0, le=0.5)  # GNSS speed within ±this over 3 s


class SpeedSection(Section):
    # priority order, first fresh source wins: ["isobus", "gnss", "radar"], or as one string
    # "isobus_then_gnss_then_radar" ("radar", "radar_then_gnss", ... as before)
    source: Annotated[list[SpeedSourceName], NoDecode] = Field(
        default_factory=_radar_only, min_length=1
    )
    moving_threshold_kmh: float = Field(0.3, ge=0, le=5)
    moving_hysteresis_kmh: float = Field(0.1, ge=0, le=5)
    stale_after_s: float = Field(2.0, gt=0, le=30)
    # A reading above this is a sensor glitch (e.g. a radar's 0xFFFF = 655.35 km/h), not a
    # speed: it is dropped with an alarm instead of dragging the filter to full motor duty.
    max_plausible_kmh: float = Field(40.0, gt=0, le=100)
    # The fastest the machine can change speed, in m/s2. The radar's trend filter never
    # extrapolates a slope steeper than this, and a reading further from the filtered speed
    # than this allows (plus noise) restarts its window (gateway.control.speed.TrendFilter).
    # 1.5 m/s2 (5.4 km/h per second): a tractor pulling a drill pulls away at about 0.5-1 m/s2 (the
    # simulator drives at 0.6) and rarely brakes harder than 1.5 in the field; the radar
    # stepping from 0 to 8 km/h between two 3 Hz polls would be 6.7 m/s2. Raise it for a
    # light, quick machine; a value too low makes the filter lag real speed changes.
    max_accel_mps2: float = Field(1.5, ge=0.2, le=10)
    correction: dict[str, float] = Field(default_factory=dict)
    radar_scale: RadarScaleSection = Field(default_factory=RadarScaleSection)

    _chain = field_validator("source", mode="before")(source_chain)
    _unique = field_validator("source")(check_unique)


class CropModel(Section):
    """Paper A's fitted models for one crop; refit per machine with ``sowgate calibrate``."""

    code: int = Field(ge=1, le=255)
    rate_min_kg_ha: float = Field(gt=0)
    rate_max_kg_ha: float = Field(gt=0)
    default_rate_kg_ha: float = Field(gt=0)
    motor_slope: float = Field(gt=0)  # R = slope*K + intercept (r/min, K in %)
    motor_intercept: float
    startup_duty_pct: float = Field(ge=0, le=100)
    meter_a: float  # Q = a*w^2 + b*w + c (g/min, w in r/min)
    meter_b: float
    meter_c: float
    omega_min_rpm: float = Field(ge=0)
    omega_max_rpm: float = Field(gt=0)
    fan_high_pct: float = Field(ge=0, le=100)
    fan_low_pct: float = Field(ge=0, le=100)
    # The drill's own shape from a rotation test of >= 5 set points (issue 25): monotone
    # piecewise cubics through [r/min, g/min] and [duty %, r/min] points, used instead of
    # meter_a/b/c and motor_slope/intercept when given (calibration.json's rotation entry
    # sets them; a config may too). Both coordinates must rise strictly.
    meter_curve: list[tuple[float, float]] | None = None
    motor_curve: list[tuple[float, float]] | None = None

    @model_validator(mode="after")
    def _ranges(self) -> CropModel:
        for key in ("meter_curve", "motor_curve"):
            points = getattr(self, key)
            if points is None:
                continue
            if len(points) < 2:
                raise FieldProblem(key, "needs at least 2 [x, y] points", points)
            try:
                MonotoneCurve.through(points)
            except ValueError as exc:
                raise FieldProblem(key, str(exc), points) from None
        if self.rate_min_kg_ha >= self.rate_max_kg_ha:
            raise FieldProblem(
                "rate_max_kg_ha",
                f"must be above rate_min_kg_ha ({self.rate_min_kg_ha:g})",
                self.rate_max_kg_ha,
            )
        if not self.rate_min_kg_ha <= self.default_rate_kg_ha <= self.rate_max_kg_ha:
            raise FieldProblem(
                "default_rate_kg_ha",
                f"must lie within {self.rate_min_kg_ha:g}..{self.rate_max_kg_ha:g} "
                "(rate_min_kg_ha..rate_max_kg_ha)",
                self.default_rate_kg_ha,
            )
        if self.omega_min_rpm >= self.omega_max_rpm:
            raise FieldProblem(
                "omega_max_rpm",
                f"must be above omega_min_rpm ({self.omega_min_rpm:g})",
                self.omega_max_rpm,
            )
        return self


def default_crops() -> dict[str, CropModel]:
    """Paper A, equations (5) and (6), Table 2 ranges."""
    return {
        "rapeseed": CropModel(
            code=1,
            rate_min_kg_ha=4.5,
            rate_max_kg_ha=7.5,
            default_rate_kg_ha=6.0,
            motor_slope=0.5330,
            motor_intercept=-5.7088,
            startup_duty_pct=10.0,
            meter_a=-0.019,
            meter_b=5.468,
            meter_c=-1.419,
            omega_min_rpm=5.0,
            omega_max_rpm=30.0,
            fan_high_pct=70.0,
            fan_low_pct=20.0,
        ),
        "wheat": CropModel(
            code=2,
            rate_min_kg_ha=120.0,
            rate_max_kg_ha=225.0,
            default_rate_kg_ha=180.0,
            motor_slope=0.6671,
            motor_intercept=-19.8309,
            startup_duty_pct=30.0,
            meter_a=-0.644,
            meter_b=132.212,
            meter_c=-398.316,
            omega_min_rpm=20.0,
            omega_max_rpm=45.0,
            fan_high_pct=85.0,
            fan_low_pct=25.0,
        ),
    }


# the rotation test's scale, ± grams per weighing: from a jeweller's 0.01 g to a bathroom
# scale's 50 g (gateway.calibration.weighing names its usual steps; the config cannot import it)
SCALE_G_RANGE = (0.01, 50.0)


class CalibrationSection(Section):
    """What the rotation test's advice needs to know about the farm's own tools.

    ``scale_g``: the stated error of the scale the catches are weighed on (± grams, taken as
    one standard deviation). Set, the touchscreen's rotation test (F=09) runs each set point
    for the length that scale needs for the rate to land within 1 % (``gateway.calibration.
    weighing``: the catch predicted from the crop's model, then from that set point's own
    runs), and ``sowgate calibrate rotation --config`` takes it as its ``--scale-g``. Unset,
    every touchscreen run lasts ``control.rotation_test_s`` and the CLI assumes paper A's 2 g.
    """

    scale_g: float | None = None

    @field_validator("scale_g")
    @classmethod
    def _scale_in_range(cls, value: float | None) -> float | None:
        lo, hi = SCALE_G_RANGE
        if value is not None and not lo <= value <= hi:
            raise ValueError(
                f"the scale's error per weighing must be {lo:g}..{hi:g} g (± grams, one "
                "standard deviation)")
        return value


class ControlSection(Section):
    crop: str = "rapeseed"
    rate_kg_ha: float | None = None  # None -> the crop's default rate
    emptying_timeout_s: float = Field(120.0, gt=0, le=3600)
    emptying_motor_pct: float = Field(100.0, ge=0, le=100)
    start_working: bool = False  # start in the "work" mode without an HMI start press
    # one run of the rotation test started from the touchscreen (paper A weighs 60 s runs);
    # with [calibration] scale_g the shortest run, each set point running as long as it needs
    rotation_test_s: float = Field(60.0, ge=1, le=600)
    crops: dict[str, CropModel] = Field(default_factory=default_crops)
    # keys older versions accepted and that never did anything: key -> value in the file
    _ignored: dict[str, Any] = PrivateAttr(default_factory=dict)

    @model_validator(mode="wrap")
    @classmethod
    def _accept_old_loop_hz(
        cls, data: Any, handler: ModelWrapValidatorHandler[ControlSection]
    ) -> ControlSection:
        """``loop_hz`` was accepted but never used: the control loop ticks once per RS485 poll
        (``rs485.poll_hz``). A file that still has it loads, and the value is kept only so
        that ``Settings.deprecation_notes`` can tell the fitter it changes nothing."""
        old: dict[str, Any] = {}
        if isinstance(data, dict) and "loop_hz" in data:
            data = dict(data)
            old["loop_hz"] = data.pop("loop_hz")
        section = handler(data)
        if old:
            section._ignored = old
        return section

    @property
    def ignored_keys(self) -> dict[str, Any]:
        """Keys given in the file that this version ignores (see ``_accept_old_loop_hz``)."""
        return dict(self._ignored)

    @field_validator("crops", mode="before")
    @classmethod
    def _over_defaults(cls, value: Any) -> Any:
        """A ``[control.crops.wheat]`` table refits wheat: the keys it gives replace paper A's,
        the rest keep paper A's values, and rapeseed stays. Without this, refitting eq. (6)
        meant copying all 14 keys and silently dropped the crop not mentioned."""
        if not isinstance(value, dict):
            return value
        merged: dict[str, Any] = {name: m.model_dump() for name, m in default_crops().items()}
        for name, table in value.items():
            if isinstance(table, CropModel):
                table = table.model_dump()
            if isinstance(table, dict) and isinstance(merged.get(name), dict):
                merged[name] = {**merged[name], **table}
            else:
                merged[name] = table  # a new crop: every key is required
        return merged

    @model_validator(mode="after")
    def _crop_known(self) -> ControlSection:
        if self.crop not in self.crops:
            raise FieldProblem(
                "crop", f"not one of the crops in control.crops: {sorted(self.crops)}", self.crop
            )
        model = self.crops[self.crop]
        if self.rate_kg_ha is not None and not (
            model.rate_min_kg_ha <= self.rate_kg_ha <= model.rate_max_kg_ha
        ):
            raise FieldProblem(
                "rate_kg_ha",
                f"outside {self.crop} range {model.rate_min_kg_ha}..{model.rate_max_kg_ha} kg/ha",
                self.rate_kg_ha,
            )
        owner: dict[int, str] = {}
        for name, crop in self.crops.items():
            if crop.code in owner:
                raise FieldProblem(
                    f"crops.{name}.code",
                    f"crop codes must be unique; crops.{owner[crop.code]}.code has it too",
                    crop.code,
                )
            owner[crop.code] = name
        return self
