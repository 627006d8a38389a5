"""The controller: sensor samples and operator commands in, motor and fan duty out.

Pure state plus arithmetic: the caller supplies timestamps (``now`` from a monotonic clock),
so every safety rule here — stale speed, lost inclinometer, emptying timeout — is tested by
moving a number, not by sleeping. The daemon polls the bus and calls ``tick``.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from gateway.calibration import fits as cal
from gateway.config import ChannelSection, CropModel, Settings
from gateway.control.attitude import Attitude as AttitudeBand
from gateway.control.attitude import zeroed_tilt
from gateway.control.hopper_loop import HopperLoop
from gateway.control.radar_scale import RadarScaleLearner, RadarScaleSettings
from gateway.control.rate_model import flow_at, omega_for_duty, plan_duty, rate_for_flow
from gateway.control.speed import Hysteresis, MovingAverage, TrendFilter
from gateway.control.work_state import (
    Attitude,
    Fan,
    Mode,
    ModeEvent,
    Motion,
    Motor,
    WorkState,
    decide,
    next_mode,
)
from gateway.core import commands as cmd
from gateway.core.alarms import AlarmBoard
from gateway.core.errors import CommandError, OutsideCalibrationError, TooFastError
from gateway.core.records import AlarmSeverity

log = logging.getLogger(__name__)

TILT_STALE_S = 2.0
LOWERED_READINGS = 3  # paper B averages 3 readings for the critical angle
CRITICAL_READINGS_WITHIN_S = 5.0  # ... taken together, not one stale and two new
WORK_STATE_SOURCES = ("inclinometer", "hitch", "agopengps")
WORK_STATE_LABEL = {
    "inclinometer": "inclinometer",
    "hitch": "ISOBUS rear hitch status",
    "agopengps": "AgOpenGPS sections/lift",
}
OTHER_SOURCE_FILTER_SAMPLES = 5
# ``rate.outside_calibration`` is raised only once the needed shaft speed has been outside the
# crop model's fitted range this long (as DEVICE_LOST_AFTER_S for a silent device): every
# pull-away from standstill crosses the low end of the range in about a second, and a start-up
# ramp is not a fault. It clears at the first tick back in range.
OUTSIDE_CALIBRATION_HOLD_S = 2.0


@dataclass
class SpeedSource:
    """Latest filtered reading of one speed source and when it arrived."""

    filter: MovingAverage | TrendFilter
    correction: float = 1.0
    last_t: float | None = None
    last_raw: float = 0.0
    raw_distance_m: float = 0.0  # uncorrected odometer, for speed calibration

    def add(self, kmh: float, t: float, stale_after_s: float = 2.0) -> None:
        raw = max(0.0, kmh)
        if self.last_t is not None and 0.0 < t - self.last_t <= stale_after_s:
            self.raw_distance_m += (self.last_raw + raw) / 2.0 / 3.6 * (t - self.last_t)
        self.filter.add(raw * self.correction, t)
        self.last_t = t
        self.last_raw = raw

    def dropped_glitch(self) -> None:
        """A reading was dropped as implausible: the trend line is not fitted across the hole
        (paper A's plain mean, ``filter = "mean"``, keeps its samples as the paper does)."""
        if isinstance(self.filter, TrendFilter):
            self.filter.reset()

    def value(self, now: float, stale_after_s: float) -> float | None:
        if self.last_t is None or now - self.last_t > stale_after_s:
            return None
        return self.filter.value


def pwm_channel(settings: Settings) -> ChannelSection | None:
    """The ``pwm_modbus`` channel (paper A's motor on the RS485 PWM module), if declared."""
    return next((c for c in settings.channel if c.drive == "pwm_modbus"), None)


@dataclass
class ControlOutputs:
    state: WorkState
    motor_pct: float
    fan_pct: float
    speed_kmh: float | None
    speed_source: str | None
    tilt_deg: float | None
    raised: bool
    commanded_rate_kg_ha: float
    message: str | None = None
    target_rate_kg_ha: float | None = None  # the rate aimed at this tick (map or operator)


@dataclass
class Counters:
    area_m2: float = 0.0
    seed_mass_g: float = 0.0
    distance_m: float = 0.0


@dataclass
class Controller:
    settings: Settings
    alarms: AlarmBoard
    # where live calibrations (speed, tilt) are kept; None: applied, not kept (tests, bench)
    calibrations: cal.CalibrationStore | None = None
    mode: Mode = Mode.STOPPED
    counters: Counters = field(default_factory=Counters)
    seed_level_monitoring: bool = False
    # the rate to aim at now (a prescription map under the outlets), None -> the operator's
    rate_provider: Callable[[], float | None] | None = None

    def __post_init__(self) -> None:
        s = self.settings
        self.crop = s.control.crop
        model = s.control.crops[self.crop]
        self.rate_kg_ha = s.control.rate_kg_ha or model.default_rate_kg_ha
        pwm = pwm_channel(s)
        if pwm is not None:  # a declared pwm_modbus channel sets paper A's crop and rate
            self.crop, self.rate_kg_ha = pwm.product, pwm.target_rate_kg_ha
        self.zero_offset_deg = s.inclinometer.zero_offset_deg
        corr = s.speed.correction
        radar_filter: MovingAverage | TrendFilter = (
            TrendFilter(
                s.radar.filter_samples,
                max_accel_mps2=s.speed.max_accel_mps2,
                restart_after_s=s.speed.stale_after_s,
            )
            if s.radar.filter == "trend"
            else MovingAverage(s.radar.filter_samples)
        )
        self.sources: dict[str, SpeedSource] = {
            "radar": SpeedSource(radar_filter, corr.get("radar", 1.0)),
            "gnss": SpeedSource(MovingAverage(OTHER_SOURCE_FILTER_SAMPLES), corr.get("gnss", 1.0)),
            "isobus": SpeedSource(
                MovingAverage(OTHER_SOURCE_FILTER_SAMPLES), corr.get("isobus", 1.0)
            ),
            "agopengps": SpeedSource(
                MovingAverage(OTHER_SOURCE_FILTER_SAMPLES), corr.get("agopengps", 1.0)
            ),
        }
        # the radar's scale learnt against an RTK-fixed GNSS (issue 25), with a GNSS only
        rs = s.speed.radar_scale
        self.radar_scale: RadarScaleLearner | None = None
        if rs.enabled and s.gnss.enabled and "radar" in s.speed.source:
            self.radar_scale = RadarScaleLearner(
                RadarScaleSettings(rs.window_s, rs.alarm_pct, rs.min_speed_kmh,
                                   rs.max_turn_deg_s, rs.steady_span),
                calibrated=corr.get("radar", 1.0))
        thr, hyst = s.speed.moving_threshold_kmh, s.speed.moving_hysteresis_kmh
        self._moving = Hysteresis(thr + hyst, thr, initial=False)
        self._attitude = AttitudeBand(
            s.inclinometer.critical_angle_deg, s.inclinometer.hysteresis_deg
        )
        self._band = (s.inclinometer.zero_offset_deg, s.inclinometer.critical_angle_deg)
        self._odometer_start: dict[str, float] | None = None
        self._implausible_t: dict[str, float] = {}  # source -> last implausible sample
        self._tilt_raw: float | None = None
        self._tilt_t: float | None = None
        self._tilt_recent: deque[tuple[float, float]] = deque(maxlen=LOWERED_READINGS)
        self._hitch_working: bool | None = None
        self._hitch_t: float | None = None
        self._aog_working: bool | None = None
        self._aog_t: float | None = None
        self._speed_lost_since: float | None = None
        self._emptying_since: float | None = None
        self._outside_since: float | None = None  # first tick of the current outside spell
        self._last_tick: float | None = None
        self._message: str | None = None
        self.last: ControlOutputs | None = None
        # the hopper scale's correction of the discharge model (true / model), if fitted
        self.hopper: HopperLoop | None = None
        if s.hopper_scale.enabled:
            self.hopper = HopperLoop(s.hopper_scale, self.alarms, self.crop,
                                     calibrations=self.calibrations,
                                     rotation_keys=self._rotation_keys(self.crop))
        if s.control.start_working:  # the operator's start, given at power-up
            self._change_mode(ModeEvent.START)

    def _rotation_keys(self, crop: str) -> list[str]:
        """calibration.json keys of the rotation test that fits ``crop`` (a pwm_modbus
        channel's test is stored under the channel's name)."""
        return [f"rotation.{c.name}" for c in self.settings.channel
                if c.drive == "pwm_modbus" and c.product == crop]

    @property
    def discharge_correction(self) -> float:
        """true / model discharge: 1.0 without a hopper scale or before it has evidence."""
        return 1.0 if self.hopper is None else self.hopper.factor

    # ---- inputs -------------------------------------------------------------------------
    @property
    def crop_model(self) -> CropModel:
        return self.settings.control.crops[self.crop]

    def on_speed(self, source: str, kmh: float, t: float) -> bool:
        """Take one speed sample; False (and an alarm) if it is not a possible ground speed.

        One glitch sample of 655 km/h would otherwise hold the 12-sample filter far above the
        real speed for 4 s: motor at 100 % and a phantom "too fast" alarm, then a swing to 0.
        A source that only sends such values goes stale and metering stops as for a lost one.
        """
        speed = self.settings.speed
        code = f"{source}.implausible"
        if not kmh <= speed.max_plausible_kmh:  # also catches NaN
            if not self.alarms.is_active(code):
                log.warning(
                    "%s reported %.2f km/h, above speed.max_plausible_kmh %g: sample ignored",
                    source, kmh, speed.max_plausible_kmh,
                )
            self._implausible_t[source] = t
            self.sources[source].dropped_glitch()
            self.alarms.raise_(
                code,
                f"{source} speed readings above {speed.max_plausible_kmh:g} km/h ignored",
            )
            return False
        last_bad = self._implausible_t.get(source)
        if last_bad is not None and t - last_bad >= speed.stale_after_s:
            del self._implausible_t[source]
            self.alarms.clear(code)
        if source == "radar" and self.radar_scale is not None:
            self._learn_radar_scale(kmh, t)
        self.sources[source].add(kmh, t, speed.stale_after_s)
        return True

    def on_gnss_epoch(self, t: float, fix: str, speed_kmh: float | None,
                      course_deg: float | None) -> None:
        """Each GNSS epoch (any fix): what the radar's scale is learnt against."""
        if self.radar_scale is not None:
            self.radar_scale.on_gnss(t, fix, speed_kmh, course_deg)

    def _learn_radar_scale(self, raw_kmh: float, t: float) -> None:
        learner = self.radar_scale
        assert learner is not None
        learner.on_radar(t, raw_kmh)
        scale = learner.scale
        if scale is None:
            return
        self.sources["radar"].correction = scale  # the corrected speed is what is sown on
        drift = learner.drift_pct() or 0.0
        self.alarms.set(
            "radar.scale_drift", learner.drifted(),
            f"radar reads {-drift:+.1f} % against the RTK GNSS since its calibration "
            f"(x{learner.calibrated:.4f} -> x{scale:.4f}, learnt on straight passes and "
            "used): the surface or the mounting changed; check the radar's mounting",
            "warning")

    def on_tilt(self, raw_deg: float, t: float) -> None:
        self._tilt_raw = raw_deg
        self._tilt_t = t
        self._tilt_recent.append((t, raw_deg))

    def on_hopper_weight(self, kg: float | None, t: float) -> None:
        """One hopper scale reading (None: the scale did not answer this poll)."""
        if self.hopper is not None:
            self.hopper.on_weight(kg, t)

    def on_hitch(self, in_work: bool, t: float) -> None:
        """ISOBUS rear hitch in-work flag, an alternative attitude source."""
        self._hitch_working = in_work
        self._hitch_t = t

    def on_agopengps_work(self, working: bool, t: float) -> None:
        """AgOpenGPS's verdict: some section on and the lift not up (``gateway.app.agopengps``)."""
        self._aog_working = working
        self._aog_t = t

    def stale_after_s(self, source: str) -> float:
        """How long a source's last value counts; ISOBUS keeps the standard's 300 ms."""
        s = self.settings
        if source == "isobus":
            return min(s.speed.stale_after_s, s.isobus.stale_after_s)
        if source == "agopengps":  # AgOpenGPS sends at its GNSS rate; gone after 4 s (RC)
            return s.agopengps.stale_after_s
        return s.speed.stale_after_s

    def speed(self, now: float) -> tuple[float | None, str | None]:
        """The first fresh source in ``[speed] source`` priority order."""
        for name in self.settings.speed.source:
            v = self.sources[name].value(now, self.stale_after_s(name))
            if v is not None:
                return v, name
        return None, None

    def tilt(self, now: float) -> float | None:
        if self._tilt_raw is None or self._tilt_t is None or now - self._tilt_t > TILT_STALE_S:
            return None
        return zeroed_tilt(self._tilt_raw, self.zero_offset_deg)

    def recalibrated(self) -> None:
        """Take the speed corrections and the inclinometer's zero and critical angle from the
        settings again: a calibration saved while running (``gateway.app.live_calibration``).
        The crop models are read from the settings at every tick already."""
        s = self.settings
        for name, source in self.sources.items():
            source.correction = s.speed.correction.get(name, 1.0)
        if self.radar_scale is not None:  # a new speed calibration: the drift is from it
            self.radar_scale.calibrated = s.speed.correction.get("radar", 1.0)
            if self.radar_scale.scale is not None:
                self.sources["radar"].correction = self.radar_scale.scale
        incl = s.inclinometer
        band = (incl.zero_offset_deg, incl.critical_angle_deg)
        if band != self._band:
            self._band = band
            self.zero_offset_deg = incl.zero_offset_deg
            self._attitude = AttitudeBand(incl.critical_angle_deg, incl.hysteresis_deg)

    # ---- commands (the one path for HMI and MQTT) ----------------------------------------
    def execute(self, command: cmd.Command, source: str) -> str:
        match command:
            case cmd.SetRate(crop=crop, rate_kg_ha=rate):
                crops = self.settings.control.crops
                if crop not in crops:
                    raise CommandError(f"unknown crop {crop!r}; known: {', '.join(sorted(crops))}")
                m = crops[crop]
                if not m.rate_min_kg_ha <= rate <= m.rate_max_kg_ha:
                    raise CommandError(
                        f"{crop} rate {rate:g} kg/ha outside "
                        f"{m.rate_min_kg_ha:g}-{m.rate_max_kg_ha:g} kg/ha"
                    )
                self.crop, self.rate_kg_ha = crop, rate
                if self.hopper is not None:
                    self.hopper.set_crop(crop, self._rotation_keys(crop))
                reply = f"{crop} {rate:g} kg/ha"
            case cmd.Start():
                self._change_mode(ModeEvent.START)
                reply = "work started"
            case cmd.Stop():
                self._change_mode(ModeEvent.STOP)
                reply = "stopped"
            case cmd.EmptySeed():
                moving = bool(self._moving.state)  # None (no valid speed) is not moving here
                self._change_mode(ModeEvent.EMPTY_WHILE_MOVING if moving else ModeEvent.EMPTY)
                reply = "emptying residual seed"
            case cmd.SeedLevelMonitoring(enabled=on):
                self.seed_level_monitoring = on
                reply = f"seed-level monitoring {'on' if on else 'off'}"
            case cmd.CriticalTilt():
                reply = self._calibrate_critical(source)
            case cmd.CalibrateSpeed(action=action, distance_m=distance):
                reply = self._calibrate_speed(action, distance)
            case cmd.ZeroTilt():
                if self._tilt_raw is None:
                    raise CommandError("cannot zero: no inclinometer reading")
                self.zero_offset_deg = self._tilt_raw
                self._attitude.forget()
                critical_raw = self._save_zero()
                if critical_raw is not None:
                    # a stored (paper B) critical angle is a raw reading: keep it where it
                    # was on the sensor, as the next start-up will (see calibration_apply)
                    self._attitude = AttitudeBand(
                        zeroed_tilt(critical_raw, self.zero_offset_deg),
                        self.settings.inclinometer.hysteresis_deg,
                    )
                reply = f"tilt zeroed at raw {self._tilt_raw:.2f} deg"
            case cmd.AckAlarm(code=code):
                reply = self.alarms.acknowledge(code)
            case _:
                raise CommandError(f"unsupported command {command!r}")
        log.info("command from %s: %s", source, reply)
        self._message = reply
        return reply

    def _calibrate_speed(self, action: str, distance_m: float | None) -> str:
        if action == "start":
            self._odometer_start = {n: s.raw_distance_m for n, s in self.sources.items()}
            return "speed calibration started: drive the measured distance, then finish"
        if action == "cancel":
            self._odometer_start = None
            return "speed calibration cancelled"
        if action != "finish":
            raise CommandError(f"unknown speed calibration action {action!r}")
        if self._odometer_start is None:
            raise CommandError("speed calibration was not started")
        if distance_m is None:
            raise CommandError("finish needs the measured distance_m")
        results = []
        for name, source in self.sources.items():
            integrated = source.raw_distance_m - self._odometer_start[name]
            if integrated <= 0.0:
                continue  # this source did not report during the run
            try:
                res = cal.speed_correction(name, distance_m, integrated)
            except cal.CalibrationError as exc:
                raise CommandError(str(exc)) from None
            results.append(res)
        if not results:
            raise CommandError("no speed source reported any distance during the run")
        if self.calibrations is not None:
            for res in results:
                self.calibrations.save(f"speed.{res.source}", cal.to_entry(res, source="live"))
        for res in results:
            self.sources[res.source].correction = res.factor
        self._odometer_start = None
        return "; ".join(
            f"{r.source} {r.integrated_m:.1f} m -> x{r.factor:.4f}" for r in results
        )

    def _calibrate_critical(self, source: str) -> str:
        """Paper B: implement lowered to the ground, mean of the last 3 readings."""
        recent = list(self._tilt_recent)
        newest = recent[-1][0] if recent else None
        if (
            len(recent) < LOWERED_READINGS
            or newest is None
            or (self._last_tick is not None and self._last_tick - newest > TILT_STALE_S)
            or newest - recent[0][0] > CRITICAL_READINGS_WITHIN_S
        ):
            raise CommandError(
                f"need {LOWERED_READINGS} fresh inclinometer readings: lower the implement to "
                "the ground, wait a moment and try again"
            )
        try:
            result = cal.tilt_lowered_critical([raw for _, raw in recent])
        except cal.CalibrationError as exc:
            raise CommandError(str(exc)) from None
        critical_raw = result.critical_angle_deg
        assert critical_raw is not None
        if self.calibrations is not None:
            try:
                cal.save_tilt(
                    self.calibrations, "tilt.inclinometer", result,
                    source=source,
                )
            except (cal.CalibrationError, OSError) as exc:
                raise CommandError(f"critical angle not saved: {exc}") from exc
        critical = zeroed_tilt(critical_raw, self.zero_offset_deg)
        self._attitude = AttitudeBand(critical, self.settings.inclinometer.hysteresis_deg)
        return f"critical angle {critical:+.2f} deg (raw {critical_raw:+.2f}): below -> working"

    def _save_zero(self) -> float | None:
        """Persist as a paper-A level-ground calibration, with undo like any other.

        Returns the stored raw critical angle, if a lowered-critical calibration exists.
        """
        if self.calibrations is None:
            return None
        result = cal.tilt_level_zero([self.zero_offset_deg])
        try:
            entry = cal.save_tilt(self.calibrations, "tilt.inclinometer", result, source="hmi")
        except (cal.CalibrationError, OSError) as exc:
            raise CommandError(f"zeroed, but could not be saved: {exc}") from exc
        critical = entry["result"].get("critical_angle_deg")
        return None if critical is None else float(critical)

    # ---- the control step ----------------------------------------------------------------
    def _attitude_now(self, now: float) -> tuple[Attitude, float | None]:
        """Raised or working from the first fresh source in ``isobus.work_state_source``.

        The inclinometer's band is kept up to date whenever it reads, so falling back to it
        starts from its real state. No fresh source at all -> raised (every meter stops).
        """
        tilt = self.tilt(now)
        if tilt is None:
            self._attitude.forget()
            incl_raised = None
        else:
            incl_raised = self._attitude.update(tilt)
        hitch_fresh = (
            self._hitch_t is not None
            and self._hitch_working is not None
            and now - self._hitch_t <= self.settings.isobus.stale_after_s
        )
        aog_fresh = (
            self._aog_t is not None
            and self._aog_working is not None
            and now - self._aog_t <= self.settings.agopengps.stale_after_s
        )
        verdicts = {
            "inclinometer": incl_raised,
            "hitch": (not self._hitch_working) if hitch_fresh else None,
            "agopengps": (not self._aog_working) if aog_fresh else None,
        }
        order = self.settings.isobus.work_state_source
        chosen = next((src for src in order if verdicts[src] is not None), None)
        for src in WORK_STATE_SOURCES:
            lost = src in order and verdicts[src] is None
            sev: AlarmSeverity
            if chosen is None:
                msg, sev = f"{WORK_STATE_LABEL[src]} lost: treated as raised", "critical"
            else:
                msg, sev = f"{WORK_STATE_LABEL[src]} lost: work state from {chosen}", "warning"
            self.alarms.set(f"{src}.lost", lost, msg, sev)
        if chosen is None:
            return Attitude.RAISED, tilt
        return (Attitude.RAISED if verdicts[chosen] else Attitude.LOWERED), tilt

    def tick(self, now: float) -> ControlOutputs:
        dt = 0.0 if self._last_tick is None else max(0.0, now - self._last_tick)
        self._last_tick = now
        speed, source = self.speed(now)
        if speed is None:
            motion = Motion.UNKNOWN
            self._moving.state = None
            if self._speed_lost_since is None:
                self._speed_lost_since = now
        else:
            self._speed_lost_since = None
            motion = Motion.MOVING if self._moving.update(speed) else Motion.STANDING
        lost_for = 0.0 if self._speed_lost_since is None else now - self._speed_lost_since
        self.alarms.set(
            "speed.lost",
            speed is None and self.mode is Mode.WORKING and lost_for >= 0.0,
            "no valid ground speed: metering stopped",
            "critical",
        )
        attitude, tilt = self._attitude_now(now)

        self._machine_mode_events(motion, now)

        out = decide(self.mode, motion, attitude)
        model = self.crop_model
        target_rate = self.rate_kg_ha
        if self.rate_provider is not None:
            prescribed = self.rate_provider()
            if prescribed is not None:
                target_rate = prescribed
        motor = 0.0
        commanded_rate = 0.0
        too_fast = outside = False
        k = self.discharge_correction  # the model delivers Q/k where the drill delivers Q
        q_model = 0.0  # what the uncorrected model predicts at the duty commanded
        if out.motor is Motor.FOLLOW and speed is not None:
            plan = plan_duty(target_rate / k, self.settings.machine.working_width_m, speed, model)
            motor = plan.duty_pct
            too_fast = isinstance(plan.problem, TooFastError)
            outside = isinstance(plan.problem, OutsideCalibrationError)
            if too_fast:
                self.alarms.raise_("rate.too_fast", str(plan.problem))
            elif outside:
                self._outside_calibration(now, str(plan.problem))
            self.alarms.set("rate.low_duty", plan.warning is not None, plan.warning or "", "info")
            q_model = flow_at(omega_for_duty(motor, model), model) if motor > 0 else 0.0
            q = q_model * k
            commanded_rate = rate_for_flow(q, self.settings.machine.working_width_m, speed)
            self.counters.seed_mass_g += max(0.0, q) * dt / 60.0
            self.counters.area_m2 += self.settings.machine.working_width_m * speed / 3.6 * dt
        elif out.motor is Motor.EMPTY:
            motor = self.settings.control.emptying_motor_pct
        if not too_fast:
            self.alarms.clear("rate.too_fast")
        if not outside:
            self._outside_since = None
            self.alarms.clear("rate.outside_calibration")
        if out.motor is not Motor.FOLLOW:
            self.alarms.clear("rate.low_duty")
        if speed is not None:
            self.counters.distance_m += speed / 3.6 * dt
        if self.hopper is not None:
            self.hopper.tick(now, q_model_g_min=q_model, seeding=out.state is WorkState.SEEDING
                             and out.motor is Motor.FOLLOW and motor > 0, speed_kmh=speed,
                             modelled=out.motor is not Motor.EMPTY)
        fan = {Fan.OFF: 0.0, Fan.LOW: model.fan_low_pct, Fan.HIGH: model.fan_high_pct}[out.fan]
        self.last = ControlOutputs(
            state=out.state,
            motor_pct=motor,
            fan_pct=fan,
            speed_kmh=speed,
            speed_source=source,
            tilt_deg=tilt,
            raised=attitude is Attitude.RAISED,
            commanded_rate_kg_ha=commanded_rate,
            message=self._message,
            target_rate_kg_ha=target_rate,
        )
        return self.last

    def _change_mode(self, event: ModeEvent) -> bool:
        """Apply ``event`` through the work-state module's mode table; True if the mode changed.

        A refused request raises ``CommandError`` and changes nothing. The emptying clock
        belongs to one emptying job: every EMPTY starts a new one (its clock starts at the
        next tick) and outside emptying there is none.
        """
        then = next_mode(self.mode, event)
        changed = then is not self.mode
        if then is not Mode.EMPTYING or event is ModeEvent.EMPTY:
            self._emptying_since = None
        self.mode = then
        return changed

    def _machine_mode_events(self, motion: Motion, now: float) -> None:
        """Tell the mode table what the machine did this tick: it may end an emptying."""
        if self.mode is Mode.EMPTYING and self._emptying_since is None:
            self._emptying_since = now
        if motion is not Motion.STANDING:
            event, message = ModeEvent.NOT_STANDING, "emptying ended: machine moving"
        elif (
            self._emptying_since is not None
            and now - self._emptying_since >= self.settings.control.emptying_timeout_s
        ):
            event, message = ModeEvent.EMPTYING_TIMED_OUT, "emptying finished (timeout)"
        else:
            return
        if self._change_mode(event):
            self._message = message

    def _outside_calibration(self, now: float, message: str) -> None:
        """Raise ``rate.outside_calibration`` once the spell has lasted
        ``OUTSIDE_CALIBRATION_HOLD_S``: a pull-away passes through the range's low end."""
        if self._outside_since is None:
            self._outside_since = now
        if now - self._outside_since >= OUTSIDE_CALIBRATION_HOLD_S:
            self.alarms.raise_("rate.outside_calibration", message)

    def take_message(self) -> str | None:
        msg, self._message = self._message, None
        return msg
