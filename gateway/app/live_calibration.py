"""A calibration saved while the daemon runs takes effect without a restart.

Why a file watch and not (only) an MQTT command: ``sowgate calibrate`` runs on the cab box,
often without a broker in reach, and the file is the one thing the CLI and the daemon share.
The daemon looks at ``calibration.json``'s signature (inode, size, mtime; a save renames a
new file over the old one) every ``WATCH_S`` from the control loop's tick, so the watch costs
no wake-up of its own, only a ``stat``. When it changed, the whole file is laid again over
the config as it was read at start (``base``), with the same start-up vet
(``gateway.app.calibration_check``), and the values the running parts read are replaced:

- paper A's crop models (``control.crops``: the controller reads them at every tick);
- each channel's ``grams_per_rev`` (the metering component holds the same channel objects);
- the speed corrections and the inclinometer's zero and critical angle (the controller is
  told: ``Controller.recalibrated``);
- the seed position calibration (``sowgate calibrate positions``): the ``[positioning]``
  section is replaced and each of ``positioning_listeners`` (the seed recorder's
  ``recalibrate``) is handed it, so new seeds are positioned with it.

A file that cannot be read (half-copied by hand, not JSON, not a calibration file) changes
nothing: the values in use are kept and ``calibration.file_invalid`` is raised until a good
file replaces it. Each (re)load is recorded in ``daemon.json`` (``gateway.calibration.presence``)
so the CLI can tell the fitter the running daemon has applied the save.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from gateway.calibration import lots
from gateway.calibration.apply import Vet, apply_entries, refused_message
from gateway.calibration.fits import CalibrationError, CalibrationStore
from gateway.calibration.presence import (
    WATCH_S,
    calibration_signature,
    remove_presence,
    write_presence,
)
from gateway.config import Settings
from gateway.config.recording import PositioningSection
from gateway.control.controller import Controller
from gateway.core.alarms import AlarmBoard
from gateway.core.errors import CommandError

log = logging.getLogger(__name__)

FILE_INVALID_ALARM = "calibration.file_invalid"
REFUSED_ALARM = "calibration.refused"  # as gateway.calibration.apply raises it at start


def _take(live: Settings, candidate: Settings) -> None:
    """Put the calibrated values of ``candidate`` into the settings the running parts read."""
    live.control.crops = candidate.control.crops
    for mine, theirs in zip(live.channel, candidate.channel, strict=True):
        mine.grams_per_rev = theirs.grams_per_rev
        mine.grams_per_rev_curve = theirs.grams_per_rev_curve
    live.speed.correction = dict(candidate.speed.correction)
    live.inclinometer.zero_offset_deg = candidate.inclinometer.zero_offset_deg
    live.inclinometer.critical_angle_deg = candidate.inclinometer.critical_angle_deg


class LiveCalibration:
    """Watches ``calibration.json`` and applies a new version to the running daemon."""

    def __init__(
        self,
        base: Settings,
        live: Settings,
        state_dir: Path,
        alarms: AlarmBoard,
        controller: Controller,
        *,
        vet: Vet | None,
        clock: Callable[[], float],
        start_notes: list[str],
        watch_s: float = WATCH_S,
    ) -> None:
        self.base = base
        self.live = live
        self.state_dir = state_dir
        self.alarms = alarms
        self.controller = controller
        self.vet = vet
        self.clock = clock
        self.watch_s = watch_s
        self.notes = list(start_notes)
        self.reloads = 0
        self._signature = calibration_signature(state_dir)  # applied at start
        self._ok = not any(n.startswith("calibration file ignored") for n in start_notes)
        if not self._ok:
            self.alarms.raise_(FILE_INVALID_ALARM, self._invalid_message(start_notes[0]),
                               "warning")
        self._next_look = clock() + watch_s
        # told of a changed [positioning] (gateway.app.wiring adds the seed recorder's)
        self.positioning_listeners: list[Callable[[PositioningSection], None]] = []
        self.lots: dict[str, str] = {}  # crop -> active seed lot (absent: default)
        self.current: dict[str, Any] = {}  # the file's entries, every lot
        with contextlib.suppress(CalibrationError):
            doc = CalibrationStore(state_dir).load()
            self.lots, self.current = lots.active_lots(doc), doc["current"]

    @staticmethod
    def _invalid_message(why: str) -> str:
        return f"calibration.json not applied, the values in use are kept: {why}"

    def announce(self) -> None:
        """Say in ``daemon.json`` that this daemon runs and what it has applied."""
        doc: dict[str, Any] = {
            "calibration": {
                "signature": self._signature,
                "ok": self._ok,
                "applied_at": datetime.now(UTC).isoformat(timespec="seconds"),
                "notes": self.notes,
            },
        }
        try:
            write_presence(self.state_dir, doc)
        except OSError as exc:
            log.warning("cannot write %s/daemon.json: %s", self.state_dir, exc)

    def retire(self) -> None:
        remove_presence(self.state_dir)

    def poll(self) -> None:
        """From the control tick: look at the file every ``watch_s``, reload when it changed."""
        now = self.clock()
        if now < self._next_look:
            return
        self._next_look = now + self.watch_s
        signature = calibration_signature(self.state_dir)
        if signature != self._signature:
            self.reload(signature)

    def reload(self, signature: list[int] | None = None) -> list[str]:
        """Apply the file as it is now; the notes (what was applied, refused, not applied)."""
        self._signature = calibration_signature(self.state_dir) if signature is None else (
            signature)
        self.reloads += 1
        try:
            doc = CalibrationStore(self.state_dir).load()
        except CalibrationError as exc:
            log.error("calibration.json changed but cannot be used (values kept): %s", exc)
            self._ok = False
            self.alarms.raise_(FILE_INVALID_ALARM, self._invalid_message(str(exc)), "warning")
            self.notes = [f"calibration file ignored: {exc}"]
            self.announce()
            return self.notes
        candidate = self.base.model_copy(deep=True)
        self.lots = lots.active_lots(doc)
        self.current = doc["current"]
        current = lots.effective_entries(candidate, self.current, self.lots)
        notes, refused = apply_entries(candidate, current, vet=self.vet)
        _take(self.live, candidate)
        self._take_positioning(candidate.positioning)
        self.controller.recalibrated()
        if self.controller.hopper is not None:
            self.controller.hopper.set_lots(self.lots, self.controller.crop)
        self._ok = True
        self.alarms.clear(FILE_INVALID_ALARM)
        self.alarms.set(REFUSED_ALARM, bool(refused), refused_message(refused), "warning")
        self.notes = notes
        log.info("calibration.json reloaded: %s", "; ".join(notes) or "no calibrations")
        self.announce()
        return notes

    def _take_positioning(self, positioning: PositioningSection) -> None:
        """Hand a changed [positioning] (a position calibration saved, or undone) to the
        parts that position seeds; one that cannot take it keeps what it had, logged."""
        if positioning == self.live.positioning:
            return
        self.live.positioning = positioning
        for listener in self.positioning_listeners:
            try:
                listener(positioning)
            except ValueError as exc:
                log.error("seed position calibration not applied (restart to apply): %s", exc)

    # ---- seed lots ---------------------------------------------------------------------------
    def lot_of(self, crop: str) -> str:
        return self.lots.get(crop, lots.DEFAULT_LOT)

    def lots_of(self, crop: str) -> list[str]:
        """``default``, then the lots with a rotation test of ``crop``, by name."""
        return lots.lots_of(self.base, self.current, crop)

    def active_rotation(self, name: str) -> dict[str, Any] | None:
        """The rotation-test entry in force for ``name`` (crop or channel): its ``crop``,
        ``seed_lot``, ``saved_at`` and result; None when the config's values are in force."""
        return lots.active_rotation(self.base, self.current, self.lots, name)

    def select_lot(self, crop: str, lot: str) -> str:
        """Make ``lot`` the active seed lot of ``crop``, applied at once; the reply text.

        Refused (``CommandError``, nothing changed) for a crop this machine does not sow or a
        lot without a rotation test of that crop (``default`` always exists: the config's or
        the default lot's fits)."""
        known_crops = lots.crops(self.base)
        if crop not in known_crops:
            raise CommandError(f"unknown crop {crop!r}; known: {', '.join(known_crops)}")
        try:
            lots.check_lot_name(lot)
        except CalibrationError as exc:
            raise CommandError(str(exc)) from None
        available = self.lots_of(crop)
        if lot not in available:
            raise CommandError(
                f"{crop} has no rotation test for seed lot {lot!r} (lots: "
                f"{', '.join(available)}); run sowgate calibrate rotation --seed-lot {lot}"
            )
        try:
            lots.select_lot(CalibrationStore(self.state_dir), crop, lot)
        except (CalibrationError, OSError) as exc:
            raise CommandError(f"seed lot not changed: {exc}") from None
        notes = self.reload()
        self._next_look = self.clock() + self.watch_s  # this write is applied already
        names = [crop, *(c.name for c in self.base.channel if c.product == crop)]
        said = [n for n in notes if any(name in n for name in names)]
        if lot == lots.DEFAULT_LOT and not said:
            said = ["the config's values"]
        return f"{crop}: seed lot {lot} ({'; '.join(said) or 'applied'})"
