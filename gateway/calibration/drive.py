"""Driving the meter through a rotation test: set point after set point, motor off between.

``sowgate calibrate rotation --drive modbus|can`` runs the metering motor itself, the way a
fitter would from the cab, so that the catch belongs to a known set point and run time:

- ``ModbusMeterDrive``: paper A's motor and fan on the RS485 PWM module. The module's
  communication-loss watchdog is programmed and read back first (a module without one is
  refused: nothing would stop the motor if this process died); the fan runs at its working
  duty for the whole test (the air carries the seed to the outlets) and both duties are
  rewritten at least every ``actuators.comm_timeout_s`` / 2, the watchdog's keep-alive.
- ``CanMeterDrive``: one of paper B's ``can_pid`` channel controllers over CAN. The command
  frames go on at ``can.command_hz`` for the whole test (target 0 between runs, so the
  controller's own command timeout never fires), and the shaft's status frames are integrated
  into the turns of each run, run-down included.

``drive_runs`` is the one place the runs happen: the motor is set to 0 at the end of each run,
and ``close()`` (motor and fan 0, bus closed) runs in a ``finally`` whatever ends the test: a
normal end, a bus or controller error, or Ctrl-C (``asyncio.run`` turns SIGINT into the
cancellation of the test's task, which reaches that ``finally``).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import threading
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from drivers.can_bus import CanBus, MeteringCanLink
from drivers.errors import DeviceRejected, DriverError
from drivers.modbus_bus import ModbusBus
from drivers.rs485_devices import PwmModule
from gateway.calibration.fits import CalibrationError
from gateway.config import Settings
from protocol.can_metering import MeterStatus

log = logging.getLogger(__name__)

TICK_S = 0.2  # progress report and health check while a run is on
RUN_DOWN_MAX_S = 3.0  # after a CAN-driven run, follow the shaft until it stops (at most)
RUN_DOWN_STOPPED_RPM = 0.5
OFF_TIMEOUT_S = 1.0
CAN_OPEN_TIMEOUT_S = 5.0  # longest wait for one "off" write at the end
# A controller idle for a while reports its command timeout until our first frames of the run
# reach it; faults are believed from this long after a run starts.
FAULT_GRACE_S = 0.5
DEFAULT_FAN_SETTLE_S = 3.0  # the fan comes up to speed before the first run's motor starts

Progress = Callable[[float], None]  # seconds of the run elapsed


class MeterDrive(Protocol):
    """What ``drive_runs`` needs of a meter it drives (see the two implementations)."""

    what: str  # the set point's unit, for the progress lines: "r/min" or "% duty"

    async def open(self) -> None:
        """Take the bus, motor 0, fan at its working duty (where there is one)."""

    async def run(self, setpoint: float, seconds: float, progress: Progress) -> float | None:
        """Drive at ``setpoint`` for ``seconds``, leave the motor at 0; the shaft's measured
        turns over the run (None: no shaft sensor). Raises on any error (motor set to 0)."""

    async def check(self) -> None:
        """Raise the error that happened between runs (a keep-alive write failed), if any."""

    async def close(self) -> None:
        """Motor and fan to 0, bus released. Safe to call twice."""


def _describe(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__


class ModbusMeterDrive:
    """Paper A's metering motor (and fan) on the RS485 PWM module, by duty %."""

    what = "% duty"

    def __init__(self, settings: Settings, *, fan_pct: float,
                 fan_settle_s: float = DEFAULT_FAN_SETTLE_S,
                 bus: ModbusBus | None = None) -> None:
        if not settings.rs485.enabled:
            raise CalibrationError("--drive modbus needs the RS485 bus ([rs485] enabled = false)")
        self.settings = settings
        self.bus = bus or ModbusBus.from_config(settings.rs485)
        self.pwm = PwmModule(self.bus, settings.actuators)
        self.fan_pct = fan_pct
        self.fan_settle_s = fan_settle_s
        act = settings.actuators
        self.keepalive_s = min(act.refresh_s, act.comm_timeout_s / 2.0)
        self._duty = {"motor": 0.0, "fan": 0.0}
        self._lock = asyncio.Lock()  # a write always sends the latest duty, in order
        self._keepalive: asyncio.Task[None] | None = None
        self._closed = False
        self._switched_on = False  # a non-zero duty was sent: the off at close must succeed

    async def _write(self, channel: str, pct: float) -> None:
        async with self._lock:
            self._duty[channel] = pct
            self._switched_on = self._switched_on or pct > 0
            await self.pwm.write_duty("motor" if channel == "motor" else "fan", pct)

    async def _keep_alive(self) -> None:
        while True:
            await asyncio.sleep(self.keepalive_s)
            async with self._lock:
                for channel in ("fan", "motor"):
                    await self.pwm.write_duty("motor" if channel == "motor" else "fan",
                                              self._duty[channel])

    async def open(self) -> None:
        await self.bus.start()
        timeout_s = self.settings.actuators.comm_timeout_s
        where = f"PWM module (id {self.pwm.device_id}) on {self.bus.port}"
        try:
            await self.pwm.set_comm_timeout(timeout_s)
        except DeviceRejected as exc:
            raise CalibrationError(
                f"{where} has no communication-loss watchdog ({exc}): nothing would stop the "
                "motor if this command died; not driving it"
            ) from None
        except DriverError as exc:
            raise CalibrationError(f"{where} does not answer: {exc}") from None
        await self._write("motor", 0.0)
        await self._write("fan", self.fan_pct)
        self._keepalive = asyncio.create_task(self._keep_alive(), name="calibrate-keepalive")
        if self.fan_pct > 0 and self.fan_settle_s > 0:
            await self._sleep_checked(self.fan_settle_s, None)

    async def _sleep_checked(self, seconds: float, progress: Progress | None) -> None:
        loop = asyncio.get_running_loop()
        start = loop.time()
        while (elapsed := loop.time() - start) < seconds:
            if progress is not None:
                progress(elapsed)
            await self.check()
            await asyncio.sleep(min(TICK_S, seconds - elapsed))
        await self.check()

    async def check(self) -> None:
        task = self._keepalive
        if task is not None and task.done():
            exc = None if task.cancelled() else task.exception()
            raise CalibrationError(
                f"the PWM module stopped answering: {_describe(exc) if exc else 'keep-alive ended'}"
            )

    async def run(self, setpoint: float, seconds: float, progress: Progress) -> float | None:
        try:
            await self._write("motor", setpoint)
            await self._sleep_checked(seconds, progress)
        finally:
            with contextlib.suppress(DriverError, TimeoutError):
                async with asyncio.timeout(OFF_TIMEOUT_S):
                    await self._write("motor", 0.0)
        return None  # no shaft sensor on paper A's bus: the fitter reads the shaft speed

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._keepalive is not None:
            self._keepalive.cancel()
            with contextlib.suppress(BaseException):
                await self._keepalive
        failed: list[str] = []
        for channel in ("motor", "fan"):
            try:
                async with asyncio.timeout(OFF_TIMEOUT_S):
                    await self._write(channel, 0.0)
            except (DriverError, TimeoutError) as exc:
                failed.append(f"{channel}: {_describe(exc)}")
        await self.bus.close()
        if failed and self._switched_on:
            raise CalibrationError(
                "could not switch the meter off (" + "; ".join(failed) + "): the PWM module's "
                "watchdog sets both to 0 after actuators.comm_timeout_s = "
                f"{self.settings.actuators.comm_timeout_s:g} s without a request"
            )


@dataclass
class _Sample:
    t: float
    rpm: float


class CanMeterDrive:
    """One ``can_pid`` channel's controller over CAN, by shaft r/min, with shaft feedback."""

    what = "r/min"

    def __init__(self, settings: Settings, channel: str) -> None:
        if not settings.can.enabled:
            raise CalibrationError("--drive can needs the CAN bus ([can] table in --config)")
        ch = next((c for c in settings.channel if c.name == channel and c.drive == "can_pid"),
                  None)
        if ch is None:
            raise CalibrationError(f"no can_pid channel named {channel!r} in the config")
        self.settings = settings
        self.node = ch.node_id
        self.channel = channel
        can = settings.can
        self.bus = CanBus(can.interface, can.channel, can.bitrate)
        self.link: MeteringCanLink | None = None
        self._task: asyncio.Task[None] | None = None
        self._samples: list[_Sample] = []
        self._last_status: MeterStatus | None = None
        self._last_status_at: float | None = None
        self._closed = False
        self._switched_on = False

    def _on_status(self, status: MeterStatus, _t: float) -> None:
        now = asyncio.get_running_loop().time()
        self._samples.append(_Sample(now, status.measured_rpm))
        self._last_status, self._last_status_at = status, now

    async def open(self) -> None:
        try:
            async with asyncio.timeout(CAN_OPEN_TIMEOUT_S):
                await self.bus.open()  # retries with backoff: not for ever here
        except TimeoutError:
            raise CalibrationError(
                f"CAN {self.settings.can.interface} {self.settings.can.channel}: cannot be "
                f"opened within {CAN_OPEN_TIMEOUT_S:g} s ({self.bus.stats.last_error})"
            ) from None
        self.link = MeteringCanLink(self.bus, [self.node], command_hz=self.settings.can.command_hz)
        self.link.stop_all()
        self._task = asyncio.create_task(self.link.run(self._on_status), name="calibrate-can")
        # the controller must answer before its shaft is driven
        loop = asyncio.get_running_loop()
        deadline = loop.time() + max(1.0, self.settings.can.feedback_timeout_s)
        while self._last_status is None:
            await self.check()
            if loop.time() > deadline:
                raise CalibrationError(
                    f"channel {self.channel!r}: no status from its controller (node "
                    f"{self.node}) on CAN {self.settings.can.channel}; nothing driven"
                )
            await asyncio.sleep(0.05)

    async def check(self) -> None:
        task = self._task
        if task is not None and task.done():
            exc = None if task.cancelled() else task.exception()
            raise CalibrationError(f"CAN link ended: {_describe(exc) if exc else 'stopped'}")

    def _health(self, now: float, since: float) -> None:
        """Raise when the controller reports a fault or its status frames stop."""
        timeout = self.settings.can.feedback_timeout_s
        last = self._last_status_at if self._last_status_at is not None else since
        if now - max(last, since) > timeout:
            raise CalibrationError(
                f"channel {self.channel!r} (node {self.node}): no shaft feedback for "
                f"{now - max(last, since):.1f} s"
            )
        st, at = self._last_status, self._last_status_at
        if st is not None and at is not None and at >= since + FAULT_GRACE_S and (
                st.faulted or st.stalled):
            what = "shaft stalled" if st.stalled else f"fault {st.fault.name.lower()}"
            raise CalibrationError(
                f"channel {self.channel!r} (node {self.node}): controller reports {what}"
            )

    async def run(self, setpoint: float, seconds: float, progress: Progress) -> float | None:
        link = self.link
        assert link is not None
        loop = asyncio.get_running_loop()
        start = loop.time()
        first = len(self._samples)
        try:
            self._switched_on = True
            link.set_target(self.node, setpoint)
            await link.send_commands()  # now, not up to a command period later
            while (elapsed := loop.time() - start) < seconds:
                progress(elapsed)
                await self.check()
                self._health(loop.time(), start)
                await asyncio.sleep(min(TICK_S, seconds - elapsed))
            link.stop_all()
            await link.send_commands()
            # what the shaft delivers while running down lands in the catch too
            stopped_at = loop.time()
            while loop.time() - stopped_at < RUN_DOWN_MAX_S:
                await asyncio.sleep(0.1)
                await self.check()
                last = self._samples[-1] if self._samples else None
                if last is not None and last.t > stopped_at and last.rpm < RUN_DOWN_STOPPED_RPM:
                    break
        finally:
            link.stop_all()
            with contextlib.suppress(DriverError, TimeoutError):
                async with asyncio.timeout(OFF_TIMEOUT_S):
                    await link.send_commands()
        samples = [(s.t, s.rpm) for s in self._samples[first:]]
        return shaft_revolutions(samples) if len(samples) >= 2 else None

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        failed = None
        if self.link is not None:
            self.link.stop_all()
            try:
                async with asyncio.timeout(OFF_TIMEOUT_S):
                    await self.link.send_commands()
            except (DriverError, TimeoutError) as exc:
                failed = _describe(exc)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(BaseException):
                await self._task
        self.bus.close()
        if failed is not None and self._switched_on:
            raise CalibrationError(
                f"could not command channel {self.channel!r} off ({failed}): its controller "
                "stops by itself when the command frames stop"
            )


def shaft_revolutions(samples: Sequence[tuple[float, float]]) -> float:
    """Turns from (time s, measured r/min) status samples (trapezoid)."""
    return sum((t1 - t0) * (r0 + r1) / 2 / 60.0
               for (t0, r0), (t1, r1) in itertools.pairwise(samples))


@dataclass(frozen=True)
class RunReport:
    """What ``drive_runs`` tells the screen: ``started`` / ``progress`` / ``done``."""

    event: str
    index: int  # 0-based run
    elapsed_s: float = 0.0


async def ask_in_thread(ask: Callable[[str], float], question: str) -> float:
    """Ask at the prompt without stopping the loop (the keep-alive writes go on meanwhile).

    A daemon thread, not the loop's executor: after Ctrl-C at the prompt the safe-off runs
    and the process ends without waiting for an Enter that never comes."""
    loop = asyncio.get_running_loop()
    future: asyncio.Future[float] = loop.create_future()

    def target() -> None:
        try:
            value = ask(question)
        except BaseException as exc:  # handed to the loop
            loop.call_soon_threadsafe(_settle, future, None, exc)
        else:
            loop.call_soon_threadsafe(_settle, future, value, None)

    thread = threading.Thread(target=target, name="calibrate-prompt", daemon=True)
    _PROMPTS.difference_update([t for t in _PROMPTS if not t.is_alive()])
    _PROMPTS.add(thread)
    thread.start()
    return await future


_PROMPTS: set[threading.Thread] = set()


def abandoned_prompt() -> bool:
    """Whether a prompt thread is still blocked reading the terminal (Ctrl-C at a prompt).

    Such a thread holds standard input's lock, and the interpreter's shutdown then aborts
    (SIGABRT) when it touches standard input: ``sowgate calibrate`` ends with ``os._exit``
    instead, once the meter is off and the output flushed."""
    return any(t.is_alive() for t in _PROMPTS)


def _settle(future: asyncio.Future[float], value: float | None,
            exc: BaseException | None) -> None:
    if future.done():
        return
    if exc is not None:
        future.set_exception(exc)
    else:
        assert value is not None
        future.set_result(value)


async def drive_runs(
    drive: MeterDrive | None,
    setpoints: Sequence[float],
    seconds: float | Sequence[float],
    report: Callable[[RunReport], None],
    after_run: Callable[[int, float | None], Awaitable[None]],
) -> list[float | None]:
    """Run each set point for ``seconds`` (one length for all, or one per run) (with
    ``drive``; None: the operator runs the meter and this only times); ``after_run(i,
    turns)`` runs with the motor off (the catch is weighed then). Returns each run's measured
    shaft turns (None without a shaft sensor).

    The motor is 0 between runs, and motor and fan are 0 when this returns or raises,
    whatever the reason (``close()`` in the ``finally``)."""
    lengths = ([float(seconds)] * len(setpoints) if isinstance(seconds, (int, float))
               else [float(t) for t in seconds])
    if len(lengths) != len(setpoints):
        raise ValueError(f"{len(lengths)} run lengths for {len(setpoints)} runs")
    turns: list[float | None] = []
    loop = asyncio.get_running_loop()
    error: BaseException | None = None
    try:
        if drive is not None:
            await drive.open()
        for i, setpoint in enumerate(setpoints):
            report(RunReport("started", i))

            def progress(elapsed: float, i: int = i) -> None:
                report(RunReport("progress", i, elapsed))

            seconds_i = lengths[i]
            if drive is not None:
                turns.append(await drive.run(setpoint, seconds_i, progress))
            else:
                start = loop.time()
                while (elapsed := loop.time() - start) < seconds_i:
                    progress(elapsed)
                    await asyncio.sleep(min(TICK_S, seconds_i - elapsed))
                turns.append(None)
            report(RunReport("done", i, seconds_i))
            await after_run(i, turns[-1])
            if drive is not None:
                await drive.check()
    except BaseException as exc:
        error = exc
        raise
    finally:
        if drive is not None:
            try:
                await drive.close()
            except CalibrationError as off_failed:
                # the meter may still run: that must be said, with what ended the test
                if error is None:
                    raise
                stopped = isinstance(error, asyncio.CancelledError | KeyboardInterrupt)
                why = "interrupted" if stopped else _describe(error)
                raise CalibrationError(f"{why}; {off_failed}") from error
    return turns
