"""Paper B's metering controllers and a tractor, simulated on a CAN bus.

``MeterPlant`` is one channel: a PID controller (paper B: Kp 0.2, Ti 0.15 s, Td 0.15 s, 1 ms
cycle) driving a proportional valve into a hydraulic motor modelled as a first-order lag, and
a fluted roller whose delivered mass is g/rev x revolutions with flute pulsation and noise. It
is pure (advanced in simulated time), so benchmarks can run it faster than real time; the
inner loop always runs at 1 ms of simulated time, i.e. faster than any CAN rate.

``MeteringControllerSim`` puts several plants on a bus (one per node) answering with status
frames at 10-20 Hz. ``TractorSimulator`` sends ISO 11783-7 speeds and hitch every 100 ms.
Faults can be injected: go silent, report a fault code, stall the shaft.

PID units: error in r/min, output in valve % (0..100); the motor gives ``rpm_per_pct`` r/min
per valve %, so Kp 0.2 is a loop gain of 0.6 with the default 3 r/min/%.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import time
from dataclasses import dataclass, field

from drivers.can_bus import CanBus
from drivers.errors import DeviceUnavailable
from protocol import can_metering, isobus
from protocol.can_metering import FaultCode, MeterStatus
from protocol.errors import ProtocolError

PAPER_B_KP = 0.2
PAPER_B_TI_S = 0.15
PAPER_B_TD_S = 0.15
INNER_DT_S = 0.001  # paper B's 1 ms controller cycle
MASS_SEGMENT_REV = 0.1  # new delivery-noise draw every tenth of a revolution
STALL_DETECT_S = 0.5
AT_TARGET_PCT = 5.0


@dataclass
class MeterPlant:
    """PID + valve + hydraulic motor + fluted roller of one metering channel."""

    grams_per_rev: float  # per outlet, as weighed in paper B's calibration
    outlets: int = 1
    kp: float = PAPER_B_KP
    ti_s: float = PAPER_B_TI_S
    td_s: float = PAPER_B_TD_S
    tau_s: float = 0.08  # hydraulic motor + valve time constant
    rpm_per_pct: float = 3.0
    valve_deadband_pct: float = 3.0
    delivery_noise_pct: float = 1.5  # per-segment random spread of the delivered mass
    flutes: int = 12
    pulsation_pct: float = 4.0  # flute pulsation amplitude
    encoder_noise_rpm: float = 0.05
    command_timeout_s: float = 1.0
    rng: random.Random = field(default_factory=lambda: random.Random(7))
    # state
    target_rpm: float = 0.0
    enabled: bool = False
    rpm: float = 0.0
    valve_pct: float = 0.0
    revs: float = 0.0
    mass_g: float = 0.0
    sim_time_s: float = 0.0
    last_command_s: float | None = None
    sequence_echo: int = 0
    # faults
    silent: bool = False
    stall: bool = False
    fault_code: FaultCode = FaultCode.NONE
    # the shaft cannot turn faster than this fraction of its target (a binding meter, too
    # little oil flow): the PID opens the valve and the shaft still lags; None: no limit
    held_fraction: float | None = None
    # the controller reports this multiple of the true shaft speed (a wrong pulses-per-rev
    # setting on its encoder input); its PID still regulates the true speed
    report_scale: float = 1.0
    # The truth of issue 25: a fluted roller's cells fill less as it turns faster, so the
    # grams per turn fall with shaft speed: by ``fill_fall`` from 10 to 60 r/min, along
    # ``((n/60)^p - (10/60)^p) / (1 - (10/60)^p)`` with ``fill_shape`` p (a power law, not
    # the controller's piecewise cubic; p < 1 falls early, p > 1 late), and ``lot_factor``
    # for the seed lot (grain size, moisture) against the one calibrated with.
    # ``grams_per_rev`` is the value at 10 r/min. Defaults: a constant g/rev.
    # ``fill_knee_rpm`` above 10: the cells fill fully up to this speed (g/rev flat) and the
    # power law runs from it to 60 r/min instead (a kink no set of knots sits on).
    fill_fall: float = 0.0
    fill_shape: float = 1.0
    fill_knee_rpm: float = 0.0
    lot_factor: float = 1.0
    # the controller's cycle; benchmarks that run thousands of simulated minutes may take
    # 5 ms (the loop stays stable: motor τ 80 ms, derivative filter 15 ms)
    inner_dt_s: float = INNER_DT_S
    _integral: float = 0.0
    _deriv: float = 0.0
    _prev_meas: float = 0.0
    _stall_timer: float = 0.0
    _segment_left: float = MASS_SEGMENT_REV
    _segment_factor: float = 1.0

    def command(self, target_rpm: float, enable: bool, sequence: int) -> None:
        self.target_rpm = target_rpm
        self.enabled = enable
        self.sequence_echo = sequence
        self.last_command_s = self.sim_time_s

    @property
    def effective_fault(self) -> FaultCode:
        if self.fault_code is not FaultCode.NONE:
            return self.fault_code
        if self._stall_timer >= STALL_DETECT_S:
            return FaultCode.STALL
        if self._timed_out():
            return FaultCode.COMMAND_TIMEOUT
        return FaultCode.NONE

    def _timed_out(self) -> bool:
        return self.last_command_s is not None and (
            self.sim_time_s - self.last_command_s > self.command_timeout_s
        )

    def _pid(self, setpoint: float, measured: float) -> float:
        dt = self.inner_dt_s
        err = setpoint - measured
        # derivative on measurement, filtered (Tf = Td/10), so target steps do not kick the valve
        tf = self.td_s / 10.0
        raw_d = -(measured - self._prev_meas) / dt
        self._deriv += (raw_d - self._deriv) * dt / (tf + dt)
        self._prev_meas = measured
        unclamped = self.kp * (err + self._integral / self.ti_s + self.td_s * self._deriv)
        out = min(100.0, max(0.0, unclamped))
        if out == unclamped or (unclamped > 100.0 and err < 0) or (unclamped < 0.0 and err > 0):
            self._integral += err * dt  # conditional integration = anti-windup
        return out

    def per_rev_g(self, rpm: float) -> float:
        """True grams per turn of one outlet at a shaft speed (the fill and the lot)."""
        p = self.fill_shape
        knee = self.fill_knee_rpm
        lo = math.pow(max(10.0, knee) / 60.0, p)
        shape = (math.pow(max(0.0, knee, rpm) / 60.0, p) - lo) / (1.0 - lo)
        return self.grams_per_rev * self.lot_factor * (1.0 - self.fill_fall * shape)

    def _deliver(self, drev: float) -> None:
        per_rev = (self.grams_per_rev * self.outlets if self.fill_fall == 0.0
                   and self.lot_factor == 1.0 else self.per_rev_g(self.rpm) * self.outlets)
        while drev > 0:
            step = min(drev, self._segment_left)
            phase = 2 * math.pi * self.flutes * (self.revs + step / 2)
            factor = self._segment_factor * (1 + self.pulsation_pct / 100 * math.sin(phase))
            self.mass_g += per_rev * step * factor
            self.revs += step
            drev -= step
            self._segment_left -= step
            if self._segment_left <= 1e-12:
                self._segment_left = MASS_SEGMENT_REV
                self._segment_factor = 1 + self.rng.gauss(0, self.delivery_noise_pct / 100)

    def advance(self, seconds: float) -> None:
        """Run the 1 ms inner loop for ``seconds`` of simulated time."""
        dt = self.inner_dt_s
        steps = max(0, round(seconds / dt))
        for _ in range(steps):
            self.sim_time_s += dt
            run = self.enabled and not self._timed_out() and self.fault_code is FaultCode.NONE
            setpoint = self.target_rpm if run else 0.0
            if setpoint <= 0.0:
                self.valve_pct, self._integral = 0.0, 0.0
            else:
                self.valve_pct = self._pid(setpoint, self.rpm)
            drive = max(0.0, self.valve_pct - self.valve_deadband_pct) * self.rpm_per_pct
            if self.stall:
                self.rpm = 0.0
            else:
                self.rpm += (drive - self.rpm) * dt / self.tau_s
                if self.held_fraction is not None:
                    self.rpm = min(self.rpm, self.held_fraction * setpoint)
            # valve well open but the shaft hardly turning: a jam (what a real RC detects)
            stalled_now = (
                setpoint > 0
                and self.valve_pct > 2 * self.valve_deadband_pct
                and self.rpm < 0.05 * setpoint
            )
            self._stall_timer = self._stall_timer + dt if stalled_now else 0.0
            if self.rpm > 0:
                self._deliver(self.rpm / 60.0 * dt)

    def measured_rpm(self) -> float:
        noisy = (self.rpm + self.rng.gauss(0, self.encoder_noise_rpm)) * self.report_scale
        return min(can_metering.SPEED_MAX_RPM, max(0.0, noisy))

    def status(self, node_id: int) -> MeterStatus:
        fault = self.effective_fault
        measured = self.measured_rpm()
        at_target = self.target_rpm > 0 and abs(measured - self.target_rpm) <= (
            AT_TARGET_PCT / 100 * self.target_rpm
        )
        return MeterStatus(
            node_id=node_id,
            measured_rpm=round(measured, 2),
            enabled=self.enabled,
            at_target=at_target,
            stalled=self._stall_timer >= STALL_DETECT_S,
            fault_active=fault is not FaultCode.NONE,
            fault=fault,
            raw_fault_code=int(fault) if fault is not FaultCode.UNKNOWN else 255,
            sequence_echo=self.sequence_echo,
            valve_pct=round(min(self.valve_pct, 127.5) * 2) / 2,
        )


class MeteringControllerSim:
    """Several metering controllers (node -> plant) answering on one CAN bus in real time."""

    def __init__(self, bus: CanBus, plants: dict[int, MeterPlant], *, status_hz: float = 20.0,
                 time_scale: float = 1.0) -> None:
        if not 10.0 <= status_hz <= 50.0:
            raise ValueError("status_hz should be 10..50 (paper B controllers answer at 10-20 Hz)")
        for node in plants:
            can_metering.status_id(node)
        self.bus = bus
        self.plants = plants
        self.status_period_s = 1.0 / status_hz
        self.time_scale = time_scale
        self.commands_received = 0

    def handle(self, arbitration_id: int, data: bytes) -> None:
        kind = can_metering.frame_kind(arbitration_id)
        if kind is None or kind[0] != "command" or kind[1] not in self.plants:
            return
        try:
            cmd = can_metering.decode_command(arbitration_id, data)
        except ProtocolError:
            return
        self.plants[cmd.node_id].command(cmd.target_rpm, cmd.enable, cmd.sequence)
        self.commands_received += 1

    async def _rx(self) -> None:
        while True:
            msg = await self.bus.recv()
            if msg is not None and not msg.is_extended_id:
                self.handle(msg.arbitration_id, bytes(msg.data))

    async def _tx(self) -> None:
        last = time.monotonic()
        while True:
            await asyncio.sleep(self.status_period_s)
            now = time.monotonic()
            for plant in self.plants.values():
                plant.advance((now - last) * self.time_scale)
            last = now
            for node, plant in self.plants.items():
                if plant.silent:
                    continue
                frame_id, data = can_metering.encode_status(plant.status(node))
                with contextlib.suppress(DeviceUnavailable):
                    await self.bus.send(frame_id, data)

    async def run(self) -> None:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._rx(), name="sim-meter-rx")
            tg.create_task(self._tx(), name="sim-meter-tx")


@dataclass
class TractorSimulator:
    """A tractor ECU sending ISO 11783-7 speeds and rear hitch status every 100 ms."""

    bus: CanBus
    speed_kmh: float = 0.0
    direction: isobus.Direction = isobus.Direction.FORWARD
    hitch_pct: float | None = 20.0
    in_work: isobus.InWork = isobus.InWork.IN_WORK
    source_address: int = 0xF0
    period_s: float = 0.1
    silent: bool = False
    raw_speed_override: dict[int, int] = field(default_factory=dict)  # pgn -> raw code
    distance_m: float = 0.0

    def frames(self) -> list[tuple[int, bytes]]:
        out = []
        for pgn in isobus.SPEED_PGNS:
            data = isobus.encode_speed(
                pgn, self.speed_kmh / 3.6, self.direction, self.distance_m,
                raw_speed=self.raw_speed_override.get(pgn),
            )
            out.append((isobus.build_can_id(pgn, self.source_address), data))
        out.append((
            isobus.build_can_id(isobus.PGN_REAR_HITCH, self.source_address),
            isobus.encode_hitch(self.hitch_pct, self.in_work),
        ))
        return out

    async def run(self) -> None:
        while True:
            if not self.silent:
                for can_id, data in self.frames():
                    with contextlib.suppress(DeviceUnavailable):
                        await self.bus.send(can_id, data, extended=True)
            await asyncio.sleep(self.period_s)
            self.distance_m += self.speed_kmh / 3.6 * self.period_s
