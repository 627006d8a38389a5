"""Paper A's rotation test started from the touchscreen (HMI F=09), run by the daemon itself.

The daemon owns the RS485 bus, so the CLI cannot drive the meter while it runs; from the cab
screen the operator runs the same test through the daemon's own control loop: with the
machine stopped (mode ``stopped``), "run" turns the metering motor at the given duty, with the
fan at the crop's seeding duty, for ``control.rotation_test_s``, then off; the operator reads
the shaft speed and weighs the catch of all ``machine.rows`` outlets and types both; after a
few runs "save" fits them with the CLI's own function and gates
(``gateway.calibration.fits.fit_rotation_test``: from 5 set points on the drill's own monotone
curves, each run weighted by its length, below that eq. 5 and eq. 6), for the crop on the
screen and its active seed lot, so a drill with a knee gets the same curve here as at the CLI.
Readings that contradict each other are refused with the duties to repeat first on the one
message line. A result more than ``LARGE_CHANGE_PCT`` from the value it replaces (the CLI's
rows, ``paper_a_changes``) is shown and saved only on "save_confirmed". The saved calibration is
applied at once (``LiveCalibration.reload``) and can be undone with ``sowgate calibrate undo``.

Run lengths: the screen's frame carries a duty, not a length, so the daemon decides how long a
run lasts and says it in the run's message. Without a known scale every run lasts
``control.rotation_test_s``. With ``[calibration] scale_g`` each set point runs for what the
CLI's weighing advice would ask of it (``weighing.run_seconds_needed``: its mean within 1 % at
p90 over paper A's 3 runs, never shorter than ``rotation_test_s``): its first run from the
catch the crop's current model predicts at that duty, its later runs from what its earlier
runs caught. The small catches (rapeseed's low duties) run long, the large ones stay short, so
the screen's test reaches the CLI's accuracy without the CLI's first 60 s pass; when a run
alone is longer than ``PRACTICAL_RUN_S`` its message names the finer scale that would do.

Safety: a run is only motor and fan duties laid over the controller's outputs for the run's
length (``apply``): the PWM module is written by the control loop as ever (keep-alive,
watchdog, safe-off at stop); "cancel", the stop button, a start of work or any mode other
than ``stopped`` end the run at once with the motor at 0.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

from gateway.app.live_calibration import LiveCalibration
from gateway.calibration import fits as cal
from gateway.calibration import lots, weighing
from gateway.config import Settings
from gateway.control.controller import Controller, ControlOutputs
from gateway.control.work_state import Mode
from gateway.core.errors import CommandError

log = logging.getLogger(__name__)

MIN_RUNS = 3  # eq. 6 is a quadratic
# one run longer than this (the runs of one set point at it take over an hour, the test over
# the two hours of weighing.PRACTICAL_TEST_S) gets the finer scale named in its message
PRACTICAL_RUN_S = 20 * 60.0


@dataclass
class _Run:
    duty_pct: float
    seconds: float
    rpm: float | None = None
    mass_g: float | None = None


@dataclass
class RotationTestSession:
    """The touchscreen's rotation test: its runs so far and the run in progress."""

    settings: Settings
    controller: Controller
    live: LiveCalibration
    runs: list[_Run] = field(default_factory=list)
    crop: str | None = None
    running_until: float | None = None
    last_note: str | None = None  # what the screen should say when a run ends

    @property
    def running(self) -> bool:
        return self.running_until is not None

    def command(self, action: str, value: float, now: float) -> str:
        if action == "cancel":
            self.running_until, self.runs, self.crop = None, [], None
            return "rotation test cancelled: motor off, runs discarded"
        if action == "run":
            return self._start_run(value, now)
        if action in ("rpm", "mass"):
            return self._enter(action, value)
        if action in ("save", "save_confirmed"):
            return self._save(confirmed=action == "save_confirmed")
        raise CommandError(f"unknown rotation test action {action!r}")

    def _start_run(self, duty: float, now: float) -> str:
        if self.controller.mode is not Mode.STOPPED:
            raise CommandError("stop work first: the rotation test runs with the machine stopped")
        if self.running:
            raise CommandError("a run is in progress; cancel it first")
        if not 0.0 < duty <= 100.0:
            raise CommandError(f"duty must be in 0..100 % (got {duty:g})")
        crop = self.controller.crop
        if self.crop not in (None, crop):
            raise CommandError(f"this test is of {self.crop}: save or cancel it first")
        if self.runs and (self.runs[-1].rpm is None or self.runs[-1].mass_g is None):
            raise CommandError(f"enter run {len(self.runs)}'s shaft r/min and mass first")
        seconds, why = self._run_seconds(crop, duty)
        self.crop = crop
        self.runs.append(_Run(duty, seconds))
        self.running_until = now + seconds
        return (f"rotation run {len(self.runs)} ({crop}): duty {duty:g} % for {seconds:g} s"
                f"{why}, then enter the shaft r/min and the mass of all outlets in g")

    def _run_seconds(self, crop: str, duty: float) -> tuple[float, str]:
        """How long a run at ``duty`` lasts, and what the message adds about it (see the
        module docstring): ``rotation_test_s`` unless the scale is known."""
        floor = self.settings.control.rotation_test_s
        scale = self.settings.calibration.scale_g
        if scale is None:
            return floor, ""
        same = [r for r in self.runs if abs(r.duty_pct - duty) < 1e-6 and r.mass_g]
        if same:  # this set point's own catches beat any model
            rate = sum(r.mass_g or 0.0 for r in same) / sum(r.seconds for r in same)
        else:
            m = self.settings.control.crops[crop]
            w = m.motor_slope * duty + m.motor_intercept  # eq. 5, as calibrated so far
            rate = (m.meter_a * w * w + m.meter_b * w + m.meter_c) / 60.0  # eq. 6, g/s
        if rate <= 0:  # below the motor's dead band as modelled: the catch will say
            return floor, ""
        runs = max(weighing.PAPER_A_REPEATS, len(same) + 1)
        # runs of this set point so far count: a short first run (the model over-predicted
        # its catch) is made up by the ones after it
        seconds = max(floor, weighing.remaining_run_seconds(
            rate, scale, runs, [r.seconds for r in same]))
        why = f" (+-{scale:g} g scale, {runs} runs here)" if seconds > floor else ""
        if seconds > PRACTICAL_RUN_S:
            finer = weighing.scale_for_seconds(rate, floor, runs)
            why = (f" (+-{scale:g} g scale, {runs} runs here take {seconds * runs / 60:.0f} min; "
                   f"a +-{finer:g} g scale does it in {floor:g} s)")
        return seconds, why

    def _enter(self, what: str, value: float) -> str:
        if not self.runs:
            raise CommandError("no run yet: start one first")
        if self.running:
            raise CommandError("wait until the run has ended")
        run = self.runs[-1]
        if what == "rpm":
            if value <= 0:
                raise CommandError("shaft speed must be above 0 r/min")
            run.rpm = value
            return f"run {len(self.runs)}: shaft {value:g} r/min"
        run.mass_g = value
        return (f"run {len(self.runs)}: {value:g} g from all {self.settings.machine.rows} "
                "outlets")

    def _save(self, *, confirmed: bool) -> str:
        if self.running:
            raise CommandError("wait until the run has ended")
        done = [r for r in self.runs if r.rpm is not None and r.mass_g is not None]
        if len(done) < MIN_RUNS:
            raise CommandError(f"need {MIN_RUNS} runs with shaft r/min and mass (have "
                               f"{len(done)})")
        crop = self.crop or self.controller.crop
        seconds = [r.seconds for r in done]
        duties = [r.duty_pct for r in done]
        rpm = [r.rpm for r in done if r.rpm is not None]
        masses = [r.mass_g for r in done if r.mass_g is not None]
        try:  # the CLI's own fit and gates; every outlet weighed: the whole machine
            fit = cal.fit_rotation_test(duties, rpm, masses, seconds)
        except cal.InconsistentSetPoints as exc:  # the screen's one line names them first
            raise CommandError(
                "not saved: repeat duty " + ", ".join(f"{k:g}" for k in exc.set_points)
                + f" % (readings inconsistent: {exc.what} falls beyond the weighing noise)"
            ) from None
        except cal.CalibrationError as exc:
            raise CommandError(f"not saved: {exc}") from None
        line, quad, problems = fit.line, fit.quad, fit.problems
        if problems:
            raise CommandError("not saved, repeat the runs: " + "; ".join(problems))
        lot = self.live.lot_of(crop)
        change, replaces = self._change(crop, fit, duties)
        large = abs(change) > cal.LARGE_CHANGE_PCT
        if large and not confirmed:
            raise CommandError(
                f"{change:+.0f} % from the value it replaces (more than "
                f"{cal.LARGE_CHANGE_PCT:g} %): check the masses; confirm to save anyway"
            )
        scale = self.settings.calibration.scale_g
        advice = weighing.weighing_advice(  # unknown scale: paper A's ±2 g
            duties, masses, seconds, weighing.DEFAULT_SCALE_G if scale is None else scale)
        key = lots.rotation_key(crop, lot)
        entry = cal.to_entry(
            fit.result(),
            channel=crop, crop=crop, seed_lot=lot, model="paper_a", source="hmi",
            outlets_weighed=self.settings.machine.rows, outlets=self.settings.machine.rows,
            weighed_mass_g=masses, replaces=replaces, accepted_poor_fit=[],
            accepted_large_change=large, weighing=advice.to_entry())
        try:
            cal.CalibrationStore(self.live.state_dir).save(key, entry)
        except (cal.CalibrationError, OSError) as exc:
            raise CommandError(f"not saved: {exc}") from None
        if large:
            log.warning("%s: %+.0f %% change confirmed on the touchscreen", key, change)
        notes = self.live.reload()
        self.runs, self.crop = [], None
        mine = [n for n in notes if crop in n]
        if advice.short:  # the CLI says it at length (gateway.calibration.weighing)
            log.warning("%s: %s", key, " ".join(advice.messages(crop, "{:.4g} % duty")))
            note = advice.practical_note(crop)
            if note is not None:
                log.warning("%s: %s", key, note)
            mine.append(self._short_note(advice, scale))
        return (f"saved {key}: R = {line.slope:.4f}K {line.intercept:+.2f}, R2 {line.r2:.3f}/"
                f"{quad.r2:.3f}; {'; '.join(mine) or 'applied'}")

    @staticmethod
    def _short_note(advice: weighing.WeighingAdvice, scale: float | None) -> str:
        """What the screen (ASCII, one line) says when runs were too short for the scale."""
        if advice.impractical:
            return (f"runs too short for a +-{advice.scale_g:g} g scale, the test would take "
                    f"{weighing.duration(advice.test_seconds())}: weigh on a "
                    f"+-{advice.practical_scale_g:g} g scale")
        if scale is None:  # every run lasts rotation_test_s: the one length that would do
            return (f"runs too short for a +-{advice.scale_g:g} g scale: "
                    f"rotation_test_s {advice.advised_seconds:g} (or set calibration.scale_g)")
        # lengths were per set point already: the model's catch was off; the next test
        # runs each set point from the catches just saved, so name the ones to repeat
        return (f"runs too short for a +-{advice.scale_g:g} g scale at "
                + ", ".join(f"{p.set_point:g} %" for p in advice.short)
                + " duty: repeat those set points")

    def _change(self, crop: str, fit: cal.PaperAFit,
                duties: list[float]) -> tuple[float, dict[str, Any]]:
        """The largest change in % against what it replaces (the CLI's rows,
        ``paper_a_changes``), and that value as the entry's ``replaces``."""
        entry = self.live.active_rotation(crop)
        if entry is not None and entry.get("model") == "paper_a":
            motor, meter, source = entry["result"]["motor"], entry["result"]["meter"], (
                f"calibration (lot {entry['seed_lot']})")
        else:
            m = self.settings.control.crops[crop]
            motor = {"slope": m.motor_slope, "intercept": m.motor_intercept}
            meter = {"a": m.meter_a, "b": m.meter_b, "c": m.meter_c}
            source = "config"
        change = max((cal.change_pct(new, old)
                      for _, old, new in cal.paper_a_changes(motor, meter, fit, duties)),
                     key=abs)
        return change, {"motor": dict(motor), "meter": dict(meter), "from": source}

    def stop(self) -> None:
        """The stop button: a run in progress ends at once (its runs so far are kept)."""
        if self.running_until is not None:
            self.running_until = None
            self.last_note = "rotation run stopped"

    def take_note(self) -> str | None:
        note, self.last_note = self.last_note, None
        return note

    def apply(self, out: ControlOutputs, now: float) -> ControlOutputs:
        """The control loop's outputs with the run's duties laid over them while it runs."""
        if self.running_until is None:
            return out
        if self.controller.mode is not Mode.STOPPED:
            self.running_until = None
            self.last_note = "rotation run ended: work mode changed"
            return out
        if now >= self.running_until:
            self.running_until = None
            self.last_note = (f"run {len(self.runs)} done: enter its shaft r/min and the "
                              "mass of all outlets")
            return out
        crop = self.settings.control.crops[self.crop or self.controller.crop]
        return dataclasses.replace(out, motor_pct=self.runs[-1].duty_pct,
                                   fan_pct=crop.fan_high_pct)
