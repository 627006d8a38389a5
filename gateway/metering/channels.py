"""Multi-channel metering (paper B): rate -> shaft speed per channel, supervision, the loop.

Each channel (shallow fertiliser, deep fertiliser, seed, ...) has its own target rate, shaft
command, feedback and alarms; all follow the one work state: raised -> every target 0.

Rate relation: a shaft turning n r/min with m_total g/rev (g/rev per outlet x outlets) delivers
n*m_total g/min over B*V/600 ha/min (B m, V km/h), so ``n = G*B*V / (0.6*m_total)``.
Paper B prints ``G = 100*n/(9*v)`` (v m/s) for "2.55 m, 10 rows x 15 g/rev"; our relation gives
that constant for B = 2.25 m (10 rows at 225 mm), and 9.80*n/v for 2.55 m, so the paper's
constant evidently uses the sown width, not the frame width. Configure the sown width.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Literal

from drivers.can_bus import CanBus, MeteringCanLink
from drivers.errors import DriverError
from gateway.config import ChannelSection, Settings
from gateway.core.errors import CommandError, RateError
from gateway.core.monotone import MonotoneCurve, cached_curve
from gateway.metering.prescription import AsAppliedLog, Pose, PrescriptionMap
from protocol.can_metering import MeterStatus

log = logging.getLogger(__name__)

HA_FACTOR = 0.6  # kg/ha = 0.6 * g/min / (m * km/h)
AS_APPLIED_PERIOD_S = 1.0
MAX_RATE_KG_HA = 2000.0  # as [[channel]] target_rate_kg_ha
STOP_SEND_TIMEOUT_S = 0.2
AlarmKind = Literal[
    "feedback_lost", "off_target", "controller_fault", "too_fast", "impossible_speed"
]


def target_shaft_rpm(rate_kg_ha: float, speed_kmh: float, width_m: float,
                     grams_per_rev_total: float) -> float:
    """Shaft speed that lays ``rate_kg_ha`` at ``speed_kmh`` over ``width_m``."""
    if grams_per_rev_total <= 0 or width_m <= 0:
        raise RateError("grams per revolution and width must be positive")
    if rate_kg_ha < 0 or speed_kmh < 0:
        raise RateError("rate and speed must not be negative")
    return rate_kg_ha * width_m * speed_kmh / (HA_FACTOR * grams_per_rev_total)


def rate_from_shaft(rpm: float, speed_kmh: float, width_m: float,
                    grams_per_rev_total: float) -> float | None:
    """Rate a shaft speed lays down; None when standing (no area covered)."""
    if speed_kmh <= 0 or width_m <= 0:
        return None
    return HA_FACTOR * rpm * grams_per_rev_total / (width_m * speed_kmh)


def _flow_curve(ch: ChannelSection) -> MonotoneCurve | None:
    """Delivered g/min of the whole channel against r/min, from its g/rev curve (through 0)."""
    if ch.grams_per_rev_curve is None:
        return None
    return cached_curve(((0.0, 0.0), *((float(n), float(n) * float(g) * ch.outlets)
                                       for n, g in ch.grams_per_rev_curve)))


def channel_target_rpm(ch: ChannelSection, rate_kg_ha: float, speed_kmh: float,
                       width_m: float) -> float:
    """``target_shaft_rpm`` with the channel's own g/rev: constant, or its curve against
    shaft speed (a meter whose g/rev falls 20 % from 10 to 60 r/min, issue 25)."""
    curve = _flow_curve(ch)
    if curve is None:
        return target_shaft_rpm(rate_kg_ha, speed_kmh, width_m, ch.grams_per_rev * ch.outlets)
    if rate_kg_ha < 0 or speed_kmh < 0 or width_m <= 0:
        raise RateError("rate and speed must not be negative, width positive")
    return max(0.0, curve.inverse(rate_kg_ha * width_m * speed_kmh / HA_FACTOR))


def channel_rate(ch: ChannelSection, rpm: float, speed_kmh: float,
                 width_m: float) -> float | None:
    """``rate_from_shaft`` with the channel's own g/rev (constant or its curve)."""
    curve = _flow_curve(ch)
    if curve is None:
        return rate_from_shaft(rpm, speed_kmh, width_m, ch.grams_per_rev * ch.outlets)
    if speed_kmh <= 0 or width_m <= 0:
        return None
    return HA_FACTOR * max(0.0, curve(rpm)) / (width_m * speed_kmh)


@dataclass(frozen=True, slots=True)
class ChannelAlarm:
    channel: str
    kind: AlarmKind
    active: bool  # False: the condition cleared
    message: str
    since: float


# Off target is judged on revolutions asked against revolutions delivered over the last
# ``off_target_s`` (a sliding window), not on the instantaneous speed: the target moves on
# every poll with the radar's noise (every ~0.3 s), so a timer restarted on each target change
# never ran out, and a shaft held at half its target for minutes raised nothing. Integrated,
# the radar's noise averages out and a PID's lag after a change costs only its lag over the
# window (0.3 s behind a 20 % step over 3 s: 2 %).
# The shaft follows its target this much later (the command frame's trip, the controller's
# PID and valve, the status frame's trip back): the revolutions delivered over the window are
# compared with those asked over the window this much earlier, so an acceleration (the target
# ramping for seconds after a headland turn) is not read as a shortfall of lag x slope.
RESPONSE_LAG_S = 0.3
# After a start (target from 0), the window opens this long after the shaft was told to turn,
# so the spin-up is not counted as a shortfall.
SETTLE_AFTER_START_S = 1.0
# The windowed error must stay beyond ``off_target_pct`` this long before it alarms (a single
# evaluation over the limit after a hard stop of the tractor is not a fault).
OFF_TARGET_HOLD_S = 1.0
# A shaft reported faster than its ``max_shaft_rpm`` by this factor cannot be: the motor is
# sized for that speed. A wrong encoder setting (pulses per revolution), a corrupt frame or
# another node's id; its speed cannot be trusted. Held this long before it alarms.
IMPOSSIBLE_SPEED_FACTOR = 1.5
IMPOSSIBLE_SPEED_HOLD_S = 0.5


@dataclass
class _Watch:
    """One channel's supervision state: the latest target and feedback, and the running
    integrals of revolutions asked and delivered (``_integrate``) sampled into ``window``."""

    target_rpm: float = 0.0
    measured_rpm: float | None = None
    feedback_at: float | None = None
    fault: str | None = None
    max_rpm: float | None = None
    asked_revs: float = 0.0
    delivered_revs: float = 0.0
    integrated_to: float | None = None
    running_since: float | None = None  # target >= min_target_rpm, feedback fresh, since
    window: deque[tuple[float, float, float]] = field(default_factory=deque)
    off_since: float | None = None
    stopped_turning_since: float | None = None
    impossible_since: float | None = None
    active: dict[str, ChannelAlarm] = field(default_factory=dict)


def _at(window: deque[tuple[float, float, float]], t: float, column: int) -> float:
    """A running integral of ``window`` (samples ``(t, asked, delivered)`` in time order)
    at ``t``, linear between the samples around it."""
    prev = window[0]
    for sample in window:
        if sample[0] >= t:
            if sample[0] == prev[0]:
                return sample[column]
            f = (t - prev[0]) / (sample[0] - prev[0])
            return prev[column] + f * (sample[column] - prev[column])
        prev = sample
    return prev[column]


class ChannelSupervisor:
    """Alarm logic for every channel, fed timestamps (pure: no clock, no I/O).

    - feedback lost: no status for more than ``feedback_timeout_s`` (since start or last frame)
    - off target: over the last ``off_target_s`` the shaft delivered more or fewer
      revolutions than it was asked for (over the same span ``RESPONSE_LAG_S`` earlier) by
      more than ``off_target_pct`` % (targets and feedback integrated over time, so a target
      that moves on every poll is judged like a steady one), held ``OFF_TARGET_HOLD_S``; or
      it turns (above ``min_target_rpm``) for
      ``off_target_s`` while told to stop
    - impossible speed: the reported shaft speed exceeds ``IMPOSSIBLE_SPEED_FACTOR`` x the
      channel's maximum (``max_rpm``), which no motor sized for it can do
    - controller fault: the controller reports a fault code
    - too fast: the shaft speed needed exceeds the channel's maximum (set by the caller)
    """

    def __init__(self, channels: Sequence[str], *, feedback_timeout_s: float = 1.0,
                 off_target_pct: float = 5.0, off_target_s: float = 3.0,
                 min_target_rpm: float = 1.0, start: float = 0.0,
                 max_rpm: Mapping[str, float] | None = None) -> None:
        self.feedback_timeout_s = feedback_timeout_s
        self.off_target_pct = off_target_pct
        self.off_target_s = off_target_s
        self.min_target_rpm = min_target_rpm
        limits = max_rpm or {}
        self._w = {name: _Watch(max_rpm=limits.get(name)) for name in channels}
        self._start = start
        self._too_fast: dict[str, str | None] = dict.fromkeys(channels)

    def _integrate(self, w: _Watch, t: float) -> None:
        """Advance the asked and delivered integrals to ``t`` with the values held since
        the last call (targets and feedback are piecewise constant between frames)."""
        last = w.integrated_to
        if last is not None and t > last:
            dt_min = (t - last) / 60.0
            w.asked_revs += w.target_rpm * dt_min
            if w.measured_rpm is not None:
                w.delivered_revs += w.measured_rpm * dt_min
        if last is None or t > last:
            w.integrated_to = t

    def command(self, channel: str, target_rpm: float, t: float) -> None:
        w = self._w[channel]
        self._integrate(w, t)
        w.target_rpm = target_rpm

    def feedback(self, channel: str, measured_rpm: float, t: float,
                 fault: str | None = None) -> None:
        w = self._w[channel]
        self._integrate(w, t)
        w.measured_rpm, w.feedback_at, w.fault = measured_rpm, t, fault

    def too_fast(self, channel: str, message: str | None) -> None:
        self._too_fast[channel] = message

    def _windowed(self, w: _Watch, t: float, fresh: bool) -> tuple[float, float] | None:
        """(revolutions asked, delivered) over the last ``off_target_s`` while running, or
        None while the window is not yet full (stopped, just started, feedback missing)."""
        self._integrate(w, t)
        running = fresh and w.target_rpm >= self.min_target_rpm
        if not running:
            w.running_since = None
            w.window.clear()
            return None
        if w.running_since is None:
            w.running_since = t
        if t - w.running_since < SETTLE_AFTER_START_S:
            return None
        window = w.window
        window.append((t, w.asked_revs, w.delivered_revs))
        span = self.off_target_s + RESPONSE_LAG_S
        while len(window) > 1 and window[1][0] <= t - span:
            window.popleft()
        if t - window[0][0] < span - 1e-9:
            return None
        asked = _at(window, t - RESPONSE_LAG_S, 1) - _at(window, t - span, 1)
        delivered = w.delivered_revs - _at(window, t - self.off_target_s, 2)
        return asked, delivered

    def _conditions(self, name: str, w: _Watch, t: float) -> dict[AlarmKind, str]:
        out: dict[AlarmKind, str] = {}
        last = w.feedback_at if w.feedback_at is not None else self._start
        if t - last > self.feedback_timeout_s:
            out["feedback_lost"] = f"{name}: no shaft feedback for {t - last:.1f} s"
        elif w.fault:
            out["controller_fault"] = f"{name}: controller fault {w.fault}"
        fresh = w.feedback_at is not None and t - w.feedback_at <= self.feedback_timeout_s
        measured = w.measured_rpm if fresh else None
        if measured is not None and w.max_rpm is not None and (
            measured > IMPOSSIBLE_SPEED_FACTOR * w.max_rpm
        ):
            w.impossible_since = t if w.impossible_since is None else w.impossible_since
            if t - w.impossible_since >= IMPOSSIBLE_SPEED_HOLD_S:
                out["impossible_speed"] = (
                    f"{name}: controller reports the shaft at {measured:.0f} r/min, beyond "
                    f"what its motor can do (max_shaft_rpm {w.max_rpm:g}): its speed "
                    "sensor or settings are wrong, the rate is not known"
                )
        else:
            w.impossible_since = None
        window = self._windowed(w, t, fresh)
        off = None
        if window is not None:
            asked, delivered = window
            if asked > 0 and abs(delivered - asked) > self.off_target_pct / 100 * asked:
                off = (
                    f"{name}: shaft delivered {delivered:.2f} rev against {asked:.2f} asked "
                    f"over the last {self.off_target_s:g} s ({(delivered / asked - 1):+.0%})"
                )
        if off is not None:
            w.off_since = t if w.off_since is None else w.off_since
            if t - w.off_since >= OFF_TARGET_HOLD_S:
                out["off_target"] = off
        else:
            w.off_since = None
        # turning when told to stop
        if measured is not None and w.target_rpm < self.min_target_rpm and (
            measured > max(self.min_target_rpm, 1.0)
        ):
            since = w.stopped_turning_since
            w.stopped_turning_since = t if since is None else since
            if t - w.stopped_turning_since > self.off_target_s:
                out["off_target"] = (
                    f"{name}: shaft {measured:.1f} r/min while commanded to stop, for "
                    f"{t - w.stopped_turning_since:.1f} s"
                )
        else:
            w.stopped_turning_since = None
        msg = self._too_fast.get(name)
        if msg:
            out["too_fast"] = msg
        return out

    def evaluate(self, t: float) -> list[ChannelAlarm]:
        """Alarms that changed (raised or cleared) since the last call."""
        changes: list[ChannelAlarm] = []
        for name, w in self._w.items():
            now = self._conditions(name, w, t)
            for kind, msg in now.items():
                if kind not in w.active:
                    w.active[kind] = ChannelAlarm(name, kind, True, msg, t)
                    changes.append(w.active[kind])
            for old in list(w.active.values()):
                if old.kind not in now:
                    del w.active[old.kind]
                    changes.append(
                        ChannelAlarm(name, old.kind, False, f"{name}: {old.kind} cleared", t)
                    )
        return changes

    def active(self, channel: str | None = None) -> list[ChannelAlarm]:
        names = [channel] if channel else list(self._w)
        return [a for n in names for a in self._w[n].active.values()]


@dataclass
class ChannelState:
    """What the component last decided and saw for one channel (telemetry)."""

    name: str
    product: str
    node_id: int
    target_rate_kg_ha: float = 0.0
    target_rpm: float = 0.0
    measured_rpm: float | None = None
    applied_rate_kg_ha: float | None = None
    fault: str | None = None


@dataclass(frozen=True, slots=True)
class ChannelStatus:
    """One CAN channel as the live view and telemetry show it (a copy of its
    ``ChannelState``, rates rounded to what is worth showing, and its active alarm kinds)."""

    product: str
    node_id: int
    target_rate_kg_ha: float
    target_rpm: float
    measured_rpm: float | None
    applied_rate_kg_ha: float | None
    fault: str | None
    alarms: tuple[AlarmKind, ...]


@dataclass(frozen=True, slots=True)
class MeteringStatus:
    """The metering component at one moment (``MeteringComponent.status()``)."""

    working: bool
    speed_kmh: float | None
    channels: Mapping[str, ChannelStatus]  # channel name -> status, in config order


def can_channels(settings: Settings) -> list[ChannelSection]:
    """The ``can_pid`` channels (their node ids are distinct: the config checks that)."""
    return [c for c in settings.channel if c.drive == "can_pid"]


class MeteringComponent:
    """Drives every ``can_pid`` channel from speed, work state and position.

    ``pwm_modbus`` channels keep paper A's existing path and are ignored here. ``prescription``
    is the map the caller loaded (``prescription.load_prescription``); None: every channel
    meters its operator rate.
    """

    def __init__(
        self,
        settings: Settings,
        get_speed_kmh: Callable[[], float | None],
        get_working: Callable[[], bool],
        get_position: Callable[[], Pose | None],
        on_alarm: Callable[[ChannelAlarm], None],
        *,
        link: MeteringCanLink | None = None,
        prescription: PrescriptionMap | None = None,
        as_applied: AsAppliedLog | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.channels = can_channels(settings)
        self._speed = get_speed_kmh
        self._working = get_working
        self._position = get_position
        self._on_alarm = on_alarm
        self._link = link
        self._clock = clock
        can = settings.can
        self.supervisor = ChannelSupervisor(
            [c.name for c in self.channels],
            feedback_timeout_s=can.feedback_timeout_s, off_target_pct=can.off_target_pct,
            off_target_s=can.off_target_s, min_target_rpm=can.min_target_rpm, start=clock(),
            max_rpm={c.name: c.max_shaft_rpm for c in self.channels},
        )
        self.prescription = prescription  # loaded once by the caller (load_prescription)
        self.as_applied = as_applied
        self.state = {
            c.name: ChannelState(c.name, c.product, c.node_id) for c in self.channels
        }
        self._by_node = {c.node_id: c for c in self.channels}
        self.rates = {c.name: c.target_rate_kg_ha for c in self.channels}  # operator's rates
        self._last_as_applied = -1e9
        # whether a channel may meter now beside the work state (AgOpenGPS's sections:
        # gateway.app.agopengps); None: every channel follows the work state alone
        self.channel_gate: Callable[[str, float], bool] | None = None
        # a channel's ground speed over the machine's (1.0 straight ahead; a channel feeding
        # the outer half of a curve runs faster): AgOpenGPS's tool speeds, None: always 1
        self.speed_factor: Callable[[str, float], float] | None = None
        self.working = False
        self.speed_kmh: float | None = None

    def set_rate(self, channel: str, rate_kg_ha: float) -> str:
        """The operator's rate for ``channel`` (used outside the map / without one)."""
        if channel not in self.rates:
            raise CommandError(f"{channel!r} is not a can_pid channel")
        if not (math.isfinite(rate_kg_ha) and 0 < rate_kg_ha <= MAX_RATE_KG_HA):
            raise CommandError(f"rate must be in 0..{MAX_RATE_KG_HA:g} kg/ha (got {rate_kg_ha})")
        self.rates[channel] = rate_kg_ha
        return f"{channel} {rate_kg_ha:g} kg/ha"

    def target_rate(self, ch: ChannelSection, pose: Pose | None) -> float:
        default = self.rates.get(ch.name, ch.target_rate_kg_ha)
        p = self.prescription
        if p is None or ch.prescription_attribute is None:
            return default
        if pose is None:  # the map's position-lost rate if it has one (ISO-XML TSK I)
            return p.position_lost.get(ch.prescription_attribute, default)
        return p.rate_ahead(pose, ch.prescription_attribute, default,
                            self.settings.prescription.lookahead_s, ch.outlet_behind_m,
                            ch.outlet_lateral_m)

    def on_status(self, status: MeterStatus, t: float) -> None:
        ch = self._by_node.get(status.node_id)
        if ch is None:
            return
        fault = status.fault.name.lower() if status.faulted else None
        self.supervisor.feedback(ch.name, status.measured_rpm, t, fault)
        st = self.state[ch.name]
        st.measured_rpm, st.fault = status.measured_rpm, fault

    def tick(self, now: float) -> dict[str, float]:
        """One control step: new shaft targets per channel (also sent to the link)."""
        width = self.settings.machine.working_width_m
        machine_speed = self._speed()
        working = bool(self._working())
        pose = self._position()
        self.working, self.speed_kmh = working, machine_speed
        targets: dict[str, float] = {}
        for ch in self.channels:
            st = self.state[ch.name]
            rate = self.target_rate(ch, pose)
            st.target_rate_kg_ha = rate
            rpm = 0.0
            too_fast = None
            gate = self.channel_gate
            section_on = gate is None or gate(ch.name, now)
            speed = machine_speed
            if speed is not None and self.speed_factor is not None:
                speed *= self.speed_factor(ch.name, now)
            if working and section_on and speed is not None and speed > 0:
                rpm = channel_target_rpm(ch, rate, speed, width)
                if rpm > ch.max_shaft_rpm:
                    at_max = channel_rate(ch, ch.max_shaft_rpm, 1.0, width) or 0.0
                    max_kmh = at_max / rate
                    too_fast = f"{ch.name}: too fast for {rate:g} kg/ha, max {max_kmh:.1f} km/h"
                    rpm = ch.max_shaft_rpm
                if rpm < self.settings.can.min_target_rpm:
                    rpm = 0.0
            self.supervisor.too_fast(ch.name, too_fast)
            self.supervisor.command(ch.name, rpm, now)
            st.target_rpm = rpm
            # a speed no motor can turn is not a rate: unknown (null) rather than a wild figure
            trusted = not any(a.kind == "impossible_speed"
                              for a in self.supervisor.active(ch.name))
            st.applied_rate_kg_ha = (
                channel_rate(ch, st.measured_rpm, speed, width)
                if st.measured_rpm is not None and speed is not None and trusted else None
            )
            if self._link is not None:
                self._link.set_target(ch.node_id, rpm, enable=rpm > 0)
            targets[ch.name] = rpm
        for alarm in self.supervisor.evaluate(now):
            (log.warning if alarm.active else log.info)("%s", alarm.message)
            self._on_alarm(alarm)
        if self.as_applied is not None and working and pose is not None and (
            now - self._last_as_applied >= AS_APPLIED_PERIOD_S
        ):
            self._last_as_applied = now
            stamp = datetime.now(UTC).isoformat(timespec="milliseconds")
            for ch in self.channels:
                st = self.state[ch.name]
                self.as_applied.record_channel(
                    pose, ch, st.target_rate_kg_ha, st.applied_rate_kg_ha, time=stamp
                )
        return targets

    async def _control_loop(self) -> None:
        period = 1.0 / self.settings.can.command_hz
        while True:
            self.tick(self._clock())
            await asyncio.sleep(period)

    async def run(self) -> None:
        """Run until cancelled; opens the CAN bus from ``settings.can`` unless given a link."""
        if not self.channels:
            log.info("no can_pid channels configured; metering component idle")
            await asyncio.Event().wait()
        if self._link is not None:
            await self._run_with(self._link)
            return
        can = self.settings.can
        async with CanBus(can.interface, can.channel, can.bitrate) as bus:
            self._link = MeteringCanLink(bus, [c.node_id for c in self.channels],
                                         command_hz=can.command_hz, clock=self._clock)
            try:
                await self._run_with(self._link)
            finally:
                self._link = None

    async def _run_with(self, link: MeteringCanLink) -> None:
        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(link.run(self.on_status), name="metering-link")
                tg.create_task(self._control_loop(), name="metering-control")
        finally:
            # leave every shaft commanded off; the controllers' own command timeout is the
            # backstop if this last frame cannot be sent
            link.stop_all()
            with contextlib.suppress(DriverError, TimeoutError):
                await asyncio.wait_for(link.send_commands(), STOP_SEND_TIMEOUT_S)

    def status(self) -> MeteringStatus:
        """A copy for the live view and telemetry: the inputs and each channel's status (not
        ``state``, which is the component's own live record per channel)."""
        return MeteringStatus(
            working=self.working,
            speed_kmh=self.speed_kmh,
            channels={
                name: ChannelStatus(
                    product=st.product,
                    node_id=st.node_id,
                    target_rate_kg_ha=round(st.target_rate_kg_ha, 3),
                    target_rpm=round(st.target_rpm, 2),
                    measured_rpm=st.measured_rpm,
                    applied_rate_kg_ha=(
                        None if st.applied_rate_kg_ha is None else round(st.applied_rate_kg_ha, 2)
                    ),
                    fault=st.fault,
                    alarms=tuple(a.kind for a in self.supervisor.active(name)),
                )
                for name, st in self.state.items()
            },
        )
