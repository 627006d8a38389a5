"""The whole seeder in software: every device the daemon talks to, on real pty pairs.

``SimulatedMachine`` starts the RS485 bus (radar, inclinometer, PWM module), the touchscreen,
and optionally the UM982 receiver and the seed-tube sensors, all driven by one plant model
running in (real) simulated time, and hands out a config that points the daemon at them.
It keeps ground truth: seed mass really discharged, area really covered, seeds really landed.
Used by ``sowgate demo``, the integration tests and the benchmarks.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from drivers.tasks import StartClose, cancel_and_wait
from gateway.config import Settings, parse_config
from simulator.hmi_peer import HmiPeer
from simulator.modbus_devices import Rs485Simulator
from simulator.plant import (
    KMH_PER_MS,
    Drive,
    HopperTruth,
    MeteringPlant,
    Pose,
    SensorNoise,
    demo_drive,
)

PLANT_STEP_S = 0.01
GNSS_OUTPUT_LATENCY_S = 0.02  # the emulated UM982's delay from epoch to sentence
SEED_SPACING_M = 0.2
# A ~45 deg N field near Wuhan-like latitudes is not needed: any origin works; pick paper C's
# region (Jilin maize) so latitudes are realistic.
ORIGIN_LAT = 43.8
ORIGIN_LON = 125.3
# Each stretch of sowing (openers in the soil and moving) starts with a transient no speed
# follower can avoid: from standstill or a lowering, the 12-sample speed filter (4 s at 3 Hz)
# and the motor's spin-up lag the true speed. ``Truth`` keeps what is applied after this
# much continuous sowing apart, so a short demo is not judged by its first metres alone.
STARTUP_TRANSIENT_S = 5.0


def _kg_ha(mass_g: float, area_m2: float) -> float:
    return 0.0 if area_m2 <= 0 else mass_g / 1000 / (area_m2 / 1e4)


@dataclass
class Truth:
    """What really happened, for accuracy checks."""

    mass_g: float = 0.0
    mass_while_seeding_g: float = 0.0
    area_m2: float = 0.0  # lowered and moving
    distance_m: float = 0.0
    mass_wasted_g: float = 0.0  # discharged while raised or standing
    sown_m: float = 0.0  # travelled lowered and moving
    # the same, counted only after STARTUP_TRANSIENT_S of continuous sowing
    settled_mass_g: float = 0.0
    settled_area_m2: float = 0.0
    settled_m: float = 0.0
    sowing_for_s: float = 0.0  # length of the current stretch of sowing

    def record(self, grams: float, moved_m: float, dt: float, sowing: bool, width_m: float) -> None:
        """Account one plant step: ``grams`` discharged while travelling ``moved_m``."""
        self.mass_g += grams
        self.distance_m += moved_m
        if not sowing:
            self.mass_wasted_g += grams
            self.sowing_for_s = 0.0
            return
        self.mass_while_seeding_g += grams
        self.area_m2 += moved_m * width_m
        self.sown_m += moved_m
        if self.sowing_for_s >= STARTUP_TRANSIENT_S - 1e-9:  # summed steps drift
            self.settled_mass_g += grams
            self.settled_area_m2 += moved_m * width_m
            self.settled_m += moved_m
        self.sowing_for_s += dt

    def applied_kg_ha(self) -> float:
        """Everything discharged over everything sown, start-up transients included."""
        return _kg_ha(self.mass_while_seeding_g, self.area_m2)

    def settled_kg_ha(self) -> float:
        """The same after the first STARTUP_TRANSIENT_S of every stretch of sowing."""
        return _kg_ha(self.settled_mass_g, self.settled_area_m2)


@dataclass
class SimulatedMachine(StartClose):
    drive: Drive = field(default_factory=demo_drive)
    crop: str = "rapeseed"
    noise: SensorNoise = field(default_factory=SensorNoise)
    seed: int = 1
    loop_drive: bool = False
    with_gnss: bool = False
    # the receiver's UTC at the start (None: now); e.g. 1024 weeks early for a receiver past a
    # GPS week rollover, or just before a UTC midnight where a leap second can be inserted
    gnss_utc_start: datetime | None = None
    with_seed_tubes: bool = False
    discharge_bias: float = 0.0  # plant discharge off the fitted model by this fraction
    pwm_watchdog: bool = True  # False: a PWM module without a comm-loss timeout register
    # a hopper on load cells, read by a weight transmitter on the RS485 bus ([hopper_scale])
    hopper: HopperTruth | None = None
    settings_overrides: dict[str, Any] = field(default_factory=dict)
    # Terrain and the receiver's mounting: a side slope (positive = right side down), the
    # antenna's height above the ground, and how the two antennas sit (gnss.heading_offset_deg:
    # 90 = secondary on the left, so #HEADINGA's pitch is the roll). The drive's pose is the
    # ground point below the antenna; the seeds land on the rolled ground.
    roll_deg: float = 0.0
    antenna_height_m: float = 0.0
    heading_offset_deg: float = 0.0

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)
        self.truth = Truth()
        # the machine being simulated: the daemon's own config (settings_overrides included),
        # so the seed tubes' outlets and the truth's width are those the daemon works with
        self.base_settings = parse_config(_merged({}, self.settings_overrides))
        model = self.base_settings.control.crops[self.crop]
        self.plant = MeteringPlant(
            slope=model.motor_slope,
            intercept=model.motor_intercept,
            startup_duty_pct=model.startup_duty_pct,
            meter_a=model.meter_a * (1 + self.discharge_bias),
            meter_b=model.meter_b * (1 + self.discharge_bias),
            meter_c=model.meter_c * (1 + self.discharge_bias),
            rng=random.Random(self.seed + 1),
        )
        self.fan_pct = 0.0
        self.rs485: Rs485Simulator | None = None
        self.hmi: HmiPeer | None = None
        self.gnss: Any = None
        self.seed_tubes: Any = None
        self._t0 = 0.0
        self._task: asyncio.Task[None] | None = None
        self._stack = contextlib.AsyncExitStack()

    # ---- time and truth ----------------------------------------------------------------------
    def now(self) -> float:
        """Simulated time (s) since start."""
        t = asyncio.get_running_loop().time() - self._t0
        if self.loop_drive:
            t %= self.drive.duration_s
        return t

    def pose(self) -> Pose:
        return self.drive.pose_at(self.now())

    def pose_at(self, t: float) -> Pose:
        return self.drive.pose_at(t % self.drive.duration_s if self.loop_drive else t)

    def radar_kmh(self) -> float:
        v = self.pose().speed_kmh
        return max(0.0, v * (1.0 + self.rng.gauss(0.0, self.noise.radar_cv))) if v > 0 else 0.0

    def tilt_deg(self) -> float:
        p = self.pose()
        return (
            p.tilt_deg
            + self.noise.tilt_mount_deg
            + self.noise.tilt_offset_deg
            + self.rng.gauss(0.0, self.noise.tilt_sigma_deg)
        )

    def hopper_reading_kg(self) -> float:
        """What the weight transmitter reads now: the true hopper mass plus vibration (and
        the field's disturbances, given the tractor's acceleration and the fan duty)."""
        assert self.hopper is not None
        now = self.now()
        accel = (self.pose_at(now).speed_kmh
                 - self.pose_at(max(0.0, now - 0.5)).speed_kmh) / KMH_PER_MS / 0.5
        return self.hopper.reading_kg(now, self.plant.mass_g / 1000.0, accel_ms2=accel,
                                      fan_pct=self.fan_pct)

    def roll_reading(self) -> float:
        """The inclinometer's roll axis: the side slope, with the tilt axis's noise."""
        return self.roll_deg + self.rng.gauss(0.0, self.noise.tilt_sigma_deg)

    def on_duty(self, channel: str, pct: float) -> None:
        if channel == "motor":
            self.plant.duty_pct = pct
        elif channel == "fan":
            self.fan_pct = pct

    async def _run_plant(self) -> None:
        last = self.now()
        while True:
            await asyncio.sleep(PLANT_STEP_S)
            now = self.now()
            dt = now - last if now >= last else PLANT_STEP_S
            last = now
            grams = self.plant.step(dt)
            p = self.drive.pose_at(now)
            self.truth.record(
                grams,
                p.speed_kmh / 3.6 * dt,
                dt,
                sowing=p.tilt_deg < 0.0 and p.speed_kmh > 0.05,  # openers in the soil
                width_m=self.base_settings.machine.working_width_m,
            )

    # ---- lifecycle -----------------------------------------------------------------------------
    async def start(self) -> None:
        self._t0 = asyncio.get_running_loop().time()
        try:
            self.rs485 = await self._stack.enter_async_context(
                Rs485Simulator(
                    radar_kmh=self.radar_kmh,
                    tilt_deg=self.tilt_deg,
                    on_duty=self.on_duty,
                    rng=random.Random(self.seed + 2),
                    pwm_watchdog=self.pwm_watchdog,
                    hopper_kg=self.hopper_reading_kg if self.hopper is not None else None,
                    hopper=self.base_settings.hopper_scale,
                    # (level ground: the roll axis reads 0 and draws no noise, as before)
                    roll_deg=self.roll_reading if self.roll_deg else None,
                )
            )
            self.hmi = await self._stack.enter_async_context(HmiPeer())
            if self.with_gnss:
                await self._start_gnss()
            if self.with_seed_tubes:
                await self._start_seed_tubes()
            self._task = asyncio.create_task(self._run_plant(), name="sim-plant")
        except BaseException:
            await self._stack.aclose()
            raise

    async def _start_gnss(self) -> None:
        from simulator.um982 import Um982Emulator

        self.gnss = await self._stack.enter_async_context(
            Um982Emulator(
                self.pose_at,
                origin_lat=ORIGIN_LAT,
                origin_lon=ORIGIN_LON,
                output_latency_s=GNSS_OUTPUT_LATENCY_S,
                seed=self.seed + 3,
                t0_mono=self._t0,
                antenna_height_m=self.antenna_height_m,
                roll_deg=self.roll_deg,
                heading_offset_deg=self.heading_offset_deg,
                utc_start=self.gnss_utc_start,
            )
        )

    async def _start_seed_tubes(self) -> None:
        from simulator.seed_tubes import PlanterModel, SeedTubeEmulator

        positioning = self.base_settings.positioning.model_copy(
            update={"target_spacing_m": SEED_SPACING_M}
        )
        model = PlanterModel.from_positioning(positioning, roll_deg=self.roll_deg)
        self.seed_tubes = await self._stack.enter_async_context(
            SeedTubeEmulator(self.drive, model, seed=self.seed + 4, t0_mono=self._t0)
        )

    async def close(self) -> None:
        await cancel_and_wait(self._task)
        await self._stack.aclose()

    # ---- config for the daemon -------------------------------------------------------------------
    def config(self, **overrides: Any) -> dict[str, Any]:
        assert self.rs485 is not None and self.hmi is not None
        model = self.base_settings.control.crops[self.crop]
        data: dict[str, Any] = {
            "rs485": {"port": self.rs485.device_path, "timeout_s": 0.2, "reconnect_max_s": 1.0},
            "inclinometer": {"zero_offset_deg": self.noise.tilt_mount_deg},
            "hmi": {"port": self.hmi.device_path},
            "control": {"crop": self.crop, "rate_kg_ha": model.default_rate_kg_ha},
        }
        if self.hopper is not None:
            data["hopper_scale"] = {"enabled": True}
        if self.gnss is not None:
            data["gnss"] = {"enabled": True, "port": self.gnss.device_path}
            if self.heading_offset_deg:
                data["gnss"]["heading_offset_deg"] = self.heading_offset_deg
            data["speed"] = {"source": "radar_then_gnss"}
            data["positioning"] = {
                "gnss_output_latency_ms": GNSS_OUTPUT_LATENCY_S * 1000,
                "target_spacing_m": SEED_SPACING_M,
            }
        if self.seed_tubes is not None:
            data["seed_sensors"] = {
                "enabled": True,
                "source": "serial",
                "port": self.seed_tubes.device_path,
            }
        return _merged(data, {**self.settings_overrides, **overrides})

    def settings(self, **overrides: Any) -> Settings:
        settings = parse_config(self.config(**overrides))
        self._check_same_planter(settings)
        return settings

    def write_config(self, path: Path, **overrides: Any) -> Path:
        import tomli_w

        data = self.config(**overrides)
        self._check_same_planter(parse_config(data))
        path.write_text(tomli_w.dumps(data))
        return path

    def _check_same_planter(self, daemon: Settings) -> None:
        """The running seed tubes' ground truth is the planter of ``base_settings``: a daemon
        given other rows or outlets (e.g. a ``machine.rows`` passed here, which also moves the
        derived row offsets) would be scored against a planter it does not have."""
        if self.seed_tubes is None:
            return

        def planter(s: Settings) -> tuple[object, ...]:
            p = s.positioning
            return (s.machine.rows, p.row_lateral_m, p.outlet_behind_antenna_m,
                    p.fall_time_table)

        if planter(daemon) != planter(self.base_settings):
            raise ValueError(
                "the daemon's rows/outlets differ from the simulated planter's: pass machine "
                "and positioning changes as SimulatedMachine(settings_overrides=...)"
            )


def _merged(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``data`` with each override table merged into its table (a non-table replaces it)."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    for section, values in overrides.items():
        if isinstance(values, dict):
            out.setdefault(section, {}).update(values)
        else:
            out[section] = values
    return out
