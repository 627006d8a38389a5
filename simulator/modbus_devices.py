"""The RS485 bus of paper A's seeder in software: radar, inclinometer, PWM module (and, when
given, the hopper scale's weight transmitter) as ONE pymodbus RTU server, reachable by the
daemon on a pty, with the faults a real bus produces.

Wiring (two pty pairs, bytes pumped by :class:`Rs485Simulator`)::

    daemon --pyserial--> device_path (symlink) = line pty  <== relay ==>  server pty <-- pymodbus

The relay is the "cable": it lets the simulator unplug the port (``vanish``/``restore``) while
the pymodbus server keeps running. Faults that concern whole frames (silence, CRC corruption,
noise before a reply) are applied in the server's ``trace_packet`` hook, where pymodbus hands
over each reply as one complete frame, so no re-framing is needed here.

The fault matrix of one device (``set_fault``), as a real RS485 node shows it to the master:
``silent`` (dead node), ``crc`` (every reply with a wrong CRC), ``wrong_id`` (replies carry
another device id), ``exception`` (replies are Modbus exception 4, device failure),
``truncated`` (replies lose their last bytes) and ``noise`` (line noise before every reply
and on one of its bytes).

The PWM module has a communication-loss watchdog, as the module type sowgate supports does
(``protocol.registers.PWM_COMM_TIMEOUT_REGISTER``): once the master has written a timeout,
a module that hears no request for that long sets both duties to 0 by itself. A module
without it (``pwm_watchdog=False``) answers "illegal data address" for that register.

Why silence is done by hand: a real RS485 device that is dead, or an id nobody owns, says
nothing and the master times out. pymodbus's server would instead answer an exception (its
``ignore_missing_devices`` is not honoured by the SimDevice datastore), so replies from
silenced or unknown ids are dropped before they reach the line.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import random
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Literal, get_args

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerRTU, FramerType
from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.tasks import StartClose
from gateway.config.machine import (
    ActuatorsSection,
    HopperScaleSection,
    InclinometerSection,
    RadarSection,
)
from protocol.errors import ProtocolError
from protocol.registers import (
    WITMOTION_ANGLE_BASE,
    RadarFormat,
    WeightFormat,
    decode_comm_timeout,
    decode_duty,
    encode_angle,
    encode_duty,
    inclinometer_span,
)
from simulator.pty_link import PtyPair

log = logging.getLogger(__name__)

Channel = Literal["motor", "fan"]
Fault = Literal["silent", "crc", "wrong_id", "exception", "truncated", "noise"]
FAULTS: tuple[Fault, ...] = get_args(Fault)

RELAY_CHUNK = 4096  # bytes per read on the relay; Modbus RTU frames are at most 256
MAX_GARBAGE_BYTES = 4096  # one injection; more would only test the pty buffer
_CATCH_ALL_ID = 0  # pymodbus routes ids without a SimDevice to id 0
EXCEPTION_DEVICE_FAILURE = 4  # the code a "exception" fault answers with
TRUNCATED_BYTES = 3  # what a "truncated" reply loses (its CRC and one data byte)
NOISE_BYTES = 5  # line noise put before every reply under a "noise" fault
WATCHDOG_CHECK_S = 0.05  # how often the simulated PWM module looks at its watchdog


def _answer_encoded(
    registers: list[int],
    start_address: int,
    address: int,
    encode: Callable[[], list[int]],
    what: str,
) -> ExcCodes | None:
    """Put the words ``encode`` gives at ``address`` in the reply a read is building (it
    starts at ``start_address``); a value the device cannot represent is what a real one does
    with it: a device-failure exception, and a warning naming ``what``."""
    try:
        words = encode()
    except (ProtocolError, ArithmeticError, ValueError) as exc:
        log.warning("simulated %s: %s", what, exc)
        return ExcCodes.DEVICE_FAILURE
    offset = address - start_address
    registers[offset : offset + len(words)] = words
    return None

class Rs485Simulator(StartClose):
    """Radar, WitMotion inclinometer and PWM module on one simulated RS485 bus.

    Use as ``async with Rs485Simulator(...) as sim:`` and point the daemon at
    ``sim.device_path``. Values come from the callables at each request, so a plant model can
    drive them; ``on_duty`` is called when the master writes a motor or fan register.
    """

    def __init__(
        self,
        *,
        radar_kmh: Callable[[], float],
        tilt_deg: Callable[[], float],
        on_duty: Callable[[str, float], None] | None = None,
        radar: RadarSection | None = None,
        inclinometer: InclinometerSection | None = None,
        actuators: ActuatorsSection | None = None,
        link_path: str | os.PathLike[str] | None = None,
        baudrate: int = 9600,
        rng: random.Random | None = None,
        pwm_watchdog: bool = True,
        hopper_kg: Callable[[], float] | None = None,
        hopper: HopperScaleSection | None = None,
        roll_deg: Callable[[], float] | None = None,
    ) -> None:
        self.radar = radar or RadarSection()
        # the hopper's weight transmitter, only when ``hopper_kg`` says what it weighs
        self.hopper = (hopper or HopperScaleSection()) if hopper_kg is not None else None
        self._hopper_kg = hopper_kg
        self.inclinometer = inclinometer or InclinometerSection()
        self.actuators = actuators or ActuatorsSection()
        ids = [self.radar.device_id, self.inclinometer.device_id, self.actuators.device_id]
        if self.hopper is not None:
            ids.append(self.hopper.device_id)
        if len(set(ids)) != len(ids):
            raise ValueError(f"RS485 device ids must be distinct (radar, incl., pwm = {ids})")
        self._radar_kmh = radar_kmh
        self._tilt_deg = tilt_deg
        # the machine's roll on the roll axis (when that is not the configured tilt axis);
        # None: the other axes read 0
        self._roll_deg = roll_deg
        self._on_duty = on_duty
        self._radar_format = RadarFormat(
            data_type=self.radar.data_type,
            word_order=self.radar.word_order,
            scale=self.radar.scale,
            unit=self.radar.unit,
            mount_angle_deg=self.radar.mount_angle_deg,
        )
        self._weight_format = None if self.hopper is None else WeightFormat(
            data_type=self.hopper.data_type,
            word_order=self.hopper.word_order,
            grams_per_count=self.hopper.scale,
            capacity_kg=self.hopper.capacity_kg,
        )
        self._baudrate = baudrate
        self._rng = rng or random.Random()
        self._requested_link = Path(link_path) if link_path is not None else None
        self._tmpdir: str | None = None
        self._link: Path | None = None
        self._line: PtyPair | None = None
        self._server_pty: PtyPair | None = None
        self._server: ModbusSerialServer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

        self._silent: set[int] = set()
        self._faults: dict[int, Fault] = {}
        self._reply_delay_s: dict[int, float] = {}
        self.replies_pending = 0  # delayed replies not on the line yet
        self._held_replies: list[bytes] = []  # what the server sent since, queued behind them
        self._radar_held: float | None = None
        self.radar_scale = 1.0  # the surface under the radar (see set_radar_scale)
        self._corrupt_left = 0
        self._garbage: bytes = b""
        self.duty_pct: dict[str, float] = {"motor": 0.0, "fan": 0.0}
        self.replies_dropped = 0  # replies swallowed because the id is silent or unknown
        self.requests_seen: dict[int, int] = {}
        # the PWM module's communication-loss watchdog (see the module docstring)
        self.pwm_watchdog = pwm_watchdog
        self.comm_timeout_s = 0.0  # 0: off, as the module powers up
        self.comm_timeout_writes = 0  # how often the master wrote the timeout register
        self.watchdog_trips = 0  # how often the module stopped both outputs by itself
        self._pwm_heard_at = 0.0  # loop time of the last request the module heard
        self._watchdog_task: asyncio.Task[None] | None = None

    # -------------------------------------------------------------------------------------
    # lifecycle

    @property
    def device_path(self) -> str:
        """The port the daemon opens (stable across ``vanish``/``restore``)."""
        if self._link is None:
            raise RuntimeError("Rs485Simulator is not started")
        return str(self._link)

    @property
    def device_ids(self) -> dict[str, int]:
        ids = {
            "radar": self.radar.device_id,
            "inclinometer": self.inclinometer.device_id,
            "pwm": self.actuators.device_id,
        }
        if self.hopper is not None:
            ids["hopper_scale"] = self.hopper.device_id
        return ids

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        if self._requested_link is None:
            self._tmpdir = tempfile.mkdtemp(prefix="sowgate-rs485-")
            self._link = Path(self._tmpdir) / "rs485"
        else:
            self._link = self._requested_link
        try:
            self._server_pty = PtyPair()
            self._server = ModbusSerialServer(
                self._build_devices(),
                framer=FramerType.RTU,
                port=self._server_pty.slave_path,
                baudrate=self._baudrate,
                trace_packet=self._trace_packet,
            )
            await self._server.serve_forever(background=True)
            self._loop.add_reader(self._server_pty.master_fd, self._pump_from_server)
            self._open_line()
            self._watchdog_task = self._loop.create_task(
                self._run_pwm_watchdog(), name="sim-pwm-watchdog"
            )
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Stop the server and remove both ptys and the symlink. Idempotent."""
        if self._watchdog_task is not None:
            task, self._watchdog_task = self._watchdog_task, None
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._close_line()
        if self._server is not None:
            server, self._server = self._server, None
            await server.shutdown()  # type: ignore[no-untyped-call]
        if self._server_pty is not None:
            if self._loop is not None:
                self._loop.remove_reader(self._server_pty.master_fd)
            self._server_pty.close()
            self._server_pty = None
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    # -------------------------------------------------------------------------------------
    # fault injection

    def inject_garbage(self, n_bytes: int) -> bytes:
        """Put ``n_bytes`` of line noise on the bus just before the next reply (noise while
        the master is idle is discarded by it anyway). Returns the bytes, for the test log."""
        if not 0 < n_bytes <= MAX_GARBAGE_BYTES:
            raise ValueError(f"n_bytes must be 1..{MAX_GARBAGE_BYTES} (got {n_bytes})")
        noise = self._rng.randbytes(n_bytes)
        self._garbage += noise
        return noise

    def inject_bytes(self, data: bytes) -> None:
        """Like :meth:`inject_garbage` with chosen bytes (reproducible tests)."""
        if len(self._garbage) + len(data) > MAX_GARBAGE_BYTES:
            raise ValueError(f"at most {MAX_GARBAGE_BYTES} bytes of noise may be pending")
        self._garbage += data

    def corrupt_next_crc(self, count: int = 1) -> None:
        """The next ``count`` replies go out with a wrong CRC (last byte inverted)."""
        if count < 0:
            raise ValueError(f"count must be >= 0 (got {count})")
        self._corrupt_left = count

    def set_silent(self, device_id: int, silent: bool) -> None:
        """A silent device ignores requests: no reply, no side effect (a dead RS485 node)."""
        if silent:
            self._silent.add(device_id)
        else:
            self._silent.discard(device_id)

    def set_fault(self, device_id: int, fault: Fault | None) -> None:
        """Every reply of ``device_id`` shows ``fault`` (see the module docstring) until
        ``set_fault(device_id, None)``. ``silent`` is :meth:`set_silent`."""
        if fault is not None and fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}, expected one of {FAULTS}")
        self.set_silent(device_id, fault == "silent")
        if fault is None or fault == "silent":
            self._faults.pop(device_id, None)
        else:
            self._faults[device_id] = fault

    def set_reply_delay(self, device_id: int, seconds: float) -> None:
        """``device_id`` answers ``seconds`` after each request (a slow node), so a test can
        find a request still outstanding; 0 answers at once again."""
        if seconds < 0:
            raise ValueError(f"reply delay must be >= 0 s (got {seconds})")
        self._reply_delay_s[device_id] = seconds

    def _delay_reply(self, data: bytes) -> bool:
        """Hold ``data`` (bytes the server put on the line) if it is the reply of a slow
        device, or if an earlier reply is still held: one reply at a time on a half-duplex
        line, so whatever the server answers meanwhile comes after it. True if held."""
        delay = self._reply_delay_s.get(data[0], 0.0) if data else 0.0
        if self.replies_pending == 0 and delay <= 0:
            return False
        assert self._loop is not None
        self._held_replies.append(data)
        if delay > 0:
            self.replies_pending += 1
            self._loop.call_later(delay, self._release_reply)
        return True

    def _release_reply(self) -> None:
        """Put the oldest held reply, and all queued behind it up to the next slow one, on
        the line."""
        self.replies_pending -= 1
        while self._held_replies:
            data = self._held_replies.pop(0)
            if self._line is not None:
                _write_all(self._line.master_fd, data, "daemon")
            next_slow = self._held_replies and self._reply_delay_s.get(
                self._held_replies[0][0], 0.0
            ) > 0
            if next_slow:
                break

    def set_radar_scale(self, scale: float) -> None:
        """The radar reads ``scale`` × the plant's speed from now on: the surface changed
        since its calibration (stubble to a seedbed, wet soil) or its mounting was knocked."""
        if not scale > 0.0:
            raise ValueError("radar scale must be above 0")
        self.radar_scale = scale

    def hold_radar(self, kmh: float | None) -> None:
        """The radar reads ``kmh`` whatever the plant does (e.g. 0 while it loses its echo);
        ``None`` hands it back to the plant."""
        self._radar_held = kmh

    @property
    def vanished(self) -> bool:
        return self._line is None

    def vanish(self) -> None:
        """Unplug the port: the daemon's open fd fails with EIO and the path disappears."""
        self._close_line()

    def restore(self) -> None:
        """Plug the port back in on the same ``device_path`` (a fresh pty behind it)."""
        if self._line is None:
            self._open_line()

    # -------------------------------------------------------------------------------------
    # the relay ("cable")

    def _open_line(self) -> None:
        assert self._loop is not None and self._link is not None
        self._line = PtyPair(self._link)
        self._loop.add_reader(self._line.master_fd, self._pump_from_daemon)

    def _close_line(self) -> None:
        if self._line is None:
            return
        line, self._line = self._line, None
        if self._loop is not None and not line.closed:
            self._loop.remove_reader(line.master_fd)
        line.close()

    def _pump_from_daemon(self) -> None:
        if self._line is None or self._server_pty is None:
            return
        data = _read_some(self._line.master_fd)
        if data:
            _write_all(self._server_pty.master_fd, data, "server")

    def _pump_from_server(self) -> None:
        if self._server_pty is None:
            return
        data = _read_some(self._server_pty.master_fd)
        if self._delay_reply(data):
            return
        if data and self._line is not None:
            _write_all(self._line.master_fd, data, "daemon")

    # -------------------------------------------------------------------------------------
    # frame-level faults (pymodbus hands us each complete frame here)

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending or not data:
            return data
        device_id = data[0]
        self.requests_seen[device_id] = self.requests_seen.get(device_id, 0) + 1
        if device_id in self._silent or device_id not in self.device_ids.values():
            self.replies_dropped += 1
            return b""
        fault = self._faults.get(device_id)
        if fault is not None:
            data = self._faulty_reply(fault, data)
        if self._corrupt_left > 0:
            self._corrupt_left -= 1
            data = data[:-1] + bytes([data[-1] ^ 0xFF])
        if self._garbage:
            data, self._garbage = self._garbage + data, b""
        return data

    def _faulty_reply(self, fault: Fault, reply: bytes) -> bytes:
        """What a device with ``fault`` puts on the line instead of ``reply``."""
        device_id, function = reply[0], reply[1] & 0x7F
        if fault == "crc":
            return reply[:-1] + bytes([reply[-1] ^ 0xFF])
        if fault == "wrong_id":
            other = (device_id % 247) + 1
            return _with_crc(bytes([other]) + reply[1:-2])
        if fault == "exception":
            return _with_crc(bytes([device_id, function | 0x80, EXCEPTION_DEVICE_FAILURE]))
        if fault == "truncated":
            return reply[:-TRUNCATED_BYTES]
        if fault == "noise":  # noise before the reply and a byte of it hit as well
            hit = 1 + self._rng.randrange(len(reply) - 3)
            flipped = reply[hit] ^ (1 + self._rng.randrange(255))
            hit_reply = reply[:hit] + bytes([flipped]) + reply[hit + 1 :]
            return self._rng.randbytes(NOISE_BYTES) + hit_reply
        return reply

    # -------------------------------------------------------------------------------------
    # the PWM module's communication-loss watchdog

    async def _run_pwm_watchdog(self) -> None:
        while True:
            await asyncio.sleep(WATCHDOG_CHECK_S)
            assert self._loop is not None
            quiet_for = self._loop.time() - self._pwm_heard_at
            on = any(pct != 0.0 for pct in self.duty_pct.values())
            if on and self.comm_timeout_s > 0.0 and quiet_for > self.comm_timeout_s:
                self.watchdog_trips += 1
                log.info(
                    "simulated PWM module heard nothing for %.2f s (timeout %.1f s): "
                    "outputs off", quiet_for, self.comm_timeout_s,
                )
                for channel in ("motor", "fan"):
                    self._set_duty(channel, 0.0)

    def _set_duty(self, channel: str, pct: float) -> None:
        self.duty_pct[channel] = pct
        if self._on_duty is not None:
            self._on_duty(channel, pct)

    # -------------------------------------------------------------------------------------
    # device models

    def _build_devices(self) -> list[SimDevice]:
        radar_regs = SimData(
            self.radar.address,
            count=self._radar_format.count,
            values=0,
            datatype=DataType.REGISTERS,
            readonly=True,
        )
        _, per_axis = inclinometer_span(self.inclinometer.layout, "roll")
        incl_regs = SimData(
            WITMOTION_ANGLE_BASE,
            count=3 * per_axis,
            values=0,
            datatype=DataType.REGISTERS,
            readonly=True,
        )
        pwm_regs = [
            SimData(self.actuators.motor_register, values=0, datatype=DataType.REGISTERS),
            SimData(self.actuators.fan_register, values=0, datatype=DataType.REGISTERS),
        ]
        if self.pwm_watchdog:
            pwm_regs.append(
                SimData(
                    self.actuators.comm_timeout_register, values=0, datatype=DataType.REGISTERS
                )
            )
        pwm_regs.sort(key=lambda d: d.address)
        hopper: list[SimDevice] = []
        if self.hopper is not None and self._weight_format is not None:
            scale_regs = SimData(
                self.hopper.address,
                count=self._weight_format.count,
                values=0,
                datatype=DataType.REGISTERS,
                readonly=True,
            )
            hopper.append(
                SimDevice(self.hopper.device_id, simdata=[scale_regs], action=self._scale_action)
            )
        return [
            *hopper,
            SimDevice(self.radar.device_id, simdata=[radar_regs], action=self._radar_action),
            SimDevice(
                self.inclinometer.device_id, simdata=[incl_regs], action=self._incl_action
            ),
            SimDevice(self.actuators.device_id, simdata=pwm_regs, action=self._pwm_action),
            SimDevice(_CATCH_ALL_ID, simdata=[SimData(0, datatype=DataType.INVALID)]),
        ]

    async def _radar_action(
        self,
        func_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if self.radar.device_id in self._silent or set_values is not None:
            return None
        kmh = (self._radar_kmh() * self.radar_scale if self._radar_held is None
               else self._radar_held)
        radar_format = self._radar_format
        return _answer_encoded(
            registers, start_address, self.radar.address,
            lambda: radar_format.encode_kmh(kmh), "radar cannot encode its speed",
        )

    async def _scale_action(
        self,
        func_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if self.hopper is None or self._hopper_kg is None or self._weight_format is None:
            return ExcCodes.DEVICE_FAILURE
        if self.hopper.device_id in self._silent or set_values is not None:
            return None
        weight_format, hopper_kg = self._weight_format, self._hopper_kg
        return _answer_encoded(
            registers, start_address, self.hopper.address,
            lambda: weight_format.encode_kg(hopper_kg()), "hopper scale cannot encode its weight",
        )

    async def _incl_action(
        self,
        func_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if self.inclinometer.device_id in self._silent or set_values is not None:
            return None
        layout = self.inclinometer.layout
        try:
            words = encode_angle(self._tilt_deg(), layout)
        except (ProtocolError, ArithmeticError, ValueError) as exc:
            log.warning("simulated inclinometer cannot encode its angle: %s", exc)
            return ExcCodes.DEVICE_FAILURE
        first, _ = inclinometer_span(layout, self.inclinometer.axis)
        zero = encode_angle(0.0, layout)
        roll = zero if self._roll_deg is None else encode_angle(self._roll_deg(), layout)
        for axis in ("roll", "pitch", "yaw"):
            axis_first, n = inclinometer_span(layout, axis)
            offset = axis_first - start_address
            other = roll if axis == "roll" else zero
            registers[offset : offset + n] = words if axis_first == first else other
        return None

    async def _pwm_action(
        self,
        func_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if self.actuators.device_id in self._silent:
            return None  # a dead node hears nothing: its watchdog keeps counting
        assert self._loop is not None
        self._pwm_heard_at = self._loop.time()
        timeout_reg = self.actuators.comm_timeout_register if self.pwm_watchdog else None
        channels = {self.actuators.motor_register: "motor", self.actuators.fan_register: "fan"}
        if set_values is None:  # a read: answer what the outputs really are
            for reg, channel in channels.items():
                if address <= reg < address + count:
                    registers[reg - start_address] = encode_duty(self.duty_pct[channel])
            if timeout_reg is not None and address <= timeout_reg < address + count:
                registers[timeout_reg - start_address] = round(self.comm_timeout_s * 10)
            return None
        changes: list[tuple[str, float]] = []
        timeout_s: float | None = None
        for i, raw in enumerate(set_values):
            reg = address + i
            try:
                if reg == timeout_reg:
                    timeout_s = decode_comm_timeout(int(raw))
                elif reg in channels:
                    changes.append((channels[reg], decode_duty(int(raw))))
            except ProtocolError:
                return ExcCodes.ILLEGAL_VALUE  # the module refuses it, nothing changes
        if timeout_s is not None:
            self.comm_timeout_s = timeout_s
            self.comm_timeout_writes += 1
        for channel, pct in changes:
            self._set_duty(channel, pct)
        return None


def _with_crc(frame: bytes) -> bytes:
    return frame + FramerRTU.compute_CRC(frame).to_bytes(2, "big")


def _read_some(fd: int) -> bytes:
    with contextlib.suppress(BlockingIOError, InterruptedError):
        try:
            return os.read(fd, RELAY_CHUNK)
        except OSError as exc:  # EIO: nobody on the far side right now
            log.debug("relay read on fd %d failed: %s", fd, exc)
    return b""


def _write_all(fd: int, data: bytes, towards: str) -> None:
    """Write everything or drop the rest: a full pty buffer means the peer is not reading,
    and an RS485 line does not queue bytes for a deaf receiver either."""
    view = memoryview(data)
    while view:
        try:
            n = os.write(fd, view)
        except (BlockingIOError, InterruptedError):
            log.warning("relay dropped %d bytes towards the %s (buffer full)", len(view), towards)
            return
        except OSError as exc:
            log.debug("relay write towards the %s failed: %s", towards, exc)
            return
        view = view[n:]
