"""A seeding field as physics: the independent ground truth the positioning benchmark judges by.

Why a second truth next to ``simulator.seed_tubes``: that one puts each seed at the rigid
outlet position ``t_edge + fall_time_table(speed)`` later, which is the position model itself,
so a benchmark built on it measures only arithmetic. This module shares no code, table or
function with ``gateway/`` (a test checks that importing it loads nothing from ``gateway``):
its seeds fall, bounce and roll by their own physics, its tractor rolls on sloping ground with
its antenna 2.5 m up, its receiver's error is correlated in time and sometimes float or absent,
its implement is trailed and swings out on curves, and its clocks drift. What the gateway gets
from it is what it would get on a field: receiver epochs (rendered as the UM982's own sentences
by ``epoch_lines``) stamped on a host clock, and seed-tube edges stamped on the same clock.

Frames and conventions (stated here, derived here, not imported):

- local ENU metres around ``origin``; heading ψ clockwise from north, so forward is
  (sin ψ, cos ψ) and right is (cos ψ, −sin ψ);
- machine body axes forward, right, up; roll φ positive = right side down, pitch θ positive =
  nose up (climbing). A body vector (f, r, u) is rolled about forward, then pitched about right,
  then yawed into ENU (``body_to_enu``);
- simulated time ``t`` is GPS time (the receiver's epochs fall on its 10 Hz grid exactly);
  the host's monotonic clock runs ``host_drift_ppm`` fast against it from ``host_t0``.

The model, part by part (each a frozen dataclass of its parameters, defaults as used by the
benchmark; every random process draws from its own stream so switching one error source on
or off leaves the draws of the others unchanged):

- ``DriveSpec``/``FieldDrive``: passes at given speeds (accelerating from the headland speed
  after lowering, decelerating before lifting), an autosteer weave, optional contour curvature,
  raised U-turns; the trailed implement's heading follows the hitch (no side slip at its
  wheels), so it articulates on curves and is straight behind the tractor on straight lines;
- ``Terrain``: a height field (cross slope, along slope, rolling undulations); roll and pitch
  of tractor and implement follow from its gradient under each;
- ``Machine``: primary antenna ``antenna_height_m`` above the ground point it is configured
  from, secondary antenna beside it (``baseline``), hitch, outlets;
- ``SeedLot``/``Tube``: seed flight from the sensor to the outlet along an inclined tube with
  wall friction, quadratic drag against the air in the tube, release velocity from the disc
  (faster at higher ground speed), then a short free fall to the furrow bottom;
- ``Furrow``: on touchdown the seed keeps a random fraction of its horizontal velocity relative
  to the ground and slides to rest (so it moves forward further the faster the machine goes),
  plus a random bounce;
- ``Receiver``: first-order Gauss–Markov position error (σ, τ) plus white noise, heading and
  baseline-pitch noise, float windows (a larger, faster-wandering error, flagged float) and
  dropouts (no epoch at all);
- ``Multipath`` (optional, off by default): reflections off a tree line or a building beside
  the field, bursts of a few centimetres of position step and a few tenths of a degree of
  heading and baseline-pitch bias lasting tens of seconds, while the receiver still reports
  RTK fixed;
- ``Timing``: receiver output latency (solution time varying by a few ms), USB jitter with
  bursts, sensor and line latency of the edges, the host clock's drift;
- ``FitterErrors``: what a fitter with a tape measure and a datasheet configures
  (``configured``): lever arm and latency, each off by a stated amount.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import Literal

import numpy as np
import numpy.typing as npt
import pymap3d

from simulator.gnss_sentences import GEOID_SEP_M, epoch_sentences

Array = npt.NDArray[np.float64]
KMH_PER_MS = 3.6
GRAVITY = 9.81
RHO_AIR = 1.2  # kg/m³
SOWING_MIN_KMH = 1.0  # the metering stops below this

# independent random streams (one per process), see module docstring
_STREAM = {
    "terrain": 1, "metering": 2, "lot": 3, "furrow": 4, "rtk": 5, "heading": 6,
    "timing": 7, "survey": 8, "edges": 9, "multipath": 10,
}


def _rng(seed: int, stream: str) -> np.random.Generator:
    return np.random.default_rng([seed, _STREAM[stream]])


# ------------------------------------------------------------------ geometry


def body_to_enu(
    f: Array | float, r: Array | float, u: Array | float,
    heading_deg: Array | float, pitch_deg: Array | float, roll_deg: Array | float,
) -> tuple[Array, Array, Array]:
    """A body-frame vector (forward, right, up) in ENU for the given attitude."""
    psi, th, ph = np.radians(heading_deg), np.radians(pitch_deg), np.radians(roll_deg)
    f, r, u = np.asarray(f, float), np.asarray(r, float), np.asarray(u, float)
    r1 = r * np.cos(ph) + u * np.sin(ph)  # roll about forward: right side down for ph > 0
    u1 = -r * np.sin(ph) + u * np.cos(ph)
    f2 = f * np.cos(th) - u1 * np.sin(th)  # pitch about right: nose up for th > 0
    u2 = f * np.sin(th) + u1 * np.cos(th)
    east = f2 * np.sin(psi) + r1 * np.cos(psi)
    north = f2 * np.cos(psi) - r1 * np.sin(psi)
    return east, north, u2


# ------------------------------------------------------------------ terrain


@dataclass(frozen=True)
class Terrain:
    """Ground height z(e, n): planar slopes plus rolling undulations in random directions."""

    cross_slope_deg: float = 2.0  # ground rises to the east (across north–south passes)
    along_slope_deg: float = 0.5  # ground rises to the north
    undulation_m: float = 0.05  # amplitude of each of the rolling waves (±0.4° of slope)
    wavelength_m: float = 40.0
    waves: int = 3
    seed: int = 0

    def _waves(self) -> list[tuple[float, float, float]]:
        rng = _rng(self.seed, "terrain")
        out = []
        for _ in range(self.waves if self.undulation_m > 0 else 0):
            direction = rng.uniform(0.0, 2.0 * math.pi)
            wl = self.wavelength_m * rng.uniform(0.7, 1.4)
            k = 2.0 * math.pi / wl
            out.append((k * math.sin(direction), k * math.cos(direction), rng.uniform(0, 6.3)))
        return out

    def height(self, e: Array, n: Array) -> Array:
        z = np.tan(np.radians(self.cross_slope_deg)) * e
        z = z + np.tan(np.radians(self.along_slope_deg)) * n
        for ke, kn, phase in self._waves():
            z = z + self.undulation_m * np.sin(ke * e + kn * n + phase)
        return np.asarray(z, float)

    def gradient(self, e: Array, n: Array) -> tuple[Array, Array]:
        ge = np.full_like(np.asarray(e, float), math.tan(math.radians(self.cross_slope_deg)))
        gn = np.full_like(np.asarray(n, float), math.tan(math.radians(self.along_slope_deg)))
        for ke, kn, phase in self._waves():
            c = self.undulation_m * np.cos(ke * e + kn * n + phase)
            ge = ge + ke * c
            gn = gn + kn * c
        return ge, gn

    def attitude(self, e: Array, n: Array, heading_deg: Array) -> tuple[Array, Array]:
        """(pitch, roll) in degrees of a body resting on the ground at (e, n) facing
        ``heading_deg``: its up axis is the ground normal."""
        ge, gn = self.gradient(e, n)
        psi = np.radians(heading_deg)
        dz_fwd = ge * np.sin(psi) + gn * np.cos(psi)
        dz_right = ge * np.cos(psi) - gn * np.sin(psi)
        norm = np.sqrt(1.0 + ge * ge + gn * gn)
        roll = np.degrees(np.arcsin(-dz_right / norm))  # ground lower on the right: positive
        pitch = np.degrees(np.arctan(dz_fwd))
        return pitch, roll


FLAT = Terrain(cross_slope_deg=0.0, along_slope_deg=0.0, undulation_m=0.0)


# ------------------------------------------------------------------ machine and drive


@dataclass(frozen=True)
class Machine:
    """Where everything sits. Distances from the ground point below the primary antenna on
    level ground (the point a fitter measures the lever arm from)."""

    antenna_height_m: float = 2.5
    baseline: Literal["side_by_side", "fore_aft"] = "side_by_side"  # secondary right / ahead
    baseline_m: float = 1.0
    hitch_behind_m: float = 1.6  # antenna ground point → hitch pin
    hitch_height_m: float = 0.5
    trailed: bool = True  # False: a mounted implement, rigid with the tractor
    outlets_behind_hitch_m: float = 1.4
    implement_wheels_behind_hitch_m: float = 2.2
    row_lateral_m: tuple[float, ...] = (-1.875, -1.125, -0.375, 0.375, 1.125, 1.875)

    @property
    def outlet_behind_antenna_m(self) -> float:
        return self.hitch_behind_m + self.outlets_behind_hitch_m


@dataclass(frozen=True)
class DriveSpec:
    speeds_kmh: tuple[float, ...] = (4.0, 8.0, 12.0, 16.0)
    pass_length_m: float = 80.0
    turn_speed_kmh: float = 6.0
    turn_radius_m: float = 6.0
    accel_ms2: float = 0.8
    decel_ms2: float = 1.0
    lead_in_s: float = 2.0  # standing, lowered, before the first pass
    weave_deg: float = 0.3  # autosteer heading weave amplitude along the passes
    weave_period_m: float = 25.0
    pass_curvature_per_m: float = 0.0  # contour passes: 1/radius, alternating sign
    run_in_m: float = 6.0  # after a turn, straight and raised before lowering
    dt: float = 0.005


class FieldDrive:
    """The tractor's ground point and heading, and the implement's heading, sampled every
    ``dt`` (numpy arrays) and interpolated in between."""

    def __init__(self, spec: DriveSpec, machine: Machine) -> None:
        self.spec, self.machine = spec, machine
        dt = spec.dt
        ts: list[float] = []
        es: list[float] = []
        ns: list[float] = []
        hs: list[float] = []  # unwrapped tractor heading, deg
        vs: list[float] = []
        his: list[float] = []  # unwrapped implement heading, deg
        low: list[bool] = []
        pas: list[int] = []
        self.pass_times: list[tuple[float, float]] = []
        t = e = n = 0.0
        h = hi = 0.0
        v = 0.0
        wheels = machine.implement_wheels_behind_hitch_m

        def step(yaw_rate_dps: float, lowered: bool, pass_i: int) -> None:
            nonlocal t, e, n, h, hi
            psi = math.radians(h)
            fe, fn = math.sin(psi), math.cos(psi)
            re, rn = math.cos(psi), -math.sin(psi)
            # hitch velocity: the ground point's, plus the hitch swinging with the yaw rate
            yaw = math.radians(yaw_rate_dps)
            vhe = v * fe - machine.hitch_behind_m * yaw * re
            vhn = v * fn - machine.hitch_behind_m * yaw * rn
            if machine.trailed:
                pi = math.radians(hi)
                hi += math.degrees((vhe * math.cos(pi) - vhn * math.sin(pi)) / wheels * dt)
            else:
                hi = h + yaw_rate_dps * dt
            e += v * fe * dt
            n += v * fn * dt
            h += yaw_rate_dps * dt
            t += dt
            ts.append(t)
            es.append(e)
            ns.append(n)
            hs.append(h)
            vs.append(v)
            his.append(hi)
            low.append(lowered)
            pas.append(pass_i)

        ts.append(0.0)
        es.append(0.0)
        ns.append(0.0)
        hs.append(0.0)
        vs.append(0.0)
        his.append(0.0)
        low.append(True)
        pas.append(0)
        for _ in range(round(spec.lead_in_s / dt)):
            step(0.0, True, 0)
        v_turn = spec.turn_speed_kmh / KMH_PER_MS
        for i, kmh in enumerate(spec.speeds_kmh):
            target = kmh / KMH_PER_MS
            s = 0.0
            sign = 1.0 if i % 2 == 0 else -1.0
            if i > 0:  # out of the turn: straighten up, then lower at the headland line
                run = 0.0
                while run < spec.run_in_m:
                    step(0.0, False, -1)
                    run += v * dt
            t_start = t
            while s < spec.pass_length_m:
                remaining = spec.pass_length_m - s
                end_v = v_turn if i < len(spec.speeds_kmh) - 1 else 0.0
                if v > end_v and remaining <= (v * v - end_v * end_v) / (2 * spec.decel_ms2):
                    v = max(end_v, v - spec.decel_ms2 * dt, 0.3 / KMH_PER_MS)
                elif v < target:
                    v = min(target, v + spec.accel_ms2 * dt)
                else:
                    v = max(target, v - spec.decel_ms2 * dt)
                k = 2.0 * math.pi / spec.weave_period_m
                weave = spec.weave_deg * k * math.cos(k * s)  # d(heading)/ds, deg/m
                curve = sign * math.degrees(spec.pass_curvature_per_m)
                step((weave + curve) * v, True, i)
                s += v * dt
            self.pass_times.append((t_start, t))
            if i == len(spec.speeds_kmh) - 1:
                v = 0.0
                for _ in range(round(3.0 / dt)):  # stop, lift, the receiver keeps talking
                    step(0.0, False, -1)
                break
            # raised U-turn to the next pass, right then left; the heading lands on 0/180
            turn_sign = 1.0 if i % 2 == 0 else -1.0
            goal = h + turn_sign * 180.0 - (h - round(h / 180.0) * 180.0)
            rate = math.degrees(v_turn / spec.turn_radius_m)
            while abs(goal - h) > 1e-9:
                v = min(v_turn, v + spec.accel_ms2 * dt)
                d = goal - h
                r = turn_sign * min(abs(d) / dt, rate)
                step(r, False, -1)
        self.duration_s = t
        self.t = np.array(ts)
        self.e, self.n = np.array(es), np.array(ns)
        self.h, self.v, self.hi = np.array(hs), np.array(vs), np.array(his)
        self.lowered = np.array(low)
        self.pass_index = np.array(pas)

    def at(self, t: Array | float) -> tuple[Array, Array, Array, Array, Array]:
        """(east, north, heading°, speed m/s, implement heading°) of the ground point."""
        tt = np.asarray(t, float)
        return (
            np.interp(tt, self.t, self.e), np.interp(tt, self.t, self.n),
            np.interp(tt, self.t, self.h), np.interp(tt, self.t, self.v),
            np.interp(tt, self.t, self.hi),
        )

    def pass_of(self, t: Array | float) -> Array:
        i = np.clip(np.searchsorted(self.t, np.asarray(t, float)), 0, len(self.t) - 1)
        return np.asarray(self.pass_index[i])


# ------------------------------------------------------------------ seed flight


@dataclass(frozen=True)
class SeedLot:
    """A lot of maize seed: size and density (drag), wall friction, scatter between seeds."""

    diameter_m: float = 0.008
    diameter_cv: float = 0.08
    density_kg_m3: float = 1250.0
    drag_coefficient: float = 0.47
    wall_friction: float = 0.55
    wall_friction_sd: float = 0.15


@dataclass(frozen=True)
class Tube:
    """Sensor to outlet along an inclined tube, then free fall to the furrow bottom."""

    sensor_to_outlet_m: float = 0.16
    angle_from_horizontal_deg: float = 75.0  # leaning back: the outlet trails the sensor
    outlet_height_m: float = 0.03
    release_speed_ms: float = 0.85  # seed leaving the disc, at standstill ...
    release_per_ground_ms: float = 0.15  # ... plus this times ground speed (disc speed)
    airflow_ms: float = 0.0  # air velocity down the tube (air-assisted delivery)


def tube_flight(
    ground_ms: Array, diameter_m: Array, friction: Array, lot: SeedLot, tube: Tube,
    dt: float = 0.0005,
) -> tuple[Array, Array]:
    """(time in the tube, exit speed along the tube) for each seed.

    Along the tube: ``s'' = g(sin α − μ cos α) − k (s' − u)|s' − u|`` with the sphere's drag
    ``k = 3 ρ_air C_d / (4 ρ_seed d)``, from the release speed at the sensor until ``s`` reaches
    the outlet. Integrated for all seeds at once (midpoint rule, exact crossing interpolated).
    """
    alpha = math.radians(tube.angle_from_horizontal_deg)
    g_eff = GRAVITY * (math.sin(alpha) - np.clip(friction, 0.0, 2.0) * math.cos(alpha))
    k = 3.0 * RHO_AIR * lot.drag_coefficient / (4.0 * lot.density_kg_m3 * diameter_m)
    u = tube.airflow_ms
    v = tube.release_speed_ms + tube.release_per_ground_ms * np.asarray(ground_ms, float)
    s = np.zeros_like(v)
    t_out = np.full_like(v, np.nan)
    v_out = np.full_like(v, np.nan)
    t = 0.0

    def acc(vel: Array) -> Array:
        rel = vel - u
        return np.asarray(g_eff - k * rel * np.abs(rel), float)

    for _ in range(int(2.0 / dt)):
        v_mid = v + 0.5 * dt * acc(v)
        s_new = s + dt * v_mid
        v_new = v + dt * acc(v_mid)
        crossed = np.isnan(t_out) & (s_new >= tube.sensor_to_outlet_m)
        if crossed.any():
            a = (tube.sensor_to_outlet_m - s[crossed]) / (s_new[crossed] - s[crossed])
            t_out[crossed] = t + a * dt
            v_out[crossed] = v[crossed] + a * (v_new[crossed] - v[crossed])
        s, v, t = s_new, v_new, t + dt
        if not np.isnan(t_out).any():
            break
    if np.isnan(t_out).any():
        raise ValueError("seeds stuck in the tube: friction too high for its angle")
    return t_out, v_out


def free_fall_s(height_m: float, down_ms: Array) -> Array:
    """Time to fall ``height_m`` starting at ``down_ms`` downwards."""
    d = np.asarray(down_ms, float)
    return np.asarray((-d + np.sqrt(d * d + 2.0 * GRAVITY * height_m)) / GRAVITY, float)


@dataclass(frozen=True)
class Furrow:
    """Touchdown: the seed keeps ``retained`` (uniform) of its horizontal velocity relative to
    the ground and slides to rest against ``friction``; plus a random bounce."""

    retained: tuple[float, float] = (0.10, 0.30)
    friction: float = 0.8
    bounce_along_sd_m: float = 0.003
    bounce_across_sd_m: float = 0.002

    def mean_slide_m(self, horizontal_ms: Array) -> Array:
        a, b = self.retained
        mean_sq = (a * a + a * b + b * b) / 3.0  # E[retained²] of the uniform
        u = np.asarray(horizontal_ms, float)
        return np.asarray(np.sign(u) * u * u * mean_sq / (2.0 * self.friction * GRAVITY), float)


# ------------------------------------------------------------------ receiver and timing


@dataclass(frozen=True)
class MultipathBurst:
    """One burst: its window and the error it holds during its plateau (reported minus
    true)."""

    start_s: float
    duration_s: float
    east_m: float
    north_m: float
    up_m: float
    heading_deg: float
    pitch_deg: float  # the baseline's elevation (#HEADINGA pitch)


@dataclass(frozen=True)
class Multipath:
    """Reflections off a tree line or a building next to the field (off unless configured).

    Why a burst of steps and not more Gauss–Markov noise: a reflected carrier biases the
    fixed solution by a few centimetres for as long as the geometry of antenna, reflector and
    satellite lasts, then lets go, and the receiver still says RTK fixed; a dual-antenna
    heading sees the difference of the two antennas' reflections. So each burst is a constant
    error vector (random direction and sign, magnitudes uniform in the stated ranges) reached
    and left over ``ramp_s`` (the tracking loops follow the reflection), bursts arriving at
    random (exponential gaps of mean ``gap_s``). Defaults (stated ranges, see
    ``benchmarks.positioning_sensitivity``): horizontal step 2–5 cm (a carrier's multipath
    error is at most a quarter wavelength, 4.8 cm at L1, per satellite), height 1.5× that,
    heading 0.2–0.6° (OxTS RT3000 manual, table 28: a 1 m baseline near trees or buildings
    1–2° 3σ against 0.6° in open sky), bursts of 10–40 s (an assumption).
    """

    gap_s: tuple[float, float] = (20.0, 60.0)  # mean gap between bursts, uniform per field
    duration_s: tuple[float, float] = (10.0, 40.0)
    step_m: tuple[float, float] = (0.02, 0.05)
    height_ratio: float = 1.5
    heading_deg: tuple[float, float] = (0.2, 0.6)
    pitch_deg: tuple[float, float] = (0.2, 0.6)
    ramp_s: float = 1.0
    position: bool = True  # the position step (False: heading and pitch bursts only)
    attitude: bool = True  # the heading and pitch bursts (False: position steps only)

    def bursts(self, seed: int, until_s: float) -> list[MultipathBurst]:
        """The bursts of a drive of ``until_s`` seconds (its own random stream)."""
        rng = _rng(seed, "multipath")
        gap = rng.uniform(*self.gap_s)
        out: list[MultipathBurst] = []
        t = rng.exponential(gap)
        while t < until_s:
            dur = rng.uniform(*self.duration_s)
            step = rng.uniform(*self.step_m) * self.position
            direction = rng.uniform(0.0, 2.0 * math.pi)
            up = step * self.height_ratio * rng.choice((-1.0, 1.0))
            hd = rng.uniform(*self.heading_deg) * rng.choice((-1.0, 1.0)) * self.attitude
            pd = rng.uniform(*self.pitch_deg) * rng.choice((-1.0, 1.0)) * self.attitude
            out.append(MultipathBurst(float(t), float(dur), float(step * math.sin(direction)),
                                      float(step * math.cos(direction)), float(up), float(hd),
                                      float(pd)))
            t += dur + rng.exponential(gap)
        return out

    def profile(self, burst: MultipathBurst, t: Array) -> Array:
        """0 outside the burst, 1 on its plateau, linear over ``ramp_s`` at either end."""
        tt = np.asarray(t, float) - burst.start_s
        ramp = max(min(self.ramp_s, burst.duration_s / 2.0), 1e-9)
        up = np.clip(tt / ramp, 0.0, 1.0)
        down = np.clip((burst.duration_s - tt) / ramp, 0.0, 1.0)
        return np.asarray(np.minimum(up, down), float)


@dataclass(frozen=True)
class Receiver:
    rate_hz: float = 10.0
    rtk_sigma_m: float = 0.012  # Gauss–Markov σ per horizontal axis (fixed RTK)
    rtk_tau_s: float = 60.0
    white_sigma_m: float = 0.003
    vertical_white_sigma_m: float = 0.006  # RTK height: about twice the horizontal noise
    heading_sigma_deg: float = 0.08  # 1 m baseline
    pitch_sigma_deg: float = 0.15
    speed_sigma_kmh: float = 0.03
    float_sigma_m: float = 0.12
    float_tau_s: float = 15.0
    # (start, duration) in simulated seconds
    float_windows: tuple[tuple[float, float], ...] = ()
    dropout_windows: tuple[tuple[float, float], ...] = ()
    multipath: Multipath | None = None  # reflections beside the field (RTK still fixed)

    def degraded(self, t: Array, margin_s: float = 0.5) -> npt.NDArray[np.bool_]:
        tt = np.asarray(t, float)
        out = np.zeros(tt.shape, bool)
        for a, d in self.float_windows + self.dropout_windows:
            out |= (tt >= a - margin_s) & (tt <= a + d + margin_s)
        return out


@dataclass(frozen=True)
class Timing:
    host_t0: float = 10_000.0
    host_drift_ppm: float = 40.0
    gnss_latency_s: float = 0.040  # epoch instant → first sentence leaves the receiver
    gnss_latency_spread_s: float = 0.004  # solution time varies by up to this (uniform)
    usb_jitter_mean_s: float = 0.003  # one-sided, exponential
    burst_prob: float = 0.05
    burst_s: tuple[float, float] = (0.005, 0.030)
    sensor_latency_s: float = 0.0005  # beam broken → edge out of the capture module
    line_s: float = 7 * 10 / 115200  # "D,n\r\n" at 115 200 bd
    edge_jitter_s: float = 0.001  # USB polling, uniform

    def host(self, t: Array | float) -> Array:
        return np.asarray(self.host_t0 + np.asarray(t, float) * (1 + self.host_drift_ppm * 1e-6))


@dataclass(frozen=True)
class Metering:
    spacing_m: float = 0.2
    spacing_cv: float = 0.08
    miss_prob: float = 0.01
    double_prob: float = 0.01
    double_gap_s: tuple[float, float] = (0.004, 0.02)


@dataclass(frozen=True)
class FitterErrors:
    """What the fitter configures, relative to the truth (positive = configured larger)."""

    behind_m: float = 0.0  # outlets further behind (on a trailed implement: behind the hitch)
    lateral_m: float = 0.0  # every row shifted the same way (the centre line mis-marked)
    gnss_latency_s: float = 0.0
    antenna_height_m: float = 0.0  # the tape from the ground to the antenna on the cab roof
    hitch_behind_m: float = 0.0  # antenna ground point → hitch pin, measured on the tractor
    hitch_height_m: float = 0.0  # hitch pin above the ground

    def configured(self, machine: Machine, timing: Timing) -> Configured:
        """The settings as entered. A trailed implement is entered as hitch geometry
        (distances and the hitch's height); ``outlet_behind_antenna_m`` is then the
        straight-line sum."""
        hitch = outlets = height = wheels = None
        if machine.trailed:
            hitch = machine.hitch_behind_m + self.hitch_behind_m
            outlets = machine.outlets_behind_hitch_m + self.behind_m
            wheels = machine.implement_wheels_behind_hitch_m + self.behind_m  # the same tape
            height = machine.hitch_height_m + self.hitch_height_m
        return Configured(
            outlet_behind_antenna_m=machine.outlet_behind_antenna_m + self.behind_m
            + self.hitch_behind_m * machine.trailed,
            row_lateral_m=tuple(r + self.lateral_m for r in machine.row_lateral_m),
            gnss_output_latency_ms=(timing.gnss_latency_s + self.gnss_latency_s) * 1000.0,
            seed_edge_latency_ms=timing.line_s * 1000.0,  # the fitter knows the line time only
            antenna_height_m=machine.antenna_height_m + self.antenna_height_m,
            hitch_behind_antenna_m=hitch,
            outlets_behind_hitch_m=outlets,
            hitch_height_m=height,
            wheels_behind_hitch_m=wheels,
        )


@dataclass(frozen=True)
class Configured:
    """Position-model settings as a fitter would enter them (plain values, no gateway type)."""

    outlet_behind_antenna_m: float
    row_lateral_m: tuple[float, ...]
    gnss_output_latency_ms: float
    seed_edge_latency_ms: float
    antenna_height_m: float = 0.0
    hitch_behind_antenna_m: float | None = None  # None: a mounted implement
    outlets_behind_hitch_m: float | None = None
    hitch_height_m: float | None = None
    wheels_behind_hitch_m: float | None = None  # the implement's wheels, behind the hitch


@dataclass(frozen=True)
class FieldConfig:
    drive: DriveSpec = field(default_factory=DriveSpec)
    terrain: Terrain = field(default_factory=Terrain)
    machine: Machine = field(default_factory=Machine)
    lot: SeedLot = field(default_factory=SeedLot)
    tube: Tube = field(default_factory=Tube)
    furrow: Furrow = field(default_factory=Furrow)
    receiver: Receiver = field(default_factory=Receiver)
    timing: Timing = field(default_factory=Timing)
    metering: Metering = field(default_factory=Metering)
    origin: tuple[float, float, float] = (45.7536, 126.6339, 150.0)  # near Harbin
    utc_start: datetime = datetime(2026, 5, 2, 6, 0, 0, tzinfo=UTC)
    seed: int = 1


# ------------------------------------------------------------------ outputs


@dataclass(frozen=True)
class ReceiverEpoch:
    """One epoch as the receiver reports it, its host arrival time, and its true error."""

    k: int
    t: float  # the instant it describes (GPS time, simulated seconds)
    utc: datetime
    t_host: float  # host monotonic time its first sentence arrives
    lat: float
    lon: float
    alt_msl_m: float
    speed_kmh: float
    course_deg: float
    heading_deg: float  # the baseline's azimuth, as HEADINGA reports it
    pitch_deg: float  # the baseline's elevation, as HEADINGA reports it
    fix: Literal["rtk_fixed", "rtk_float"]
    err_east_m: float  # reported minus true primary-antenna position
    err_north_m: float
    err_heading_deg: float  # reported machine heading minus true


@dataclass(frozen=True)
class Seed:
    row: int
    t_edge: float  # true instant the seed broke the beam
    t_host: float  # host stamp of its edge
    t_land: float  # true touchdown in the furrow
    east: float  # where it came to rest
    north: float
    expected_t_land: float  # a mean seed of the lot, no randomness
    expected_east: float  # where such a seed comes to rest (mean slide, no bounce)
    expected_north: float
    pass_index: int
    speed_kmh: float  # ground speed at the edge
    articulation_deg: float  # implement heading minus tractor heading at touchdown
    roll_deg: float  # tractor roll at touchdown
    slide_m: float  # how far it slid forward in the furrow after touchdown (before bounce)


@dataclass
class FieldRun:
    config: FieldConfig
    drive: FieldDrive
    epochs: list[ReceiverEpoch]
    seeds: list[Seed]  # in host arrival order of their edges

    def antenna_ground_at(self, t: Array | float) -> tuple[Array, Array]:
        """The primary antenna's configured reference point (the ground point below it when
        level) — the pivot a heading error turns the outlets around."""
        e, n, *_ = self.drive.at(t)
        return e, n

    def to_geodetic(self, east: Array, north: Array) -> tuple[Array, Array]:
        lat0, lon0, h0 = self.config.origin
        lat, lon, _ = pymap3d.enu2geodetic(east, north, 0.0, lat0, lon0, h0)
        return np.asarray(lat, float), np.asarray(lon, float)

    def to_enu(self, lat: Array, lon: Array) -> tuple[Array, Array]:
        lat0, lon0, h0 = self.config.origin
        e, n, _ = pymap3d.geodetic2enu(lat, lon, h0, lat0, lon0, h0)
        return np.asarray(e, float), np.asarray(n, float)


# ------------------------------------------------------------------ the model


def antenna_positions(
    cfg: FieldConfig, drive: FieldDrive, t: Array
) -> tuple[tuple[Array, Array, Array], tuple[Array, Array, Array], Array, Array, Array]:
    """Primary and secondary antenna (ENU, up above the origin's height), tractor heading,
    pitch and roll at ``t``."""
    e, n, h, _v, _hi = drive.at(t)
    pitch, roll = cfg.terrain.attitude(e, n, h)
    z = cfg.terrain.height(e, n)
    m = cfg.machine
    de, dn, du = body_to_enu(0.0, 0.0, m.antenna_height_m, h, pitch, roll)
    primary = (e + de, n + dn, z + du)
    bf, br = (0.0, m.baseline_m) if m.baseline == "side_by_side" else (m.baseline_m, 0.0)
    se, sn, su = body_to_enu(bf, br, m.antenna_height_m, h, pitch, roll)
    secondary = (e + se, n + sn, z + su)
    return primary, secondary, h, pitch, roll


def outlet_positions(
    cfg: FieldConfig, drive: FieldDrive, t: Array, rows: npt.NDArray[np.intp]
) -> tuple[Array, Array, Array]:
    """Horizontal position of row ``rows``' outlet at ``t`` (and the implement heading)."""
    e, n, h, _v, hi = drive.at(t)
    m = cfg.machine
    pitch, roll = cfg.terrain.attitude(e, n, h)
    he, hn, _ = body_to_enu(-m.hitch_behind_m, 0.0, m.hitch_height_m, h, pitch, roll)
    hitch_e, hitch_n = e + he, n + hn
    # the implement rests on the ground at its own place and heading
    psi_i = np.radians(hi)
    mid_e = hitch_e - m.outlets_behind_hitch_m * np.sin(psi_i)
    mid_n = hitch_n - m.outlets_behind_hitch_m * np.cos(psi_i)
    ipitch, iroll = cfg.terrain.attitude(mid_e, mid_n, hi)
    lateral = np.asarray(m.row_lateral_m)[rows - 1]
    oe, on, _ = body_to_enu(-m.outlets_behind_hitch_m, lateral, 0.0, hi, ipitch, iroll)
    return hitch_e + oe, hitch_n + on, hi


def _gauss_markov(
    rng: np.random.Generator, n: int, sigma: float, tau_s: float, dt: float
) -> Array:
    a = math.exp(-dt / tau_s) if tau_s > 0 else 0.0
    w = rng.normal(0.0, sigma * math.sqrt(1.0 - a * a), n)
    out = np.empty(n)
    x = rng.normal(0.0, sigma) if sigma > 0 else 0.0
    for i in range(n):
        x = a * x + w[i]
        out[i] = x
    return out


def gauss_markov(sigma: float, tau_s: float, dt: float, n: int, seed: int = 0) -> Array:
    """A stationary first-order Gauss–Markov sequence (σ, correlation time τ), for tests."""
    return _gauss_markov(_rng(seed, "rtk"), n, sigma, tau_s, dt)


def _receiver_epochs(cfg: FieldConfig, drive: FieldDrive) -> list[ReceiverEpoch]:
    rx, timing = cfg.receiver, cfg.timing
    period = 1.0 / rx.rate_hz
    k_all = np.arange(int(drive.duration_s * rx.rate_hz) + 1)
    t = (k_all * period).astype(np.float64)
    count = len(t)
    rng = _rng(cfg.seed, "rtk")
    err_e = _gauss_markov(rng, count, rx.rtk_sigma_m, rx.rtk_tau_s, period)
    err_n = _gauss_markov(rng, count, rx.rtk_sigma_m, rx.rtk_tau_s, period)
    err_u = _gauss_markov(rng, count, 2 * rx.rtk_sigma_m, rx.rtk_tau_s, period)
    err_e = err_e + rng.normal(0.0, rx.white_sigma_m, count)
    err_n = err_n + rng.normal(0.0, rx.white_sigma_m, count)
    fix = np.full(count, "rtk_fixed", dtype=object)
    for start, dur in rx.float_windows:
        inside = (t >= start) & (t < start + dur)
        m = int(inside.sum())
        if m:
            # the float solution starts near the fixed one and wanders off quickly
            ramp = np.minimum(1.0, (t[inside] - start) / 2.0)
            err_e[inside] += ramp * _gauss_markov(rng, m, rx.float_sigma_m, rx.float_tau_s, period)
            err_n[inside] += ramp * _gauss_markov(rng, m, rx.float_sigma_m, rx.float_tau_s, period)
            fix[inside] = "rtk_float"
            err_u[inside] += ramp * _gauss_markov(rng, m, 2 * rx.float_sigma_m, rx.float_tau_s,
                                                  period)
    # drawn last, so the other errors' draws do not depend on it
    err_u = err_u + rng.normal(0.0, rx.vertical_white_sigma_m, count)
    hrng = _rng(cfg.seed, "heading")
    err_h = hrng.normal(0.0, rx.heading_sigma_deg, count)
    err_p = hrng.normal(0.0, rx.pitch_sigma_deg, count)
    err_v = hrng.normal(0.0, rx.speed_sigma_kmh, count)
    if rx.multipath is not None:
        for b in rx.multipath.bursts(cfg.seed, float(t[-1])):
            w = rx.multipath.profile(b, t)
            err_e, err_n, err_u = err_e + w * b.east_m, err_n + w * b.north_m, err_u + w * b.up_m
            err_h, err_p = err_h + w * b.heading_deg, err_p + w * b.pitch_deg
    trng = _rng(cfg.seed, "timing")
    latency = timing.gnss_latency_s + trng.uniform(0.0, timing.gnss_latency_spread_s, count)
    jitter = trng.exponential(timing.usb_jitter_mean_s, count) if timing.usb_jitter_mean_s else (
        np.zeros(count))
    burst = trng.random(count) < timing.burst_prob
    jitter = jitter + np.where(burst, trng.uniform(*timing.burst_s, count), 0.0)
    t_host = timing.host(t + latency) + jitter

    (pe, pn, pu), (se, sn, su), h, _pitch, _roll = antenna_positions(cfg, drive, t)
    dt = 0.005
    (pe0, pn0, _), _s0, *_ = antenna_positions(cfg, drive, t - dt)
    (pe1, pn1, _), _s1, *_ = antenna_positions(cfg, drive, t + dt)
    ve, vn = (pe1 - pe0) / (2 * dt), (pn1 - pn0) / (2 * dt)
    speed = np.hypot(ve, vn) * KMH_PER_MS
    course = np.degrees(np.arctan2(ve, vn)) % 360.0
    be, bn, bu = se - pe, sn - pn, su - pu
    azimuth = np.degrees(np.arctan2(be, bn)) % 360.0
    elevation = np.degrees(np.arctan2(bu, np.hypot(be, bn)))
    lat0, lon0, h0 = cfg.origin
    lat, lon, alt = pymap3d.enu2geodetic(pe + err_e, pn + err_n, pu + err_u, lat0, lon0, h0)
    # the machine heading the baseline implies, for the oracle's heading error
    offset = -90.0 if cfg.machine.baseline == "side_by_side" else 0.0
    true_h = h % 360.0
    out = []
    for i in range(count):
        if any(a <= t[i] < a + d for a, d in rx.dropout_windows):
            continue
        rep_h = (azimuth[i] + err_h[i]) % 360.0
        out.append(ReceiverEpoch(
            k=int(k_all[i]), t=float(t[i]),
            utc=cfg.utc_start + timedelta(milliseconds=round(float(t[i]) * 1000.0)),
            t_host=float(t_host[i]), lat=float(lat[i]), lon=float(lon[i]),
            alt_msl_m=float(alt[i]) - GEOID_SEP_M,
            speed_kmh=max(0.0, float(speed[i] + err_v[i])), course_deg=float(course[i]),
            heading_deg=float(rep_h), pitch_deg=float(elevation[i] + err_p[i]),
            fix=fix[i], err_east_m=float(err_e[i]), err_north_m=float(err_n[i]),
            err_heading_deg=float(((rep_h + offset - true_h[i] + 180.0) % 360.0) - 180.0),
        ))
    return out


def epoch_lines(ep: ReceiverEpoch) -> list[str]:
    """The epoch as the UM982 prints it: $GNRMC, $GNGGA and #HEADINGA (with its pitch)."""
    return epoch_sentences(
        ep.utc, ep.lat, ep.lon, ep.alt_msl_m, ep.speed_kmh, ep.course_deg, ep.heading_deg,
        ep.fix, pitch_deg=ep.pitch_deg, hdg_std=0.08,
    )


def _edges(cfg: FieldConfig, drive: FieldDrive) -> tuple[Array, npt.NDArray[np.intp]]:
    """True edge instants and rows: seeds metered per distance while lowered and moving."""
    met = cfg.metering
    rng = _rng(cfg.seed, "metering")
    sowing = drive.lowered[1:] & (drive.v[1:] * KMH_PER_MS >= SOWING_MIN_KMH)
    step = np.hypot(np.diff(drive.e), np.diff(drive.n)) * sowing
    dist = np.concatenate(([0.0], np.cumsum(step)))
    total = dist[-1]
    times: list[Array] = []
    rows: list[npt.NDArray[np.intp]] = []
    for r in range(1, len(cfg.machine.row_lateral_m) + 1):
        count = int(total / met.spacing_m * 1.3) + 10
        gaps = met.spacing_m * np.maximum(0.2, rng.normal(1.0, met.spacing_cv, count))
        at = rng.uniform(0.0, met.spacing_m) + np.concatenate(([0.0], np.cumsum(gaps[:-1])))
        at = at[at < total]
        keep = rng.random(len(at)) >= met.miss_prob
        at = at[keep]
        idx = np.searchsorted(dist, at, side="left")
        idx = np.clip(idx, 1, len(dist) - 1)
        d0, d1 = dist[idx - 1], dist[idx]
        a = np.where(d1 > d0, (at - d0) / np.where(d1 > d0, d1 - d0, 1.0), 0.0)
        te = drive.t[idx - 1] + a * (drive.t[idx] - drive.t[idx - 1])
        doubles = rng.random(len(te)) < met.double_prob
        extra = te[doubles] + rng.uniform(*met.double_gap_s, int(doubles.sum()))
        te = np.concatenate((te, extra))
        times.append(te)
        rows.append(np.full(len(te), r, dtype=np.intp))
    t_all = np.concatenate(times)
    r_all = np.concatenate(rows)
    order = np.argsort(t_all, kind="stable")
    return t_all[order], r_all[order]


def _land(
    cfg: FieldConfig, drive: FieldDrive, t_edge: Array, rows: npt.NDArray[np.intp],
    diameter: Array, friction: Array, retained_sq: Array | None,
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """(t_land, rest east, rest north, implement heading, ground speed at the edge,
    along-furrow slide) for seeds of the given properties; ``retained_sq`` None: the mean
    slide (the oracle's seed)."""
    _e, _n, _h, v_edge, _hi = drive.at(t_edge)
    t_tube, v_exit = tube_flight(v_edge, diameter, friction, cfg.lot, cfg.tube)
    beta = math.radians(90.0 - cfg.tube.angle_from_horizontal_deg)
    t_exit = t_edge + t_tube
    t_ff = free_fall_s(cfg.tube.outlet_height_m, v_exit * math.cos(beta))
    t_land = t_exit + t_ff
    oe, on, hi = outlet_positions(cfg, drive, t_exit, rows)
    _e, _n, _h, v_exit_ground, _ = drive.at(t_exit)
    u_h = v_exit_ground - v_exit * math.sin(beta)  # seed's forward velocity over the ground
    psi = np.radians(hi)
    fe, fn = np.sin(psi), np.cos(psi)
    if retained_sq is None:
        slide = cfg.furrow.mean_slide_m(u_h)
    else:
        slide = np.sign(u_h) * u_h * u_h * retained_sq / (2.0 * cfg.furrow.friction * GRAVITY)
    along = u_h * t_ff + slide
    return t_land, oe + along * fe, on + along * fn, hi, v_edge, slide


def mean_fall_time_s(cfg: FieldConfig, speed_kmh: Array) -> Array:
    """Sensor edge to touchdown for a mean seed of the lot at a steady ground speed: what a
    perfectly measured fall-time table for this lot and tube would say."""
    v = np.asarray(speed_kmh, float) / KMH_PER_MS
    ones = np.ones_like(v)
    t_tube, v_exit = tube_flight(
        v, cfg.lot.diameter_m * ones, cfg.lot.wall_friction * ones, cfg.lot, cfg.tube
    )
    beta = math.radians(90.0 - cfg.tube.angle_from_horizontal_deg)
    return np.asarray(t_tube + free_fall_s(cfg.tube.outlet_height_m, v_exit * math.cos(beta)))


@functools.lru_cache(maxsize=4)
def _field_drive(spec: DriveSpec, machine: Machine) -> FieldDrive:
    """The drive of ``spec`` with ``machine``: a pure function of the two, kept for the next
    run of the same field (sensitivity rows change the seeds or the receiver, not the
    drive; building it is a tenth of a run)."""
    return FieldDrive(spec, machine)


def simulate(cfg: FieldConfig | None = None) -> FieldRun:
    """Drive the field: receiver epochs and seeds (truth and host-stamped edges)."""
    cfg = cfg or FieldConfig()
    drive = _field_drive(cfg.drive, cfg.machine)
    epochs = _receiver_epochs(cfg, drive)
    t_edge, rows = _edges(cfg, drive)
    lrng = _rng(cfg.seed, "lot")
    lot = cfg.lot
    diameter = lot.diameter_m * np.maximum(0.5, 1.0 + lrng.normal(0.0, lot.diameter_cv,
                                                                   len(t_edge)))
    friction = np.clip(lrng.normal(lot.wall_friction, lot.wall_friction_sd, len(t_edge)),
                       0.0, 1.5)
    frng = _rng(cfg.seed, "furrow")
    retained = frng.uniform(*cfg.furrow.retained, len(t_edge))
    t_land, east, north, hi, v_edge, slide = _land(
        cfg, drive, t_edge, rows, diameter, friction, retained * retained
    )
    psi = np.radians(hi)
    b_along = frng.normal(0.0, cfg.furrow.bounce_along_sd_m, len(t_edge))
    b_across = frng.normal(0.0, cfg.furrow.bounce_across_sd_m, len(t_edge))
    east = east + b_along * np.sin(psi) + b_across * np.cos(psi)
    north = north + b_along * np.cos(psi) - b_across * np.sin(psi)
    ones = np.ones_like(t_edge)
    x_land, x_east, x_north, *_ = _land(
        cfg, drive, t_edge, rows, lot.diameter_m * ones, lot.wall_friction * ones, None
    )
    _e, _n, h_land, _v, hi_land = drive.at(t_land)
    ge, gn, gh, *_ = drive.at(t_land)
    _p, roll = cfg.terrain.attitude(ge, gn, gh)
    timing = cfg.timing
    trng = _rng(cfg.seed, "edges")
    t_host = timing.host(t_edge + timing.sensor_latency_s + timing.line_s) + trng.uniform(
        0.0, timing.edge_jitter_s, len(t_edge)
    )
    keep = t_land < drive.duration_s
    passes = drive.pass_of(t_edge)
    seeds = [
        Seed(
            row=int(rows[i]), t_edge=float(t_edge[i]), t_host=float(t_host[i]),
            t_land=float(t_land[i]), east=float(east[i]), north=float(north[i]),
            expected_t_land=float(x_land[i]), expected_east=float(x_east[i]),
            expected_north=float(x_north[i]), pass_index=int(passes[i]),
            speed_kmh=float(v_edge[i] * KMH_PER_MS),
            articulation_deg=float(hi_land[i] - h_land[i]), roll_deg=float(roll[i]),
            slide_m=float(slide[i]),
        )
        for i in np.flatnonzero(keep)
    ]
    seeds.sort(key=lambda s: s.t_host)
    return FieldRun(cfg, drive, epochs, seeds)


def survey(run: FieldRun, seeds: Sequence[Seed], sigma_m: float = 0.005) -> list[
    tuple[float, float]
]:
    """Surveyed (lat, lon) of ``seeds``: the rest point plus an RTK rover's pole error."""
    rng = _rng(run.config.seed, "survey")
    e = np.array([s.east for s in seeds]) + rng.normal(0.0, sigma_m, len(seeds))
    n = np.array([s.north for s in seeds]) + rng.normal(0.0, sigma_m, len(seeds))
    lat, lon = run.to_geodetic(e, n)
    return list(zip(lat.tolist(), lon.tolist(), strict=True))
