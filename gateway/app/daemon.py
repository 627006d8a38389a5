"""The daemon: one named task per driver under one supervisor, the controller in the middle.

The RS485 task is also the control loop: it polls the radar and the inclinometer, ticks the
controller and writes the PWM module, one request at a time on the one bus, because that is
the order a half-duplex RS485 bus imposes anyway and it keeps the reply→write latency to the
few microseconds of arithmetic between them. Everything else (HMI, GNSS, seed sensors, the
record store, MQTT, CAN) runs beside it and talks to the controller only through callbacks
that never block, so a broker outage or a dead screen cannot delay a duty write.

A stop (SIGTERM, ``request_stop``) is ordered, because nothing recorded may be lost: the
control loop is stopped and motor and fan set to 0 at once, and beside that the tasks
registered with a ``stop_stage`` are stopped one stage after the other (CAN metering and the
seed sensors first, the sensors handing over the lines already sent; then the GNSS reader its
open epoch; then the recorder positions and stores everything; then the store commits; see
``gateway.app.wiring``); then the ``stop_drains`` run (the MQTT link publishes what that
last commit added to the outbox, bounded); only then is the rest (MQTT, HMI, ...) cancelled.
Cancelling everything at once let the recorder's final flush run before the sensors had
delivered what they had already received; cancelling MQTT right after the last commit left
the seeds stored by that flush unpublished until the next start.

The supervisor is hand-written rather than an ``asyncio.TaskGroup`` because a TaskGroup
cancels each child once and then waits for ever: on Python 3.11 a polling loop can swallow
that one cancel (see ``drivers.tasks``), and a daemon that hangs on SIGTERM never writes the
motor and fan to 0. Here a stop re-cancels until every task has ended, waits at most
``SHUTDOWN_TIMEOUT_S``, and the PWM module is set to 0 whatever happened.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import signal
import time
from collections import deque
from collections.abc import Callable, Coroutine
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from drivers.errors import DeviceRejected, DriverError
from drivers.modbus_bus import ModbusBus
from drivers.rs485_devices import BadReading, Channel, HopperScale, Inclinometer, PwmModule, Radar
from drivers.tasks import cancel_all
from gateway.app import wiring
from gateway.app.calibration_check import working_speed_problem
from gateway.app.live_calibration import LiveCalibration
from gateway.app.parts import Parts
from gateway.app.rotation_test import RotationTestSession
from gateway.calibration.apply import apply_calibrations
from gateway.calibration.fits import CalibrationStore
from gateway.config import Settings, parts_summary, start_problems
from gateway.control.controller import Controller, ControlOutputs
from gateway.core import commands as cmd
from gateway.core.alarms import AlarmBoard
from gateway.core.errors import CommandError, ConfigError
from gateway.core.records import AlarmEvent, FixQuality
from gateway.state import ActiveAlarmState, MachineState
from gateway.ui.touchscreen import HmiAdapter

log = logging.getLogger(__name__)

LATENCY_SAMPLES = 4096  # reply→write latencies kept for the benchmark and the status view
SAFE_OFF_TIMEOUT_S = 1.0
# Longest wait for the driver tasks to end after a stop; past it the stuck ones are named in
# the log and the motor and fan are switched off anyway.
SHUTDOWN_TIMEOUT_S = 5.0
DUTY_EPSILON_PCT = 0.05  # below this a change is not worth a bus write
# A device alarms once it has not answered for this long (as speed.lost does): one CRC error
# from motor noise must not flash "radar not answering" on the screen and over MQTT.
DEVICE_LOST_AFTER_S = 2.0
# good hopper readings in a row that clear hopper_scale.bad_reading (a transmitter sending
# NaN every other reading must not raise and clear the alarm on every poll)
BAD_READING_CLEAR_AFTER = 10
# A PWM module that refused its communication-loss timeout is asked again this often (it may
# have been swapped); one that did not answer, as soon as this after the last try.
WATCHDOG_RETRY_REFUSED_S = 10.0
WATCHDOG_RETRY_UNANSWERED_S = 1.0
# Allocations (net of frees) between two young-generation collections in the service process;
# Python's default is 700 (see settle_gc).
GC_YOUNG_THRESHOLD = 10_000


def settle_gc() -> None:
    """Tune the garbage collector for the long-running service, once start-up is done.

    Why: everything imported and built at start-up (modules, pydantic schemas, the daemon's
    parts) lives as long as the process, yet every full collection walked all of it again;
    ``gc.freeze()`` takes it out of the collector's sight. And the seed path allocates tens of
    thousands of short-lived containers a second, nearly all freed by reference counting: at
    Python's default threshold of 700 the young generation was collected every ~30 ms. At
    ``GC_YOUNG_THRESHOLD`` the collector's share of the daemon's CPU at 2 100 seeds/s fell
    from about 0.3 % to 0.15 % of a core (bench machine), for a few MB at most.

    Only ``sowgate run`` (and the benchmark standing in for it) calls this: a library user or
    the test process keeps Python's defaults.
    """
    gc.collect()
    gc.freeze()
    _young, middle, old = gc.get_threshold()
    gc.set_threshold(GC_YOUNG_THRESHOLD, middle, old)


class Daemon:
    def __init__(
        self,
        settings: Settings,
        state_dir: Path,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        # Files and directories first: a missing CA or a state directory that is a file is a
        # config error naming the key (exit 78), not a traceback or an endless reconnect.
        problems = start_problems(settings, state_dir)
        if problems:
            raise ConfigError(problems)
        for note in settings.deprecation_notes():  # logged here: logging is set up by now
            log.warning("config: %s", note)
        log.info("%s", parts_summary(settings))  # which parts run; none is off without a word
        self.state_dir = state_dir
        self.clock = clock
        self.alarms = AlarmBoard(settings.machine.id)
        base = settings.model_copy(deep=True)  # the config alone: live reloads start from it
        self.calibrations = apply_calibrations(
            settings, state_dir, vet=working_speed_problem, alarms=self.alarms
        )
        self.alarm_log: deque[AlarmEvent] = deque(maxlen=64)
        self.alarms.subscribe(self.alarm_log.append)
        self.controller = Controller(
            settings, self.alarms, calibrations=CalibrationStore(state_dir)
        )
        self.live_calibration = LiveCalibration(
            base, settings, state_dir, self.alarms, self.controller,
            vet=working_speed_problem, clock=clock, start_notes=self.calibrations,
        )
        self.positioning_listeners = self.live_calibration.positioning_listeners
        self.rotation_test = RotationTestSession(settings, self.controller, self.live_calibration)
        self.rs485 = settings.rs485.enabled  # False: no radar, inclinometer or PWM module
        self.bus = ModbusBus.from_config(settings.rs485)
        self.radar = Radar(self.bus, settings.radar)
        self.inclinometer = Inclinometer(self.bus, settings.inclinometer)
        # terrain compensation from the inclinometer's roll axis (positioning.attitude_source):
        # a second read of the same sensor; its configured axis keeps telling raised/lowered
        self.roll_sensor: Inclinometer | None = None
        if settings.positioning.attitude_source == "inclinometer":
            self.roll_sensor = Inclinometer(
                self.bus, settings.inclinometer.model_copy(update={"axis": "roll"})
            )
        self.roll_listeners: list[Callable[[float, float], None]] = []
        self.pwm = PwmModule(self.bus, settings.actuators)
        self._hopper_good = 0  # good hopper readings since the last bad one
        self.hopper_scale = (
            HopperScale(self.bus, settings.hopper_scale)
            if self.rs485 and settings.hopper_scale.enabled else None
        )
        self.latencies_s: deque[float] = deque(maxlen=LATENCY_SAMPLES)
        self.outputs: ControlOutputs | None = None
        self._written: dict[str, float] = {}
        self._written_at: float = -1e18
        # Duties are rewritten at least this often: also the keep-alive of the PWM module's
        # communication-loss watchdog, so well inside its timeout.
        act = settings.actuators
        self._refresh_s = min(act.refresh_s, act.comm_timeout_s / 2.0)
        self._watchdog_verified = False
        self._watchdog_ever_verified = False  # the module held its timeout at least once
        self._watchdog_retry_at = -1e18
        self._safe_off_tried = False
        # Why motor and fan may still be running after exit (None: set to 0, or no RS485);
        # ``sowgate run`` repeats it as its last line and exits non-zero.
        self.safe_off_failure: str | None = None
        if self.rs485 and act.comm_timeout_s < 3.0 / settings.rs485.poll_hz:
            log.warning(
                "actuators.comm_timeout_s %g s is less than 3 control periods "
                "(rs485.poll_hz %g): one slow poll may let the PWM module switch off",
                act.comm_timeout_s, settings.rs485.poll_hz,
            )
        # device -> last tick it was answering (or its first failure if it never answered)
        self._answering_at: dict[str, float] = {}
        self._stop = asyncio.Event()
        self._extra: list[tuple[str, Callable[[], Coroutine[Any, Any, None]], int | None]] = []
        self.hmi: HmiAdapter | None = None
        if settings.hmi.enabled:
            self.hmi = HmiAdapter(
                settings.hmi,
                crops=settings.control.crops,
                execute=self.try_execute,
                state=self.state,
                seed_lots=self.live_calibration.lots_of,
            )
        self.parts = Parts()  # the optional parts, filled by gateway.app.wiring
        self.tick_hooks: list[Callable[[ControlOutputs], None]] = []
        self.tick_hooks.append(lambda _out: self.live_calibration.poll())
        self.closers: list[Callable[[], None]] = []
        # Awaited on a stop after the last stage (the store's commit), before the rest is
        # cancelled: each is bounded by its own timeout and must not raise.
        self.stop_drains: list[Callable[[], Coroutine[Any, Any, None]]] = []
        self.epoch_listeners: list[Callable[[Any], None]] = []
        self._build_optional()

    # ---- optional subsystems --------------------------------------------------------------
    def _build_optional(self) -> None:
        """Seed recording, MQTT and CAN metering, each only when its table enables it."""
        wiring.attach(self)

    def add_task(
        self,
        name: str,
        factory: Callable[[], Coroutine[Any, Any, None]],
        *,
        stop_stage: int | None = None,
    ) -> None:
        """Run ``factory()`` as task ``name`` beside the control loop.

        On a stop, tasks with a ``stop_stage`` are cancelled and awaited stage by stage,
        lowest first, before the others are cancelled together: a producer finishes handing
        over (in its cancellation path) before its consumer's final flush begins.
        """
        self._extra.append((name, factory, stop_stage))

    # ---- command path -----------------------------------------------------------------------
    def execute(self, command: cmd.Command, source: str) -> str:
        """The one command path for HMI and MQTT (see gateway.core.commands)."""
        if isinstance(command, cmd.SetChannelRate):
            return self._set_channel_rate(command, source)
        if isinstance(command, cmd.RotationTest):
            reply = self.rotation_test.command(command.action, command.value, self.clock())
            log.info("command from %s: %s", source, reply)
            return reply
        if isinstance(command, cmd.Stop):
            self.rotation_test.stop()
        if isinstance(command, cmd.SelectSeedLot):
            reply = self.live_calibration.select_lot(command.crop, command.lot)
            log.info("command from %s: %s", source, reply)
            return reply
        return self.controller.execute(command, source)

    def _set_channel_rate(self, command: cmd.SetChannelRate, source: str) -> str:
        """A can_pid channel's rate goes to the metering component; the pwm_modbus channel's
        is paper A's rate (same crop range checks as the HMI)."""
        names = [c.name for c in self.settings.channel]
        ch = next((c for c in self.settings.channel if c.name == command.channel), None)
        if ch is None:
            raise CommandError(
                f"unknown channel {command.channel!r}; known: {', '.join(names) or 'none'}"
            )
        if ch.drive == "pwm_modbus":
            return self.controller.execute(cmd.SetRate(ch.product, command.rate_kg_ha), source)
        metering = self.parts.metering
        if metering is None:
            raise CommandError(f"channel {ch.name!r} is not running ([can] not enabled)")
        reply: str = metering.set_rate(ch.name, command.rate_kg_ha)
        log.info("command from %s: %s", source, reply)
        return reply

    def try_execute(self, command: cmd.Command, source: str) -> tuple[bool, str]:
        try:
            return True, self.execute(command, source)
        except CommandError as exc:
            return False, str(exc)

    # ---- lifecycle ---------------------------------------------------------------------------
    def request_stop(self) -> None:
        self._stop.set()

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        installed: list[signal.Signals] = []
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(sig, self.request_stop)
                installed.append(sig)
        if self.rs485:
            await self.bus.start()
        self.live_calibration.announce()
        try:
            # both outputs are 0 before anything else happens
            await self._write_outputs(0.0, 0.0, force=True)
            await self._keep_pwm_watchdog()
            await self._supervise()
        finally:
            await self._safe_off()  # again: the net for the paths that skipped _stop_control
            self.live_calibration.retire()
            if self.rs485:
                await self.bus.close()
            for close in reversed(self.closers):
                try:
                    close()
                except Exception:
                    log.exception("error while closing %r", close)
            for sig in installed:
                loop.remove_signal_handler(sig)

    async def _supervise(self) -> None:
        """Run every task until a stop is requested or one of them fails, then end them all.

        A task that returns normally just ends (as in a TaskGroup); a task that raises stops
        the daemon and its exceptions are re-raised as an ExceptionGroup after shutdown.
        """
        factories: list[tuple[str, Callable[[], Coroutine[Any, Any, None]], int | None]] = [
            ("rs485", self._control_loop, None)
        ]
        if self.hmi is not None:
            factories += [
                ("hmi", self.hmi.link.run, None), ("hmi-view", self.hmi.refresh_loop, None)
            ]
        factories += self._extra
        tasks = [asyncio.create_task(factory(), name=name) for name, factory, _ in factories]
        control = tasks[0]
        stages: dict[int, list[asyncio.Task[None]]] = {}
        for task, (_name, _factory, stage) in zip(tasks, factories, strict=True):
            if stage is not None:
                stages.setdefault(stage, []).append(task)
        stop = asyncio.create_task(self._stop.wait(), name="stop")
        failures: list[Exception] = []
        try:
            running: set[asyncio.Task[Any]] = set(tasks)
            while not stop.done() and not failures:
                done, _ = await asyncio.wait(
                    running | {stop}, return_when=asyncio.FIRST_COMPLETED
                )
                for finished in done - {stop}:
                    running.discard(finished)
                    exc = None if finished.cancelled() else finished.exception()
                    if isinstance(exc, Exception):
                        log.error("task %s failed: %r", finished.get_name(), exc)
                        failures.append(exc)
                    elif exc is not None:
                        raise exc
            # The ordered stop, after a failure too: what was recorded must still be stored.
            try:
                async with asyncio.timeout(SHUTDOWN_TIMEOUT_S):
                    await asyncio.gather(
                        self._stop_control(control), _stop_in_stages(stages, self.stop_drains)
                    )
            except TimeoutError:
                log.error("ordered stop took over %.0f s; cancelling the rest", SHUTDOWN_TIMEOUT_S)
        finally:
            stuck = await cancel_all([stop, *tasks], timeout_s=SHUTDOWN_TIMEOUT_S)
            if stuck:
                log.error(
                    "task(s) still running %.0f s after the stop: %s; switching off anyway",
                    SHUTDOWN_TIMEOUT_S,
                    ", ".join(t.get_name() for t in stuck),
                )
        if failures:
            raise ExceptionGroup("sowgate task failed", failures)

    async def _stop_control(self, control: asyncio.Task[None]) -> None:
        """The safe state first, not delayed by the recording drain that runs beside it. The
        loop is stopped before the 0 is written so that no later duty write can undo it; a
        poll it had on the bus is waited out first (``ModbusBus`` keeps the bus until its
        reply is in), so the final write never meets that reply."""
        await cancel_all([control])
        await self._safe_off()

    async def _safe_off(self) -> None:
        """Motor and fan to 0 before exit, whatever else has gone wrong; if the PWM module
        cannot be reached, say so (ERROR, ``safe_off_failure``) and what will stop it.

        Tried once to the end: the call in ``run``'s exit path is the net for a stop that
        never got to ``_stop_control`` (or was cancelled in it), not a second wait of up to
        ``SAFE_OFF_TIMEOUT_S`` on a dead module.
        """
        if self._safe_off_tried:
            return
        failed: dict[Channel, str] = {}
        try:
            async with asyncio.timeout(SAFE_OFF_TIMEOUT_S):
                failed = await self._write_outputs(0.0, 0.0, force=True)
        except TimeoutError:
            failed = {"motor": f"no answer within {SAFE_OFF_TIMEOUT_S:g} s"}
        self._safe_off_tried = True  # not when cancelled half-way: then the net tries again
        if not failed:
            return
        act = self.settings.actuators
        if self._watchdog_ever_verified:
            fallback = (
                "its communication-loss watchdog sets both to 0 by itself after "
                f"actuators.comm_timeout_s = {act.comm_timeout_s:g} s without a request"
            )
        else:
            fallback = (
                "no communication-loss watchdog was verified on it "
                f"(actuators.comm_timeout_s = {act.comm_timeout_s:g} s): switch the metering "
                "motor and the fan off by hand"
            )
        port_error = self.bus.port_error
        # the port down says it all once; otherwise each register's own failure
        why = (f"the port is down ({port_error})" if port_error is not None
               else "; ".join(dict.fromkeys(failed.values())))
        self.safe_off_failure = (
            f"could not set motor and fan to 0 on exit: PWM module (id {self.pwm.device_id}) "
            f"on RS485 port {self.bus.port}: {why}; {fallback}"
        )
        log.error("%s", self.safe_off_failure)

    # ---- the control loop --------------------------------------------------------------------
    async def _control_loop(self) -> None:
        period = 1.0 / self.settings.rs485.poll_hz
        next_at = self.clock()
        # The stop flag, not only cancellation, ends this loop: a cancel swallowed by a Modbus
        # read (drivers.tasks) must not let it write a duty after the safe-off.
        while not self._stop.is_set():
            reply_t = None
            if self.rs485:
                try:
                    kmh = await self.radar.read()
                    reply_t = self.clock()
                    self.controller.on_speed("radar", kmh, reply_t)
                except DriverError:
                    pass
                try:
                    tilt = await self.inclinometer.read()
                    reply_t = self.clock()
                    self.controller.on_tilt(tilt, reply_t)
                except DriverError:
                    pass
                if self.roll_sensor is not None:
                    await self._read_roll()
                if self.hopper_scale is not None:  # lost: the controller keeps its factor
                    self.controller.on_hopper_weight(await self._read_hopper(), self.clock())
            out = self.rotation_test.apply(self.controller.tick(self.clock()), self.clock())
            note = self.rotation_test.take_note()
            if note is not None and self.hmi is not None:
                self.hmi.show(note)
            self.outputs = out
            await self._write_outputs(out.motor_pct, out.fan_pct, reply_t=reply_t)
            await self._keep_pwm_watchdog()
            self._update_device_alarms()
            self.on_tick(out)
            next_at += period
            delay = next_at - self.clock()
            if delay < -period:  # fell behind (e.g. timeouts): don't burst to catch up
                next_at = self.clock()
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    async def _read_hopper(self) -> float | None:
        """One hopper scale reading; None when it does not answer or answers a value no
        working scale reports (counted and alarmed, never fed to the correction)."""
        scale = self.hopper_scale
        assert scale is not None
        try:
            kg = await scale.read()
        except BadReading as exc:
            self._hopper_good = 0
            if not self.alarms.is_active("hopper_scale.bad_reading"):
                log.warning("%s; %d such readings rejected so far", exc, scale.bad_readings)
            self.alarms.set(
                "hopper_scale.bad_reading", True,
                f"{exc}: {scale.bad_readings} readings rejected so far, none used; sowing on "
                "the model with the last correction", "warning",
            )
            return None
        except DriverError:
            return None
        self._hopper_good += 1
        if self._hopper_good >= BAD_READING_CLEAR_AFTER:  # no alarm event per flicker
            self.alarms.clear("hopper_scale.bad_reading")
        return kg

    def on_tick(self, out: ControlOutputs) -> None:
        """Hook for per-tick observers (watchdog kick, telemetry); set by optional parts."""
        for hook in self.tick_hooks:
            hook(out)

    async def _write_outputs(
        self, motor: float, fan: float, *, force: bool = False, reply_t: float | None = None
    ) -> dict[Channel, str]:
        """Write the duties that changed (or all, when due or forced); the channels whose
        write failed, with the driver's error (the control loop retries them next tick)."""
        failed: dict[Channel, str] = {}
        if not self.rs485:
            return failed
        now = self.clock()
        refresh = now - self._written_at >= self._refresh_s
        wanted: dict[Channel, float] = {"motor": round(motor, 1), "fan": round(fan, 1)}
        for channel, pct in wanted.items():
            prev = self._written.get(channel)
            if not (force or refresh or prev is None or abs(prev - pct) >= DUTY_EPSILON_PCT):
                continue
            if reply_t is not None:
                self.latencies_s.append(self.clock() - reply_t)
                reply_t = None  # latency is to the first write after the reply
            try:
                await self.pwm.write_duty(channel, pct)
            except DriverError as exc:
                self._written.pop(channel, None)  # unknown: rewrite as soon as it answers
                failed[channel] = str(exc)
                continue
            self._written[channel] = pct
        if refresh or force:
            self._written_at = now
        return failed

    async def _read_roll(self) -> None:
        """The inclinometer's roll axis for the seed positioner's terrain correction; a
        missed reading only leaves the seeds of the next second uncorrected (and flagged)."""
        assert self.roll_sensor is not None
        try:
            roll = await self.roll_sensor.read()
        except DriverError:
            return
        t = self.clock()
        for listener in self.roll_listeners:
            listener(t, roll)

    async def _keep_pwm_watchdog(self) -> None:
        """Program the PWM module's communication-loss timeout and verify it by reading back.

        Done at start and again whenever the module was lost (a request to it failed, the port
        vanished): it may have been power-cycled, and its watchdog is the only thing that
        stops the motor while sowgate cannot reach it. A module that refuses the register or
        reads back something else has no such watchdog: critical alarm ``pwm.no_watchdog``.
        """
        if not self.rs485:
            return
        if self._watchdog_verified:
            if self.bus.available(self.pwm.name):
                return
            self._watchdog_verified = False  # lost since: program it again once it answers
        now = self.clock()
        if now < self._watchdog_retry_at:
            return
        timeout_s = self.settings.actuators.comm_timeout_s
        try:
            await self.pwm.set_comm_timeout(timeout_s)
        except DeviceRejected as exc:
            self._watchdog_retry_at = now + WATCHDOG_RETRY_REFUSED_S
            self.alarms.set(
                "pwm.no_watchdog",
                True,
                "PWM module has no communication-loss watchdog "
                f"(register {self.pwm.comm_timeout_register:#06x}: {exc}); the motor would "
                "keep running if RS485 failed: do not use this module",
                "critical",
            )
            return
        except DriverError:
            self._watchdog_retry_at = now + WATCHDOG_RETRY_UNANSWERED_S
            return  # not answering: pwm.unavailable says so
        if not self.alarms.is_active("pwm.no_watchdog"):
            log.info("PWM module comm-loss timeout set to %g s and verified", timeout_s)
        self._watchdog_verified = self._watchdog_ever_verified = True
        self.alarms.clear("pwm.no_watchdog")

    def _update_device_alarms(self) -> None:
        if not self.rs485:
            return
        now = self.clock()
        devices = [("radar", "radar"), ("inclinometer", "inclinometer"), ("pwm", "PWM module")]
        if self.hopper_scale is not None:
            devices.append(("hopper_scale", "hopper scale"))
        for name, label in devices:
            st = self.bus.stats.get(name)
            lost = False
            if st is not None and st.available:
                self._answering_at[name] = now
            elif st is not None:
                since = self._answering_at.setdefault(name, now)
                lost = now - since >= DEVICE_LOST_AFTER_S
            self.alarms.set(
                f"{name}.unavailable",
                lost,
                f"{label} not answering on RS485: {st.last_error if st else ''}"
                + ("; sowing on the model with the last correction"
                   if name == "hopper_scale" else ""),
                "critical" if name == "pwm" else "warning",
            )

    # ---- telemetry ----------------------------------------------------------------------------
    def state(self) -> MachineState:
        """The machine now, for the terminal view, the touchscreen and the MQTT state payload:
        built afresh on each call from the controller's last outputs and the parts' states."""
        out = self.outputs
        c = self.controller
        parts = self.parts
        devices = {name: st.available for name, st in self.bus.stats.items()}
        gnss = parts.gnss
        fix: FixQuality = "none"
        if gnss is not None and gnss.available and gnss.latest is not None:
            fix = gnss.latest.fix
            devices["gnss"] = True
        elif gnss is not None:
            devices["gnss"] = False
        # the screen and the seed-tube sensors are devices a dashboard must see go missing too
        if self.hmi is not None:
            devices["hmi"] = self.hmi.link.available
        if parts.seed_sensors is not None:
            devices["seed_sensors"] = bool(parts.seed_sensors.available)
        return MachineState(
            machine_id=self.settings.machine.id,
            utc=datetime.now(UTC),
            work_state=out.state.value if out else "stopped",
            mode=c.mode.value,
            speed_kmh=out.speed_kmh if out else None,
            speed_source=out.speed_source if out else None,
            tilt_deg=out.tilt_deg if out else None,
            raised=out.raised if out else True,
            crop=c.crop,
            target_rate_kg_ha=(
                out.target_rate_kg_ha
                if out is not None and out.target_rate_kg_ha is not None
                else c.rate_kg_ha
            ),
            commanded_rate_kg_ha=out.commanded_rate_kg_ha if out else 0.0,
            motor_duty_pct=out.motor_pct if out else 0.0,
            fan_duty_pct=out.fan_pct if out else 0.0,
            devices=devices,
            alarms=tuple(
                ActiveAlarmState(a.code, a.severity, a.message, a.since)
                for a in self.alarms.active
            ),
            area_ha=c.counters.area_m2 / 10_000.0,
            seed_mass_kg=c.counters.seed_mass_g / 1000.0,
            gnss_fix=fix,
            store=parts.store.state() if parts.store is not None else None,
            seeds=parts.seeds.state() if parts.seeds is not None else None,
            metering=parts.metering.status() if parts.metering is not None else None,
            pwm_channel=parts.pwm_channel.state() if parts.pwm_channel is not None else None,
            rejected=parts.rejected.counts() if parts.rejected is not None else None,
            hopper=c.hopper.state(self.clock()) if c.hopper is not None else None,
            unacknowledged=tuple((a.code, a.message) for a in self.alarms.unacknowledged),
            seed_lot=self.live_calibration.lot_of(c.crop),
            seed_lots=dict(self.live_calibration.lots),
            row_monitor=parts.row_alarms.report() if parts.row_alarms is not None else None,
        )

async def _stop_in_stages(
    stages: dict[int, list[asyncio.Task[None]]],
    drains: list[Callable[[], Coroutine[Any, Any, None]]],
) -> None:
    """Cancel each stage's tasks and wait until they have finished, lowest stage first; then
    run the drains (what the last stage committed, published while the link still runs).

    Only waited for, never awaited: a task's own error is the supervisor's to report. A task
    that swallows its cancel is cancelled again (``cancel_all``) rather than waited for
    forever. A drain that fails is logged; the stop goes on.
    """
    for stage in sorted(stages):
        await cancel_all(stages[stage])
    for drain in drains:
        try:
            await drain()
        except Exception:
            log.exception("drain on stop failed")
