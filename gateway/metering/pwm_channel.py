"""Paper A's PWM-driven motor seen as a metering channel: its rate from the prescription map
under its outlets, and its as-applied log, so one drill can mix it with CAN channels."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from gateway.config import ChannelSection
from gateway.metering.channels import AS_APPLIED_PERIOD_S
from gateway.metering.prescription import AsAppliedLog, Pose, PrescriptionMap

# the alarms that are about paper A's motor (the PWM module and the rate its duty can give)
PWM_CHANNEL_ALARMS = ("pwm.unavailable", "rate.too_fast", "rate.outside_calibration",
                      "rate.low_duty")


@dataclass(frozen=True, slots=True)
class PwmChannelState:
    """Paper A's motor shaped like a CAN channel's status, so the live view shows every
    channel in one table; the motor has no shaft feedback, so the duty written is what there
    is to show. The rates and duty are None until the first control tick."""

    name: str
    product: str
    prescription: bool  # its rate comes from the prescription map
    target_rate_kg_ha: float | None
    commanded_rate_kg_ha: float | None
    duty_pct: float | None
    alarms: tuple[str, ...]  # the active ones of PWM_CHANNEL_ALARMS


class PwmChannelPart:
    """Paper A's motor as a channel: its rate from the map under its outlets, as-applied log.

    The controller asks ``prescribed_rate`` every tick; outside the map (or without a GNSS
    position) it gets None and sows the operator's rate, which starts as the channel's
    ``target_rate_kg_ha``.
    """

    def __init__(
        self,
        channel: ChannelSection,
        prescription: PrescriptionMap | None,
        as_applied: AsAppliedLog,
        *,
        pose: Callable[[], Pose | None],
        operator_rate: Callable[[], float],
        lookahead_s: float,
        active_alarms: Callable[[], set[str]],
        clock: Callable[[], float],
    ) -> None:
        self.pose = pose
        self.operator_rate = operator_rate
        self.lookahead_s = lookahead_s
        self.active_alarms = active_alarms
        self.clock = clock
        self.channel = channel
        self.prescription = prescription if channel.prescription_attribute else None
        self.as_applied = as_applied
        self._last_logged = float("-inf")
        self.last_target: float | None = None
        self.last_commanded: float | None = None
        self.last_duty_pct: float | None = None

    def prescribed_rate(self) -> float | None:
        ch = self.channel
        if self.prescription is None or ch.prescription_attribute is None:
            return None
        pose = self.pose()
        if pose is None:  # the map's position-lost rate if it has one (ISO-XML TSK I)
            return self.prescription.position_lost.get(ch.prescription_attribute)
        rate: float = self.prescription.rate_ahead(
            pose, ch.prescription_attribute, self.operator_rate(), self.lookahead_s,
            ch.outlet_behind_m, ch.outlet_lateral_m,
        )
        return rate

    def on_tick(
        self, seeding: bool, target_kg_ha: float | None, commanded_kg_ha: float, duty_pct: float
    ) -> None:
        """After each control tick: what the controller aimed at and wrote; while seeding, an
        as-applied row every ``AS_APPLIED_PERIOD_S`` where the position is known."""
        self.last_target, self.last_commanded = target_kg_ha, commanded_kg_ha
        self.last_duty_pct = duty_pct
        now = self.clock()
        if not seeding or now - self._last_logged < AS_APPLIED_PERIOD_S:
            return
        pose = self.pose()
        if pose is None:
            return
        self._last_logged = now
        self.as_applied.record_channel(pose, self.channel, target_kg_ha or 0.0, commanded_kg_ha)

    def state(self) -> PwmChannelState:
        """What the controller last aimed at and wrote, and the motor's active alarms."""
        active = self.active_alarms()
        return PwmChannelState(
            name=self.channel.name,
            product=self.channel.product,
            prescription=self.prescription is not None,
            target_rate_kg_ha=self.last_target,
            commanded_rate_kg_ha=self.last_commanded,
            duty_pct=self.last_duty_pct,
            alarms=tuple(code for code in PWM_CHANNEL_ALARMS if code in active),
        )
