"""Typed calls for the devices on the RS485 bus: the daemon asks for km/h, degrees, kg and
duty percent, never for registers.

Each wrapper is built from its config section (``gateway.config.RadarSection`` etc., passed
duck-typed so this layer does not import ``gateway``). Bus failures arrive as
DeviceUnavailable / DeviceRejected naming the device; a reply that arrives intact but does not
decode (e.g. a NaN float) raises :class:`BadReading`. Polling and control live in gateway/.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

from drivers.errors import DeviceRejected
from drivers.modbus_bus import ModbusBus
from protocol.errors import FieldError, ProtocolError
from protocol.registers import (
    RadarFormat,
    WeightFormat,
    decode_angle,
    decode_comm_timeout,
    decode_duty,
    encode_comm_timeout,
    encode_duty,
    inclinometer_span,
)

Channel = Literal["motor", "fan"]


class BadReading(DeviceRejected):
    """The device answered a well-formed frame whose value makes no sense."""


class WatchdogNotSet(DeviceRejected):
    """The PWM module answered, but its communication-loss timeout does not read back as
    written: it has no such watchdog (or a different one) and would not stop by itself."""


class _BusDevice:
    """What the device wrappers share: a name on the bus, a Modbus id, and a read whose intact
    reply that does not decode becomes :class:`BadReading` naming the device (a bus failure
    stays DeviceUnavailable / DeviceRejected, raised by the bus)."""

    bus: ModbusBus
    name: str
    device_id: int

    @property
    def available(self) -> bool:
        return self.bus.available(self.name)

    async def _read_decoded(
        self, address: int, count: int, decode: Callable[[list[int]], float]
    ) -> float:
        registers = await self.bus.read_holding(self.name, self.device_id, address, count)
        try:
            return decode(registers)
        except ProtocolError as exc:
            raise BadReading(f"{self.name} (id {self.device_id}): {exc}") from exc


class Radar(_BusDevice):
    """Ground speed from the mm-wave radar, in km/h (Doppler eq. 1 applied if configured)."""

    def __init__(self, bus: ModbusBus, section: Any, *, name: str = "radar") -> None:
        self.bus = bus
        self.name = name
        self.device_id: int = section.device_id
        self.address: int = section.address
        self.format = RadarFormat(
            data_type=section.data_type,
            word_order=section.word_order,
            scale=section.scale,
            unit=section.unit,
            mount_angle_deg=section.mount_angle_deg,
        )

    async def read(self) -> float:
        return await self._read_decoded(self.address, self.format.count, self.format.decode_kmh)


class Inclinometer(_BusDevice):
    """Raw angle of the configured axis in degrees (zeroing and raised/lowered are gateway's)."""

    def __init__(self, bus: ModbusBus, section: Any, *, name: str = "inclinometer") -> None:
        self.bus = bus
        self.name = name
        self.device_id: int = section.device_id
        self.axis: str = section.axis
        self.layout: str = section.layout
        self.address, self.count = inclinometer_span(section.layout, section.axis)

    async def read(self) -> float:
        return await self._read_decoded(self.address, self.count, self._decode)

    def _decode(self, registers: list[int]) -> float:
        return decode_angle(registers, self.layout)  # type: ignore[arg-type]


class HopperScale(_BusDevice):
    """Gross mass on the hopper's load cells in kg, from a Modbus weight transmitter."""

    def __init__(self, bus: ModbusBus, section: Any, *, name: str = "hopper_scale") -> None:
        self.bus = bus
        self.name = name
        self.device_id: int = section.device_id
        self.address: int = section.address
        try:
            self.format = WeightFormat(
                data_type=section.data_type,
                word_order=section.word_order,
                grams_per_count=section.scale,
                capacity_kg=section.capacity_kg,
            )
        except ProtocolError as exc:
            raise FieldError(f"{self.name}: {exc}") from exc

        self.bad_readings = 0  # replies that arrived intact but held no plausible weight

    async def read(self) -> float:
        try:
            return await self._read_decoded(self.address, self.format.count, self.format.decode_kg)
        except BadReading:
            self.bad_readings += 1
            raise


class PwmModule(_BusDevice):
    """The PWM output module driving the metering motor and the fan."""

    def __init__(self, bus: ModbusBus, section: Any, *, name: str = "pwm") -> None:
        self.bus = bus
        self.name = name
        self.device_id: int = section.device_id
        self.registers: dict[str, int] = {
            "motor": section.motor_register,
            "fan": section.fan_register,
        }
        self.comm_timeout_register: int = section.comm_timeout_register

    def _register(self, channel: str) -> int:
        try:
            return self.registers[channel]
        except KeyError:
            raise ValueError(
                f"{self.name}: unknown channel {channel!r}, expected 'motor' or 'fan'"
            ) from None

    async def write_duty(self, channel: Channel, pct: float) -> None:
        """Set ``channel`` to ``pct`` percent (0..100, 0.1 % resolution)."""
        register = self._register(channel)
        try:
            value = encode_duty(pct)
        except FieldError as exc:
            raise FieldError(f"{self.name} {channel}: {exc}") from exc
        await self.bus.write_register(self.name, self.device_id, register, value)

    async def read_duty(self, channel: Channel) -> float:
        """The duty the module currently applies on ``channel`` (read back)."""
        register = self._register(channel)
        (value,) = await self.bus.read_holding(self.name, self.device_id, register, 1)
        try:
            return decode_duty(value)
        except ProtocolError as exc:
            raise BadReading(f"{self.name} (id {self.device_id}) {channel}: {exc}") from exc

    async def set_comm_timeout(self, seconds: float) -> float:
        """Program the module's communication-loss watchdog and read it back.

        Returns the timeout the module holds. Raises :class:`WatchdogNotSet` if it reads back
        otherwise, DeviceRejected if the module refuses the register (no such watchdog) and
        DeviceUnavailable if it does not answer.
        """
        register = self.comm_timeout_register
        try:
            value = encode_comm_timeout(seconds)
        except FieldError as exc:
            raise FieldError(f"{self.name}: {exc}") from exc
        await self.bus.write_register(self.name, self.device_id, register, value)
        (back,) = await self.bus.read_holding(self.name, self.device_id, register, 1)
        if back != value:
            raise WatchdogNotSet(
                f"{self.name} (id {self.device_id}) register {register:#06x} reads {back} "
                f"after writing {value} (comm-loss timeout {seconds:g} s)"
            )
        return decode_comm_timeout(back)
