"""The seeder and tractor as physics, with ground truth kept for every accuracy check.

Two parts, both driven by simulated time so tests and benchmarks are repeatable:

* ``Drive`` — where the tractor is: a time-parameterised path (legs of constant target speed
  and yaw rate, with finite acceleration), local ENU metres, heading clockwise from north,
  implement raised or lowered per leg. ``pose_at(t)`` answers for any t by interpolation.
* ``MeteringPlant`` — paper A's metering drive: duty → shaft speed through eq. (5) with the
  start-up dead band and a first-order lag, shaft speed → discharge through eq. (6) with slowly
  varying noise; it integrates the mass really applied and the distance really travelled.

Sensors (radar, inclinometer) are noisy views of the true state: ``radar_kmh`` and ``tilt_deg``.
"""

from __future__ import annotations

import bisect
import math
import random
from dataclasses import dataclass, field

KMH_PER_MS = 3.6
RAISED_TILT_DEG = 8.75  # paper A, Table 5: hitch raised
LOWERED_TILT_DEG = -6.25  # paper A, Table 5: working ("far below 0")
TILT_SWING_S = 1.5  # time the hitch needs to travel between the two
MAX_SHAFT_RPM = 50.0  # paper A: motor speed range 0-50 r/min


@dataclass(frozen=True)
class Pose:
    """True state of the main GNSS antenna / tractor reference point at one instant."""

    t: float
    east: float
    north: float
    heading_deg: float  # clockwise from north
    speed_kmh: float
    raised: bool
    tilt_deg: float  # true implement angle to the seedbed


@dataclass(frozen=True)
class Leg:
    """One part of a drive: hold a target speed and yaw rate for a while."""

    duration_s: float
    speed_kmh: float
    yaw_rate_dps: float = 0.0
    raised: bool = False


@dataclass
class Drive:
    """A precomputed path sampled every ``dt``; poses between samples are interpolated."""

    legs: list[Leg]
    accel_ms2: float = 0.6
    dt: float = 0.01
    start_heading_deg: float = 0.0
    _t: list[float] = field(default_factory=list, init=False, repr=False)
    _rows: list[tuple[float, float, float, float, bool, float]] = field(
        default_factory=list, init=False, repr=False
    )

    def __post_init__(self) -> None:
        t = 0.0
        e = n = 0.0
        v = 0.0  # m/s
        hdg = self.start_heading_deg
        tilt = LOWERED_TILT_DEG if not self.legs or not self.legs[0].raised else RAISED_TILT_DEG
        tilt_rate = (RAISED_TILT_DEG - LOWERED_TILT_DEG) / TILT_SWING_S
        self._t.append(t)
        self._rows.append((e, n, hdg, v, bool(self.legs and self.legs[0].raised), tilt))
        for leg in self.legs:
            steps = max(1, round(leg.duration_s / self.dt))
            target_v = leg.speed_kmh / KMH_PER_MS
            target_tilt = RAISED_TILT_DEG if leg.raised else LOWERED_TILT_DEG
            for _ in range(steps):
                dv = target_v - v
                v += max(-self.accel_ms2 * self.dt, min(self.accel_ms2 * self.dt, dv))
                hdg = (hdg + leg.yaw_rate_dps * self.dt) % 360.0
                rad = math.radians(hdg)
                e += v * math.sin(rad) * self.dt
                n += v * math.cos(rad) * self.dt
                dtilt = target_tilt - tilt
                tilt += max(-tilt_rate * self.dt, min(tilt_rate * self.dt, dtilt))
                t += self.dt
                self._t.append(t)
                self._rows.append((e, n, hdg, v, leg.raised, tilt))

    @property
    def duration_s(self) -> float:
        return self._t[-1]

    def pose_at(self, t: float) -> Pose:
        t = min(max(t, 0.0), self._t[-1])
        i = min(bisect.bisect_right(self._t, t), len(self._t) - 1)
        i0 = max(i - 1, 0)
        t0, t1 = self._t[i0], self._t[i]
        a = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        e0, n0, h0, v0, r0, g0 = self._rows[i0]
        e1, n1, h1, v1, _r1, g1 = self._rows[i]
        dh = ((h1 - h0 + 540.0) % 360.0) - 180.0
        return Pose(
            t=t,
            east=e0 + a * (e1 - e0),
            north=n0 + a * (n1 - n0),
            heading_deg=(h0 + a * dh) % 360.0,
            speed_kmh=(v0 + a * (v1 - v0)) * KMH_PER_MS,
            raised=r0,
            tilt_deg=g0 + a * (g1 - g0),
        )

    def distance_between(self, t0: float, t1: float, step: float = 0.05) -> float:
        """Path length travelled between two instants (ground truth for rate checks)."""
        total = 0.0
        t = t0
        prev = self.pose_at(t)
        while t < t1:
            t = min(t + step, t1)
            cur = self.pose_at(t)
            total += math.hypot(cur.east - prev.east, cur.north - prev.north)
            prev = cur
        return total


def gear_run(speed_kmh: float, distance_m: float = 50.0, lead_in_s: float = 8.0) -> Drive:
    """Paper A's Fig. 19 setting: stand lowered, accelerate, sow a measured distance, stop."""
    run_s = distance_m / (speed_kmh / KMH_PER_MS)
    return Drive(
        legs=[
            Leg(3.0, 0.0, raised=False),
            Leg(lead_in_s + run_s, speed_kmh),
            Leg(4.0, 0.0),
        ]
    )


def field_passes(
    speeds_kmh: tuple[float, ...] = (4.0, 6.0, 8.0, 10.0, 12.0),
    pass_length_m: float = 60.0,
    turn_radius_m: float = 4.0,
    turn_speed_kmh: float = 5.0,
) -> Drive:
    """Back-and-forth passes at several speeds with raised headland U-turns between them."""
    legs: list[Leg] = [Leg(2.0, 0.0, raised=False)]
    turn_v = turn_speed_kmh / KMH_PER_MS
    turn_s = math.pi * turn_radius_m / turn_v
    yaw = 180.0 / turn_s
    for i, v in enumerate(speeds_kmh):
        legs.append(Leg(pass_length_m / (v / KMH_PER_MS), v))
        if i < len(speeds_kmh) - 1:
            direction = 1.0 if i % 2 == 0 else -1.0
            legs.append(Leg(turn_s, turn_speed_kmh, yaw_rate_dps=direction * yaw, raised=True))
    legs.append(Leg(4.0, 0.0))
    return Drive(legs=legs)


def demo_drive() -> Drive:
    """A few minutes of field work for ``make demo``: gears, headlands, a pause, speed changes."""
    legs = [Leg(4.0, 0.0)]
    for v in (3.0, 4.5, 6.0, 5.0):
        legs += [Leg(45.0, v), Leg(12.0, 4.0, yaw_rate_dps=15.0, raised=True)]
    legs += [Leg(10.0, 0.0, raised=True), Leg(5.0, 0.0), Leg(60.0, 4.0)]
    return Drive(legs=legs)


@dataclass
class SensorNoise:
    radar_cv: float = 0.03  # paper A Table 4: CV up to 4.12 %, typically ~3 %
    tilt_sigma_deg: float = 0.03
    tilt_offset_deg: float = 0.14  # paper A Table 5: 0.13-0.15 deg sensor offset
    tilt_mount_deg: float = -1.25  # paper A: raw angle with the machine standing level


@dataclass
class MeteringPlant:
    """Paper A's motor + metering device, as the controller cannot see it."""

    slope: float
    intercept: float
    startup_duty_pct: float
    meter_a: float
    meter_b: float
    meter_c: float
    tau_s: float = 0.25
    discharge_cv: float = 0.015
    rng: random.Random = field(default_factory=lambda: random.Random(7))
    duty_pct: float = 0.0
    rpm: float = 0.0
    mass_g: float = 0.0
    _noise: float = 0.0

    def steady_rpm(self, duty_pct: float) -> float:
        if duty_pct <= 0.0:
            return 0.0
        if duty_pct < self.startup_duty_pct and self.rpm < 1.0:
            return 0.0  # stiction: below start-up duty a standing motor does not turn
        return min(MAX_SHAFT_RPM, max(0.0, self.slope * duty_pct + self.intercept))

    def discharge_g_min(self, rpm: float) -> float:
        if rpm <= 0.0:
            return 0.0
        return max(0.0, self.meter_a * rpm * rpm + self.meter_b * rpm + self.meter_c)

    def step(self, dt: float) -> float:
        """Advance ``dt`` seconds; returns grams discharged in that step."""
        target = self.steady_rpm(self.duty_pct)
        self.rpm += (target - self.rpm) * min(1.0, dt / self.tau_s)
        # AR(1) discharge noise: seed flow fluctuates over seconds, not per millisecond
        alpha = min(1.0, dt / 2.0)
        self._noise += alpha * (self.rng.gauss(0.0, self.discharge_cv) - self._noise)
        grams = self.discharge_g_min(self.rpm) * (1.0 + self._noise) * dt / 60.0
        self.mass_g += grams
        return grams


@dataclass(frozen=True)
class HopperDisturbances:
    """What a moving seeder does to its load cells beyond independent vibration; all off by
    default (each figure 0), so a plain ``HopperTruth`` keeps its meaning.

    * ``vibration_kg`` / ``vibration_tau_s``: correlated vibration, a first-order
      Gauss–Markov process (σ, correlation time): the frame rocking, not the engine buzz.
    * ``slope_transfer_pct`` / ``slope_tau_s``: load transfer on slopes: the hopper tilts on
      its cells and the reading is ``mass × (1 + ε)``, ε Gauss–Markov of σ this % of the
      mass and correlation time tens of seconds (the terrain at working speed).
    * ``accel_transfer_pct_per_ms2``: the same tilt when accelerating or braking: ε adds this
      % of the mass per m/s² of longitudinal acceleration (given with each reading).
    * ``bumps_per_min`` / ``bump_kg``: bumps: a spike on one reading, exponential in size
      (mean ``bump_kg``), either sign.
    * ``drift_kg_per_h``: the load cell's temperature drift: an offset growing with time.
    * ``pressure_kg``: a pressurised hopper: air pressure on the lid and walls adds this
      offset at full fan duty, in proportion to the fan duty given with each reading.
    """

    vibration_kg: float = 0.0
    vibration_tau_s: float = 10.0
    slope_transfer_pct: float = 0.0
    slope_tau_s: float = 30.0
    accel_transfer_pct_per_ms2: float = 0.0
    bumps_per_min: float = 0.0
    bump_kg: float = 20.0
    drift_kg_per_h: float = 0.0
    pressure_kg: float = 0.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not math.isfinite(value) or (value < 0 and name != "drift_kg_per_h"
                                            and name != "pressure_kg"):
                raise ValueError(f"HopperDisturbances.{name} must be finite and >= 0 ({value})")
        if self.vibration_tau_s <= 0 or self.slope_tau_s <= 0:
            raise ValueError("HopperDisturbances correlation times must be positive")


@dataclass
class DisturbanceState:
    """The disturbances' own state and random stream, apart from the white noise's, so that
    switching them on leaves the white noise draws unchanged."""

    spec: HopperDisturbances
    rng: random.Random = field(default_factory=lambda: random.Random(23))
    vibration_kg: float = 0.0
    tilt: float = 0.0  # ε of the slope load transfer
    last_t: float | None = None
    started: bool = False

    def kg(self, t: float, mass_kg: float, *, accel_ms2: float = 0.0,
           fan_pct: float = 0.0) -> float:
        """The disturbance on a reading at ``t`` (seconds, increasing) of ``mass_kg``."""
        d = self.spec
        dt = 0.0 if self.last_t is None else max(0.0, t - self.last_t)
        self.last_t = t
        if not self.started:  # stationary from the first reading
            self.started = True
            self.vibration_kg = self.rng.gauss(0.0, d.vibration_kg)
            self.tilt = self.rng.gauss(0.0, d.slope_transfer_pct / 100.0)
        else:
            self.vibration_kg = _gauss_markov(self.rng, self.vibration_kg, d.vibration_kg,
                                              d.vibration_tau_s, dt)
            self.tilt = _gauss_markov(self.rng, self.tilt, d.slope_transfer_pct / 100.0,
                                      d.slope_tau_s, dt)
        eps = self.tilt + d.accel_transfer_pct_per_ms2 / 100.0 * accel_ms2
        out = self.vibration_kg + mass_kg * eps
        out += d.drift_kg_per_h * t / 3600.0
        out += d.pressure_kg * max(0.0, min(100.0, fan_pct)) / 100.0
        if d.bumps_per_min > 0.0 and dt > 0.0 and \
                self.rng.random() < 1.0 - math.exp(-d.bumps_per_min * dt / 60.0):
            out += self.rng.choice((-1.0, 1.0)) * self.rng.expovariate(1.0 / d.bump_kg)
        return out


def _gauss_markov(rng: random.Random, x: float, sigma: float, tau_s: float, dt: float) -> float:
    """One exact step of a first-order Gauss–Markov process of stationary σ ``sigma``."""
    if sigma <= 0.0:
        return 0.0
    a = math.exp(-dt / tau_s)
    return a * x + sigma * math.sqrt(max(0.0, 1.0 - a * a)) * rng.gauss(0.0, 1.0)


@dataclass
class HopperTruth:
    """The seed hopper on its load cells: what a weight transmitter under it reads.

    The mass is the initial fill, plus each refill from its time on, minus what the meter
    really discharged (the plant's truth, not the controller's model). Each reading carries
    vibration noise: independent per reading (a transmitter read at a few Hz samples a
    machine shaking at tens of Hz), σ ``noise_kg``, kilograms on a moving seeder; and the
    correlated ``disturbances`` of a field (off by default; ``HopperDisturbances``).

    ``fault_kg``: fault injection: while set, the transmitter reports this value instead
    (NaN, an overload code, a jump), whatever the load cells carry.
    """

    initial_kg: float = 800.0
    noise_kg: float = 2.0
    refills: tuple[tuple[float, float], ...] = ()  # (time s, kg added)
    rng: random.Random = field(default_factory=lambda: random.Random(11))
    disturbances: HopperDisturbances = field(default_factory=HopperDisturbances)
    fault_kg: float | None = None
    _state: DisturbanceState | None = field(default=None, init=False, repr=False)

    def mass_kg(self, t: float, discharged_kg: float) -> float:
        added = sum(kg for at, kg in self.refills if t >= at)
        return self.initial_kg + added - discharged_kg

    def disturbance_kg(self, t: float, mass_kg: float, *, accel_ms2: float = 0.0,
                       fan_pct: float = 0.0) -> float:
        """The correlated part of a reading at ``t`` (0 with the disturbances off)."""
        if self.disturbances == HopperDisturbances():
            return 0.0
        if self._state is None:
            self._state = DisturbanceState(self.disturbances)
        return self._state.kg(t, mass_kg, accel_ms2=accel_ms2, fan_pct=fan_pct)

    def reading_kg(self, t: float, discharged_kg: float, *, accel_ms2: float = 0.0,
                   fan_pct: float = 0.0) -> float:
        if self.fault_kg is not None:
            return self.fault_kg
        mass = self.mass_kg(t, discharged_kg)
        return (mass + self.rng.gauss(0.0, self.noise_kg)
                + self.disturbance_kg(t, mass, accel_ms2=accel_ms2, fan_pct=fan_pct))
