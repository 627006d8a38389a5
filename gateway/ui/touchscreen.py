"""The touchscreen as the operator sees it: HMI frames become commands, state becomes text.

Translation lives here, not in the driver: the driver knows frames and instructions, this
module knows that crop code 2 is wheat in this machine's config and that a refused rate must
be explained on the screen in words the operator can act on.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Mapping

from drivers.hmi_link import LOG_EVERY_S, HmiLink
from drivers.log_limit import RateLimitedLog
from gateway.config import CropModel, HmiSection
from gateway.core import commands as cmd
from gateway.state import HopperState, MachineState
from protocol import hmi

log = logging.getLogger(__name__)

# The screen has one alarm line: the most severe active alarm takes it (the oldest of those),
# so "record store cannot write" is not hidden behind an older warning about the GNSS fix.
_SEVERITY_ORDER = {"critical": 0, "warning": 1, "info": 2}

DEFAULT_STATE_LABELS = {
    "stopped": "STOPPED",
    "pre_seed": "PRE-SEED",
    "seeding": "SEEDING",
    "turning": "TURNING",
    "paused": "PAUSED",
    "emptying": "EMPTYING",
}


def hopper_text(h: HopperState) -> str:
    """``412 kg 2.3 h x1.080`` (mass, time to empty, correction; ``~`` before the factor
    while the evidence is not enough to apply it)."""
    mass = "-- kg" if h.mass_kg is None else f"{h.mass_kg:.0f} kg"
    tte = h.time_to_empty_min
    empty = "" if tte is None else (f" {tte:.0f} min" if tte < 120 else f" {tte / 60:.1f} h")
    mark = "x" if h.correction_applied else "~x"
    est = h.discharge_correction if h.correction_applied else (h.correction_estimate or 1.0)
    return f"{mass}{empty} {mark}{est:.3f}"


class HmiAdapter:
    """The screen, given what it needs from the daemon and nothing more: the crop table (codes),
    the one command path (``execute`` -> ok, reply text) and the machine's state."""

    def __init__(
        self,
        section: HmiSection,
        *,
        crops: Mapping[str, CropModel],
        execute: Callable[[cmd.Command, str], tuple[bool, str]],
        state: Callable[[], MachineState],
        seed_lots: Callable[[str], list[str]] | None = None,
    ) -> None:
        self.section = section
        self.crops = crops
        self.execute = execute
        self.state = state
        # crop -> its seed lots, numbered as F=08 numbers them (0 is "default")
        self.seed_lots = seed_lots or (lambda _crop: ["default"])
        self.link = HmiLink(
            section.port,
            section.baudrate,
            section.encoding,
            on_event=self.on_event,
            write_timeout_s=section.write_timeout_s,
            reconnect_max_s=section.reconnect_max_s,
        )
        self.last_message: str = ""
        self._dirty = asyncio.Event()
        self._log = RateLimitedLog(log, LOG_EVERY_S)

    def crop_for_code(self, code: int) -> str | None:
        for name, model in self.crops.items():
            if model.code == code:
                return name
        return None

    def to_command(self, event: hmi.HmiEvent) -> cmd.Command | str:
        """The command for an HMI event, or the reason it is refused."""
        match event:
            case hmi.StartWork():
                return cmd.Start()
            case hmi.StopWork():
                return cmd.Stop()
            case hmi.SelectCrop(crop_code=code, rate_kg_ha=rate):
                crop = self.crop_for_code(code)
                if crop is None:
                    return f"unknown crop code {code}"
                return cmd.SetRate(crop, rate)
            case hmi.EmptySeed():
                return cmd.EmptySeed()
            case hmi.SeedLevelMonitoring(enabled=on):
                return cmd.SeedLevelMonitoring(on)
            case hmi.ZeroTilt():
                return cmd.ZeroTilt()
            case hmi.AckAlarm():
                return cmd.AckAlarm()
            case hmi.SelectSeedLot(crop_code=code, lot_number=number):
                crop = self.crop_for_code(code)
                if crop is None:
                    return f"unknown crop code {code}"
                lots = self.seed_lots(crop)
                if number >= len(lots):
                    listed = ", ".join(f"{i} {name}" for i, name in enumerate(lots))
                    return f"{crop} has no seed lot {number} (lots: {listed})"
                return cmd.SelectSeedLot(crop, lots[number])
            case hmi.RotationTest(action=action, value=value):
                return cmd.RotationTest(action, value)
            case hmi.Rejected(reason=reason):
                return f"bad frame: {reason}"
        return f"unsupported input {event!r}"

    def on_event(self, event: hmi.HmiEvent) -> None:
        command = self.to_command(event)
        if isinstance(command, str):
            # a bad frame is the link's to log (rate-limited, per kind) and count; a refused
            # good frame (unknown crop code) is logged here, rate-limited too
            if not isinstance(event, hmi.Rejected):
                key = f"refused:{type(event).__name__}"
                self._log.warning(key, "HMI input refused: %s", command)
            self.last_message = command
        else:
            ok, text = self.execute(command, "hmi")
            self.last_message = text if ok else f"refused: {text}"
        self._dirty.set()

    def show(self, text: str) -> None:
        """Put ``text`` on the message line now (e.g. "run 2 done: enter ...")."""
        self.last_message = text
        self._dirty.set()

    def screen_texts(self) -> dict[str, str]:
        o = self.section.objects
        state = self.state()
        labels = {**DEFAULT_STATE_LABELS, **self.section.state_labels}
        crop = state.crop
        speed = state.speed_kmh
        tilt = state.tilt_deg
        # the alarms come oldest first: min keeps the oldest of the most severe
        top = min(state.alarms, key=lambda a: _SEVERITY_ORDER.get(a.severity, 3), default=None)
        alarm_line = top.message if top is not None else ""
        active = {a.code for a in state.alarms}
        # a critical alarm that cleared before anyone acknowledged it keeps the line (unless
        # another critical one is active): the operator must see that it happened
        waiting = [(c, m) for c, m in state.unacknowledged if c not in active]
        if waiting and (top is None or top.severity != "critical"):
            _, message = waiting[0]
            alarm_line = f"cleared, acknowledge: {message}"
        texts = {
            o.speed: "--" if speed is None else f"{speed:.1f} km/h",
            o.tilt: "--" if tilt is None else f"{tilt:+.1f} deg",
            o.state: labels.get(state.work_state, state.work_state),
            o.crop: self.section.crop_labels.get(crop, crop),
            o.rate: f"{state.target_rate_kg_ha:g} kg/ha",
            o.alarm: alarm_line,
            o.message: self.last_message,
        }
        if state.hopper is not None:  # only a screen for a machine with a hopper scale
            texts[o.hopper] = hopper_text(state.hopper)
        if o.lot is not None:  # "1 2026-B": the number F=08 selects it by, and its name
            lots = self.seed_lots(crop)
            number = lots.index(state.seed_lot) if state.seed_lot in lots else 0
            texts[o.lot] = f"{number} {state.seed_lot}"
        return texts

    async def refresh_loop(self) -> None:
        period = 1.0 / self.section.update_hz
        while True:
            await self.link.show_many(self.screen_texts())
            self._dirty.clear()
            try:
                async with asyncio.timeout(period):
                    await self._dirty.wait()
            except TimeoutError:
                pass
