"""Wiring of the subsystems a machine may or may not have: systemd notification, the GNSS
receiver and seed recording, the record store and MQTT, CAN metering channels. Each is attached
only when it is on (its table is in the config and does not say ``enabled = false``, see
``gateway.config._base.OptionalPart``), so a paper-A-only drill runs with the RS485 bus and the
screen.

Every part talks to the control loop through callbacks that only store a value or enqueue
work; none of them is awaited by the control loop.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from gateway.app.parts import Parts
from gateway.config import Settings, as_applied_path, store_path, undriven_channels
from gateway.control.controller import Controller, ControlOutputs
from gateway.core import commands as cmd
from gateway.core.alarms import AlarmBoard
from gateway.core.records import AlarmEvent, AlarmSeverity
from gateway.ui.touchscreen import HmiAdapter

if TYPE_CHECKING:
    from drivers.gnss_reader import GnssEpoch
    from gateway.link.payloads import HopperInfo, RowMonitorInfo, StatePayload
    from gateway.metering.isobus import TractorInputs
    from gateway.state import HopperState, MachineState

log = logging.getLogger(__name__)

# The graceful stop, in order (``Daemon.add_task(stop_stage=...)``). First, at once and beside
# the RS485 control loop's own stop: the CAN metering channels (their shafts commanded off, so
# the safe state never waits for recording) and the seed sensors, which hand over the lines
# already sent while the receiver still runs (those seeds can still get their bracketing
# epoch). Then the receiver hands over its open epoch, then the recorder positions (or
# extrapolates and flags) and stores every seed, then the store commits; then the MQTT link
# publishes what that commit added (``Daemon.stop_drains``, bounded), and MQTT and the rest
# are cancelled after that, so the last records are durable and, with the broker up,
# delivered before the status goes offline.
STOP_FIRST, STOP_GNSS, STOP_RECORDER, STOP_STORE = range(4)


class Daemon(Protocol):
    """What the wiring needs of the daemon it attaches parts to (``gateway.app.daemon.Daemon``
    is one): its config and clock, the controller and alarms, the hooks a part registers on,
    and the place the parts are kept. A protocol, so the wiring does not import the daemon."""

    settings: Settings
    state_dir: Path
    alarms: AlarmBoard
    controller: Controller
    parts: Parts
    hmi: HmiAdapter | None
    outputs: ControlOutputs | None
    tick_hooks: list[Callable[[ControlOutputs], None]]
    closers: list[Callable[[], None]]
    stop_drains: list[Callable[[], Coroutine[Any, Any, None]]]
    epoch_listeners: list[Callable[[Any], None]]
    roll_listeners: list[Callable[[float, float], None]]
    # told of a [positioning] changed by a calibration saved while running (LiveCalibration)
    positioning_listeners: list[Callable[[Any], None]]

    def clock(self) -> float: ...

    def add_task(
        self,
        name: str,
        factory: Callable[[], Coroutine[Any, Any, None]],
        *,
        stop_stage: int | None = None,
    ) -> None: ...

    def state(self) -> MachineState: ...

    def execute(self, command: cmd.Command, source: str) -> str: ...


async def _forever() -> None:
    await asyncio.Event().wait()


def state_payload(daemon: Daemon) -> StatePayload:
    """The MQTT ``state`` message: the daemon's state, as docs/mqtt.md documents it."""
    from gateway.link.payloads import ActiveAlarmInfo, RejectedInput, StatePayload

    state = daemon.state()
    records_lost = 0
    if state.store is not None:
        records_lost += state.store.records_lost
    if state.seeds is not None:
        records_lost += state.seeds.records_lost
    rejected = state.rejected
    return StatePayload(
        machine_id=state.machine_id,
        utc=state.utc,
        work_state=state.work_state,
        speed_kmh=state.speed_kmh,
        speed_source=state.speed_source or "none",
        tilt_deg=state.tilt_deg,
        raised=state.raised,
        crop=state.crop,
        target_rate_kg_ha=state.target_rate_kg_ha,
        commanded_rate_kg_ha=state.commanded_rate_kg_ha,
        motor_duty_pct=state.motor_duty_pct,
        fan_duty_pct=state.fan_duty_pct,
        devices=dict(state.devices),
        gnss_fix=state.gnss_fix,
        alarms=[
            ActiveAlarmInfo(code=a.code, severity=a.severity, message=a.message, since=a.since)
            for a in state.alarms
        ],
        unacknowledged=[code for code, _ in state.unacknowledged],
        area_ha=state.area_ha,
        seed_mass_kg=state.seed_mass_kg,
        records_held=state.store.records_held if state.store is not None else 0,
        records_lost=records_lost,
        rejected=RejectedInput() if rejected is None else RejectedInput(
            gnss=dict(rejected.gnss),
            gnss_discarded_bytes=rejected.gnss_discarded_bytes,
            hmi=dict(rejected.hmi),
            seed_sensors=dict(rejected.seed_sensors),
        ),
        hopper=None if state.hopper is None else _hopper_info(state.hopper),
        row_monitor=None if state.row_monitor is None else _row_monitor_info(state),
        seed_lot=state.seed_lot,
        seed_lots=dict(state.seed_lots),
    )


def _row_monitor_info(state: MachineState) -> RowMonitorInfo:
    """``RowMonitorInfo`` at the published resolution, with each row's implausible edges."""
    from gateway.link.payloads import RowMonitorInfo, RowStatusInfo

    report = state.row_monitor
    assert report is not None
    recorded = state.seeds.rows if state.seeds is not None else {}

    def r(value: float | None, digits: int) -> float | None:
        return None if value is None else round(value, digits)

    return RowMonitorInfo(
        judging=report.judging,
        all_rows_silent=report.all_rows_silent,
        expected_seeds_per_s=r(report.expected_seeds_per_s, 2),
        rows={
            str(row): RowStatusInfo(
                state=rr.verdict,
                seeds_per_s=r(rr.seeds_per_s, 2),
                pct_of_reference=r(rr.pct_of_reference, 1),
                implausible_edges=recorded[row].implausible_edges if row in recorded else 0,
            )
            for row, rr in report.rows.items()
        },
    )


def _hopper_info(h: HopperState) -> HopperInfo:
    """``HopperInfo`` at the published resolution (0.1 kg, 4 decimals for factors)."""
    from gateway.link.payloads import HopperInfo

    def r(value: float | None, digits: int) -> float | None:
        return None if value is None else round(value, digits)

    return HopperInfo(
        mass_kg=r(h.mass_kg, 1),
        time_to_empty_min=r(h.time_to_empty_min, 1),
        discharge_correction=round(h.discharge_correction, 4),
        correction_estimate=r(h.correction_estimate, 4),
        correction_standard_error=r(h.correction_standard_error, 4),
        correction_applied=h.correction_applied,
        scale_sigma_kg=r(h.scale_sigma_kg, 2),
        windows=h.windows,
        refills=h.refills,
    )


def attach(daemon: Daemon) -> None:
    """Create the enabled optional components and register their tasks on ``daemon``."""
    s = daemon.settings
    _attach_systemd(daemon)
    store = None
    recording = s.gnss.enabled and s.seed_sensors.enabled
    if recording or s.mqtt.enabled:
        from gateway.recording.store import RecordStore

        store = RecordStore(
            store_path(daemon.settings, daemon.state_dir),
            s.machine.id,
            commit_interval_s=s.store.commit_interval_s,
            retention_days=s.store.retention_days,
            backlog_alarm_records=s.store.backlog_alarm_records,
        )
        daemon.parts.store = store
        daemon.add_task("store", store.run, stop_stage=STOP_STORE)
        daemon.closers.append(store.close)
        _record_alarms_and_runs(daemon, store)
    if s.gnss.enabled:
        _attach_gnss(daemon)
    if recording and store is not None:
        _attach_seed_recording(daemon, store)
    if s.gnss.enabled or store is not None:  # the store's own alarms need it too
        _attach_recording_health(daemon, store)
    if recording and s.row_monitor.enabled:
        _attach_row_monitor(daemon)
    if s.mqtt.enabled and store is not None:
        _attach_mqtt(daemon, store)
    _attach_channels(daemon)
    if s.isobus.enabled:
        _attach_isobus(daemon)
    if s.agopengps.enabled:
        from gateway.app.agopengps import attach_agopengps

        attach_agopengps(daemon)
    _attach_rejected_inputs(daemon)


def _record_alarms_and_runs(daemon: Daemon, store: Any) -> None:
    """Alarm events into the store, MQTT or not; the run's start now and its stop on a clean
    stop (``gateway.recording.runs``): views end an alarm still active at a stop there."""
    from gateway.recording.alarm_recorder import AlarmRecorder

    s = daemon.settings
    active = daemon.alarms.active  # raised while starting, before the store was open
    now = datetime.now(UTC)
    store.start_run(
        {
            "target_spacing_m": s.positioning.target_spacing_m,
            "rows": s.machine.rows,
            "working_width_m": s.machine.working_width_m,
            "crop": s.control.crop,
            "machine_id": s.machine.id,
        },
        min([now, *(a.since for a in active)]),
    )
    daemon.parts.alarm_recorder = AlarmRecorder(daemon.alarms, store)
    for a in active:
        store.add_alarm(AlarmEvent(machine_id=s.machine.id, code=a.code, active=True,
                                   severity=a.severity, message=a.message, utc=a.since))
    # closers run in reverse: this one before store.close, after the store's last commit
    daemon.closers.append(lambda: store.stop_run(datetime.now(UTC)))


def _attach_rejected_inputs(daemon: Daemon) -> None:
    """``state.rejected`` and the periodic INFO summary of rejected input (only with a device
    that can reject input: screen, receiver or seed sensors)."""
    from gateway.app.rejected_input import RejectedInputs

    parts = daemon.parts
    hmi = daemon.hmi.link if daemon.hmi is not None else None
    if hmi is None and parts.gnss is None and parts.seed_sensors is None:
        return
    rejected = RejectedInputs(
        gnss=parts.gnss, hmi=hmi, seed_sensors=parts.seed_sensors, recorder=parts.seeds
    )
    parts.rejected = rejected
    daemon.add_task("rejected-input-summary", rejected.run)


def _attach_systemd(daemon: Daemon) -> None:
    from gateway.link.sdnotify import Notifier, Watchdog

    notifier = Notifier()
    if not notifier.enabled:
        return
    watchdog = Watchdog.from_environment(notifier)
    ready = False

    def on_tick(_: ControlOutputs) -> None:
        nonlocal ready
        watchdog.kick()
        if not ready:
            ready = notifier.ready("control loop running")

    daemon.tick_hooks.append(on_tick)
    daemon.add_task("watchdog", watchdog.run)

    def stopping() -> None:
        notifier.stopping()
        notifier.close()

    daemon.closers.append(stopping)


def _attach_gnss(daemon: Daemon) -> None:
    from drivers.gnss_reader import GnssReader

    g = daemon.settings.gnss
    epoch_listeners = daemon.epoch_listeners

    def on_epoch(epoch: GnssEpoch) -> None:
        # every epoch, any fix: the radar's scale is learnt against the RTK-fixed ones
        daemon.controller.on_gnss_epoch(epoch.t_mono, epoch.fix, epoch.speed_kmh,
                                        epoch.course_deg)
        if epoch.fix != "none" and epoch.speed_kmh is not None:
            daemon.controller.on_speed("gnss", epoch.speed_kmh, epoch.t_mono)
        for listener in epoch_listeners:
            listener(epoch)

    reader = GnssReader(
        g.port,
        g.baudrate,
        on_epoch=on_epoch,
        stale_after_s=g.stale_after_s,
        required=g.epoch_sentences,
        silence_reconnect_s=g.silence_reconnect_s,
        heading_offset_deg=g.heading_offset_deg,
    )
    daemon.parts.gnss = reader

    async def run() -> None:
        async with reader:
            await _forever()

    daemon.add_task("gnss", run, stop_stage=STOP_GNSS)


def _attach_seed_recording(daemon: Daemon, store: Any) -> None:
    from gateway.recording.recorder import SeedRecorder

    recorder = SeedRecorder(daemon.settings, store)
    daemon.parts.seeds = recorder
    # a position calibration saved while running positions the next seeds (no restart)
    daemon.positioning_listeners.append(recorder.recalibrate)
    sensors = _seed_sensor_source(daemon, recorder.on_edge)
    if hasattr(sensors, "read_pending"):
        # GPIO: the edges the kernel queued go to the recorder ahead of each epoch, in the
        # wake-up the epoch brought, so they need none of their own (drivers.seed_sensors)
        daemon.epoch_listeners.append(lambda _epoch: sensors.read_pending())
    daemon.epoch_listeners.append(recorder.on_epoch)
    if daemon.settings.positioning.attitude_source == "inclinometer":
        daemon.roll_listeners.append(recorder.on_roll)
    daemon.parts.seed_sensors = sensors
    daemon.add_task("seed-sensors", sensors.run, stop_stage=STOP_FIRST)
    daemon.add_task("seed-recorder", recorder.run, stop_stage=STOP_RECORDER)


def _attach_recording_health(daemon: Daemon, store: Any) -> None:
    """Alarms for a lost receiver, a degraded fix, lost seed sensors and a failing, stalled
    or replaced store."""
    from gateway.recording.health import RecordingHealth

    health = RecordingHealth(
        daemon.alarms,
        gnss=daemon.parts.gnss,
        sensors=daemon.parts.seed_sensors,
        recorder=daemon.parts.seeds,
        store=store,
        clock=daemon.clock,
    )
    daemon.parts.recording_health = health
    daemon.tick_hooks.append(lambda _: health.check())


def _attach_row_monitor(daemon: Daemon) -> None:
    """Blocked, skipping and chattering rows, and all rows silent while the meter turns
    (``gateway.recording.row_alarms``), judged on every control tick."""
    from gateway.recording.row_alarms import RowAlarms

    recorder = daemon.parts.seeds
    assert recorder is not None
    rows = RowAlarms(daemon.settings, daemon.alarms, recorder, daemon.clock)
    daemon.parts.row_alarms = rows

    def meter_turning(out: ControlOutputs) -> bool:
        """The seed meter is being driven: the PWM motor, or a CAN channel given a target."""
        if out.motor_pct > 0:
            return True
        metering = daemon.parts.metering
        return metering is not None and any(
            st.target_rpm > 0 for st in metering.state.values()
        )

    daemon.tick_hooks.append(
        lambda out: rows.check(
            working=out.state.value == "seeding", speed_kmh=out.speed_kmh,
            meter_turning=meter_turning(out),
        )
    )


def _seed_sensor_source(daemon: Daemon, on_edge: Any) -> Any:
    ss = daemon.settings.seed_sensors
    if ss.source == "gpio":
        from drivers.seed_sensors import GpioSeedSensors

        return GpioSeedSensors(
            ss.gpio_chip, ss.gpio_lines, ss.debounce_ms, on_edge, bias=ss.gpio_bias
        )
    from drivers.seed_sensors import SerialSeedSensors

    return SerialSeedSensors(ss.port, ss.baudrate, daemon.settings.machine.rows, on_edge)


def _attach_mqtt(daemon: Daemon, store: Any) -> None:
    from gateway.link.mqtt import MqttLink

    link = MqttLink(daemon.settings, store, daemon, lambda: state_payload(daemon), daemon.alarms,
                    recorded=daemon.parts.alarm_recorder)
    daemon.parts.mqtt = link

    def on_tick(out: ControlOutputs) -> None:
        link.notify_state_changed()  # a tick is when speed, duty and work state change

    daemon.tick_hooks.append(on_tick)
    daemon.add_task("mqtt", link.run)
    daemon.stop_drains.append(link.drain)


def _gnss_pose(daemon: Daemon) -> Any:
    """Position for prescription look-ups: the latest fresh GNSS epoch, else None."""
    from gateway.metering.prescription import Pose

    reader = daemon.parts.gnss
    if reader is None or not reader.available or reader.latest is None:
        return None
    e = reader.latest
    heading = e.heading_deg if e.heading_valid else e.course_deg
    return Pose(lon=e.lon, lat=e.lat, heading_deg=heading or 0.0, speed_kmh=e.speed_kmh or 0.0)


def _load_prescription(daemon: Daemon) -> Any:
    """The prescription map, or None when disabled or unusable (alarm says why: a bad map
    must not keep the drill from sowing at the default rates)."""
    from gateway.metering.prescription import PrescriptionError, load_prescription

    try:
        return load_prescription(daemon.settings)
    except PrescriptionError as exc:
        log.error("prescription map not used: %s", exc)
        daemon.alarms.raise_(
            "prescription.invalid", f"prescription map not used: {exc}", "critical"
        )
        return None


def _attach_channels(daemon: Daemon) -> None:
    """Metering channels: ``can_pid`` ones on the CAN bus, the ``pwm_modbus`` one through the
    RS485 control loop; one prescription map and one as-applied log for all of them."""
    from gateway.control.controller import pwm_channel
    from gateway.metering.prescription import AsAppliedLog
    from gateway.metering.pwm_channel import PwmChannelPart

    s = daemon.settings
    pwm = pwm_channel(s)
    undriven = undriven_channels(s)
    if undriven:
        names = ", ".join(c.name for c in undriven)
        log.error("can_pid channels %s configured but [can] is not enabled", names)
        daemon.alarms.raise_(
            "channel.can_disabled",
            f"channel(s) {names} not driven: can is off (no [can] table, or [can] "
            "enabled = false)",
            "critical",
        )
    can_pid = [c for c in s.channel if c.drive == "can_pid" and c not in undriven]
    if not can_pid and pwm is None:
        if s.prescription.enabled:
            daemon.alarms.raise_(
                "prescription.unused", "prescription map enabled but no metering channel uses it"
            )
        return

    def on_write_error(error: str | None) -> None:
        daemon.alarms.set(
            "as_applied.write_failed", error is not None, f"as-applied log not written: {error}"
        )

    as_applied = AsAppliedLog(
        as_applied_path(daemon.settings, daemon.state_dir),
        on_error=on_write_error,
    )
    prescription = _load_prescription(daemon)
    if prescription is not None and s.gnss.enabled:
        from gateway.metering.prescription import FarFromFieldWatch

        # a map of another field: alarmed from the machine's first fixed positions on
        daemon.epoch_listeners.append(FarFromFieldWatch(prescription, daemon.alarms).on_epoch)
    if can_pid:
        _attach_metering(daemon, prescription, as_applied)
    if pwm is not None:
        part = PwmChannelPart(
            pwm,
            prescription,
            as_applied,
            pose=lambda: _gnss_pose(daemon),
            operator_rate=lambda: daemon.controller.rate_kg_ha,
            lookahead_s=s.prescription.lookahead_s,
            active_alarms=lambda: {a.code for a in daemon.alarms.active},
            clock=daemon.clock,
        )
        daemon.parts.pwm_channel = part
        daemon.controller.rate_provider = part.prescribed_rate
        daemon.tick_hooks.append(
            lambda out: part.on_tick(
                out.state.value == "seeding", out.target_rate_kg_ha,
                out.commanded_rate_kg_ha, out.motor_pct,
            )
        )


def _attach_metering(daemon: Daemon, prescription: Any, as_applied: Any) -> None:
    from gateway.metering.channels import ChannelAlarm, MeteringComponent

    def speed() -> float | None:
        out = daemon.outputs
        return None if out is None else out.speed_kmh

    def working() -> bool:
        out = daemon.outputs
        return out is not None and out.state.value == "seeding"

    def on_alarm(alarm: ChannelAlarm) -> None:
        severity: AlarmSeverity = (
            "critical"
            if alarm.kind in ("feedback_lost", "controller_fault", "impossible_speed")
            else "warning"
        )
        daemon.alarms.set(
            f"channel.{alarm.channel}.{alarm.kind}", alarm.active, alarm.message, severity
        )

    component = MeteringComponent(
        daemon.settings,
        speed,
        working,
        lambda: _gnss_pose(daemon),
        on_alarm,
        prescription=prescription,
        as_applied=as_applied,
    )
    daemon.parts.metering = component
    daemon.add_task("metering", component.run, stop_stage=STOP_FIRST)


ISOBUS_PUMP_S = 0.05  # half the tractor's 100 ms, so a value reaches the controller young


def isobus_pump_step(daemon: Daemon, tractor: TractorInputs, fed: dict[str, float]) -> None:
    """Hand the controller each new ISOBUS speed and hitch value once, stamped with the time
    its frame arrived, so the controller's own staleness check (``isobus.stale_after_s``,
    300 ms) runs from the frame and not from this pump."""
    now = daemon.clock()
    speed = tractor.speed(now)
    if speed is not None:
        at = now - speed.age_s
        if at > fed.get("speed", float("-inf")):
            fed["speed"] = at
            daemon.controller.on_speed("isobus", speed.speed_kmh, at)
    working = tractor.working(now)
    at_hitch = tractor.hitch_received_at()
    if working is not None and at_hitch is not None and at_hitch > fed.get("hitch", float("-inf")):
        fed["hitch"] = at_hitch
        daemon.controller.on_hitch(working, at_hitch)


def _attach_isobus(daemon: Daemon) -> None:
    from drivers.can_bus import CanBus, IsobusListener
    from gateway.metering.isobus import TractorInputs

    cfg = daemon.settings.isobus
    listener = IsobusListener(clock=daemon.clock)
    tractor = TractorInputs(
        listener,
        speed_priority=cfg.speed_priority,
        stale_after_s=cfg.stale_after_s,
        hitch_in_work_below_pct=cfg.hitch_in_work_below_pct,
    )
    daemon.parts.isobus = listener

    async def pump() -> None:
        fed: dict[str, float] = {}
        while True:
            await asyncio.sleep(ISOBUS_PUMP_S)
            isobus_pump_step(daemon, tractor, fed)

    async def run() -> None:
        async with CanBus(cfg.interface, cfg.channel) as bus:
            listener.bus = bus
            async with asyncio.TaskGroup() as tg:
                tg.create_task(listener.run(), name="isobus-listen")
                tg.create_task(pump(), name="isobus-pump")

    daemon.add_task("isobus", run)
