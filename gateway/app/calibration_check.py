"""The start-up check of a saved calibration against the machine's working speeds.

A rotation test with the wrong units (the catch of all 24 outlets saved as one outlet's
g/rev) or a typing error gives a calibration that the fit alone cannot catch: the drill then
commands 0 r/min (the shaft speed needed falls below ``can.min_target_rpm``) or runs flat out,
and sows nothing or far too little without a word. Before the daemon applies a calibration it
works out the command at the channel's configured rate over ``machine.working_speed_kmh`` with
the calibrated value; a calibration that makes it 0 or saturates it at a speed where the
config value works with a margin (``CONFIG_MARGIN``) is refused
(``gateway.calibration.apply`` keeps the config value and raises ``calibration.refused``).

It lives in the app layer because it needs both rate chains: paper B's shaft speed
(``gateway.metering.channels``) and paper A's duty (``gateway.control.rate_model``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from gateway.config import ChannelSection, CropModel, Settings
from gateway.control.rate_model import (
    MAX_DUTY_PCT,
    duty_for_omega,
    flow_for_rate,
    omega_for_flow,
)
from gateway.core.errors import OutsideCalibrationError
from gateway.metering.channels import channel_target_rpm

SPEED_SAMPLES = 9  # speeds checked across the working range (its ends included)
# The config value must work with this margin at a speed for a calibration failing there to be
# blamed: a shaft speed 25 % clear of can.min_target_rpm and max_shaft_rpm (paper A: a duty at
# least the crop's start-up duty and 25 % below 100 %). Without it, a 2 % refit of a channel
# whose config value saturates just above a checked speed would be refused.
CONFIG_MARGIN = 0.25

Verdict = Literal["ok", "zero", "saturated"]


@dataclass(frozen=True)
class Command:
    """What the command is at one working speed, and whether it is well clear of the limits."""

    verdict: Verdict
    why: str
    comfortable: bool  # ok, with CONFIG_MARGIN to spare


def _speeds(settings: Settings) -> list[float]:
    lo, hi = settings.machine.working_speed_kmh
    return [lo + (hi - lo) * i / (SPEED_SAMPLES - 1) for i in range(SPEED_SAMPLES)]


def _channel_verdict(settings: Settings, ch: ChannelSection, speed: float) -> Command:
    width = settings.machine.working_width_m
    rpm = channel_target_rpm(ch, ch.target_rate_kg_ha, speed, width)
    low = settings.can.min_target_rpm
    if rpm < low:
        return Command("zero", (
            f"commands 0 r/min at {speed:g} km/h (needs {rpm:.2f} r/min, below "
            f"can.min_target_rpm {low:g})"
        ), False)
    if rpm > ch.max_shaft_rpm:
        return Command("saturated", (
            f"saturates at {speed:g} km/h (needs {rpm:.0f} r/min, above max_shaft_rpm "
            f"{ch.max_shaft_rpm:g})"
        ), False)
    clear = low * (1 + CONFIG_MARGIN) <= rpm <= ch.max_shaft_rpm / (1 + CONFIG_MARGIN)
    return Command("ok", "", clear)


def _crop_verdict(settings: Settings, crop: CropModel, rate: float, speed: float) -> Command:
    flow = flow_for_rate(rate, settings.machine.working_width_m, speed)
    try:
        duty = duty_for_omega(omega_for_flow(flow, crop), crop)
    except OutsideCalibrationError:
        return Command("saturated", (
            f"saturates at {speed:g} km/h ({flow:.0f} g/min is beyond the refitted meter)"
        ), False)
    if duty > MAX_DUTY_PCT:
        return Command("saturated", (
            f"saturates at {speed:g} km/h (needs duty {duty:.0f} %, above {MAX_DUTY_PCT:g} %)"
        ), False)
    if duty <= 0:
        return Command("zero", f"commands 0 at {speed:g} km/h (duty {duty:.1f} %)", False)
    clear = crop.startup_duty_pct <= duty <= MAX_DUTY_PCT / (1 + CONFIG_MARGIN)
    return Command("ok", "", clear)


def _verdicts(settings: Settings, key: str) -> list[Command] | None:
    """The command's verdict at each working speed for what ``key`` calibrates, or None when
    the key is not a metering calibration this check knows."""
    kind, _, name = key.partition(".")
    if kind != "rotation":
        return None
    ch = next((c for c in settings.channel if c.name == name), None)
    if ch is not None and ch.drive == "can_pid":
        return [_channel_verdict(settings, ch, v) for v in _speeds(settings)]
    if ch is not None:  # a pwm_modbus channel: paper A's crop model for its product
        crop_name, rate = ch.product, ch.target_rate_kg_ha
    elif name in settings.control.crops:
        crop_name = name
        model = settings.control.crops[name]
        rate = (settings.control.rate_kg_ha if name == settings.control.crop
                and settings.control.rate_kg_ha is not None else model.default_rate_kg_ha)
    else:
        return None
    crop = settings.control.crops.get(crop_name)
    if crop is None:
        return None
    return [_crop_verdict(settings, crop, rate, v) for v in _speeds(settings)]


def working_speed_problem(before: Settings, after: Settings, key: str) -> str | None:
    """Why the calibration ``key`` (applied in ``after``) must not be used, or None.

    Refused when, at some working speed, the command with the calibration is 0 or saturated
    and with the config value (``before``) it was well clear of both (``CONFIG_MARGIN``): the
    calibration made it so. A rate the configured value cannot reach either is the rate's or
    the speed range's problem, and the running daemon's own alarms
    (``channel.<name>.too_fast``, ``rate.too_fast``) report it.
    """
    new = _verdicts(after, key)
    old = _verdicts(before, key)
    if new is None or old is None:
        return None
    lo, hi = after.machine.working_speed_kmh
    for cmd, was in zip(new, old, strict=True):
        if cmd.verdict != "ok" and was.comfortable:
            return (
                f"at the configured rate it {cmd.why}; the config value does not "
                f"(machine.working_speed_kmh {lo:g}..{hi:g})"
            )
    return None
