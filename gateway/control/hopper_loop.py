"""The hopper scale in the control loop: samples in, ``discharge_correction`` out.

``Controller`` owns one when ``[hopper_scale]`` is on. Each control tick it is told the
discharge the (uncorrected) model predicts at the duty just commanded and whether the drill
is seeding; the daemon passes each weight reading (``on_weight``). It keeps the cumulative
model discharge, gates the samples (``SteadyGate``), feeds the estimator
(``hopper_correction``), logs each new factor with its confidence, raises the hopper alarms,
and keeps the factor in ``hopper_correction.json`` for the calibration identity it belongs to
(``hopper_store``): a new rotation test or another seed lot starts again at 1.0.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque
from dataclasses import dataclass

from gateway.calibration.fits import CalibrationStore
from gateway.calibration.lots import rotation_key
from gateway.config import HopperScaleSection
from gateway.control.hopper_correction import (
    CorrectionState,
    HopperCorrection,
    SteadyGate,
    time_to_empty_min,
)
from gateway.control.hopper_store import DEFAULT_SEED_LOT, HopperStore, Identity, rotation_saved_at
from gateway.core.alarms import AlarmBoard
from gateway.core.records import AlarmSeverity

log = logging.getLogger(__name__)

MASS_MEDIAN_N = 5  # readings in the shown hopper mass (vibration is at the kg level)
MASS_FRESH_S = 5.0  # a mass older than this is not shown
# calibration.json is looked at this often for a new rotation test (saved by the CLI or the
# touchscreen while the daemon runs): the old correction must not stay on a new fit
IDENTITY_CHECK_S = 10.0
# hopper_scale.out_of_range is critical when the drill sows this far (%) off target after the
# clamped correction, a warning below (the bound itself is `hopper_scale.max_correction_pct`)
OUT_OF_RANGE_CRITICAL_PCT = 5.0


@dataclass(frozen=True, slots=True)
class HopperState:
    """The hopper scale's part of the machine state (``MachineState.hopper``)."""

    mass_kg: float | None  # median of the last readings; None while the scale is silent
    time_to_empty_min: float | None  # at the current discharge; None when not discharging
    discharge_correction: float  # applied: true / model
    correction_estimate: float | None  # pooled estimate before shrinkage and clamp
    correction_standard_error: float | None  # its standard error (the confidence)
    correction_applied: bool  # the evidence was enough to apply it
    scale_sigma_kg: float | None  # the scale noise seen in the residuals
    windows: int
    refills: int


class HopperLoop:
    def __init__(self, section: HopperScaleSection, alarms: AlarmBoard, crop: str, *,
                 calibrations: CalibrationStore | None = None,
                 rotation_keys: list[str] | None = None) -> None:
        self.section = section
        self.alarms = alarms
        self.calibrations = calibrations
        self.store = None if calibrations is None else HopperStore(calibrations.path.parent)
        self._extra_keys = rotation_keys or []
        self.seed_lot = DEFAULT_SEED_LOT
        self.lots: dict[str, str] = {}  # crop -> active seed lot (gateway.calibration.lots)
        self._identity_checked_at: float | None = None
        self.gate = SteadyGate()
        self.model_kg = 0.0  # cumulative discharge the uncorrected model predicted
        self._q_model = 0.0  # g/min at the duty in effect since the last tick
        self._last_t: float | None = None
        self._pending: float | None = None  # weight read since the last tick
        self._readings: deque[tuple[float, float]] = deque(maxlen=MASS_MEDIAN_N)
        self._flow_g_min = 0.0
        self._jumps_seen = 0
        self.identity = self._identity(crop)
        self.estimator = self._fresh(self.identity)

    # ---- identity and persistence --------------------------------------------------------------
    def _identity(self, crop: str) -> Identity:
        lot = self.lots.get(crop, self.seed_lot)
        keys = [rotation_key(crop, lot), *self._extra_keys]
        return Identity(crop, lot, rotation_saved_at(self.calibrations, keys))

    def _fresh(self, identity: Identity) -> HopperCorrection:
        saved = self.store.load(identity) if self.store is not None else None
        est = HopperCorrection(
            window_s=self.section.window_s,
            max_correction_pct=self.section.max_correction_pct,
            evidence=saved.evidence if saved else None,
            factor=saved.factor if saved else 1.0,
        )
        if saved is not None:
            log.info("hopper correction for %s restored: x%.4f", identity.crop, est.factor)
        return est

    def set_crop(self, crop: str, rotation_keys: list[str] | None = None,
                 seed_lot: str | None = None) -> None:
        """Another crop, seed lot (named: seed lots are kept per crop) or calibration is
        sown: its own correction, or 1.0."""
        if rotation_keys is not None:
            self._extra_keys = rotation_keys
        if seed_lot is not None:
            self.seed_lot = seed_lot
        self._check_identity(crop)

    def set_lots(self, lots: dict[str, str], crop: str) -> None:
        """The active seed lot of each crop (calibration.json, reloaded live): a newly selected
        lot of the crop sown has its own correction (or 1.0), as a new rotation test does."""
        self.lots = dict(lots)
        self._check_identity(crop)

    def _check_identity(self, crop: str) -> None:
        identity = self._identity(crop)
        if identity == self.identity:
            return
        if identity.crop == self.identity.crop:
            log.warning("hopper correction reset to 1.0: the calibration changed (%s -> %s)",
                        self.identity.to_dict(), identity.to_dict())
        self.identity = identity
        self.estimator = self._fresh(identity)
        self._jumps_seen = 0
        self.gate = SteadyGate()

    @property
    def factor(self) -> float:
        return self.estimator.factor

    # ---- samples ---------------------------------------------------------------------------------
    def on_weight(self, kg: float | None, t: float) -> None:
        """A reading from the scale (None: it did not answer this poll)."""
        self._pending = kg
        if kg is not None:
            self._readings.append((t, kg))

    def tick(self, now: float, *, q_model_g_min: float, seeding: bool, speed_kmh: float | None,
             modelled: bool) -> None:
        """Once per control tick, after the duty is decided: ``q_model_g_min`` is what the
        uncorrected model predicts at it (0 with the motor off); ``modelled`` False when the
        motor runs outside the rate model (emptying)."""
        dt = 0.0 if self._last_t is None else max(0.0, now - self._last_t)
        self._last_t = now
        self.model_kg += self._q_model * dt / 60.0 / 1000.0
        steady = self.gate.update(now, seeding, speed_kmh)
        weight, self._pending = self._pending, None
        pooled = self.estimator.add(now, weight, self.model_kg, steady=steady,
                                    modelled=modelled)
        if self.estimator.jumps > self._jumps_seen:
            self._jumps_seen = self.estimator.jumps
            if not self.alarms.is_active("hopper_scale.jump"):  # once until a window fits
                log.warning("hopper scale jumped by %+.1f kg: not seed; the fit restarts there",
                            self.estimator.last_jump_kg)
            self.alarms.set(
                "hopper_scale.jump", True,
                f"hopper weight fell {-self.estimator.last_jump_kg:.0f} kg at once "
                f"({self.estimator.jumps} such jumps): not seed; check the load cells", "warning",
            )
        self._q_model = max(0.0, q_model_g_min)
        self._flow_g_min = self._q_model * self.estimator.factor
        if pooled:
            self._after_window()
        elif self.calibrations is not None and (
            self._identity_checked_at is None or now - self._identity_checked_at >= IDENTITY_CHECK_S
        ):
            self._identity_checked_at = now
            self._check_identity(self.identity.crop)
        self._mass_alarm(now)

    def _after_window(self) -> None:
        st = self.estimator.state()
        log.info(
            "hopper correction x%.4f%s (estimate %s, SE %s, scale sigma %s, %d windows)",
            st.factor, "" if st.applied else " (not applied yet: too little evidence)",
            "-" if st.estimate is None else f"{st.estimate:.4f}",
            "-" if st.standard_error is None else
            f"{st.standard_error * 100:.2f} % (x{st.dispersion ** 0.5:.2f} for correlated noise)",
            "-" if st.sigma_kg is None else f"{st.sigma_kg:.2f} kg", st.windows,
        )
        self.alarms.clear("hopper_scale.jump")  # a window fitted since: the line is sane again
        bound = self.section.max_correction_pct
        self.alarms.set(
            "hopper_scale.at_bound", st.at_bound,
            f"hopper scale finds the discharge x{st.estimate or 1.0:.3f} of the model: "
            f"correction held at its {bound:g} % bound; do a rotation test", "warning",
        )
        self._range_alarm(st)
        diff = self.estimator.disagreement(self.section.disagree_pct)
        self.alarms.set(
            "hopper_scale.disagrees", diff is not None,
            f"hopper scale and model disagree by {(diff or 0.0) * 100:+.1f} % over the last "
            "window: check the outlets, the hopper and the scale", "warning",
        )
        if self.store is not None:
            try:
                self.store.save(self.identity, st.factor, self.estimator.evidence(),
                                st.standard_error)
            except OSError as exc:
                log.error("hopper correction not saved: %s", exc)
        if self.calibrations is not None:
            self._check_identity(self.identity.crop)  # a rotation test saved meanwhile

    def _range_alarm(self, st: CorrectionState) -> None:
        """The drill is off its model beyond what the correction may apply: it sows
        ``residual_pct`` off target, silently otherwise. Critical from
        ``OUT_OF_RANGE_CRITICAL_PCT`` of residual error (a tenth of the seed off)."""
        if not st.out_of_range:
            self.alarms.clear("hopper_scale.out_of_range")
            return
        bound = self.section.max_correction_pct
        severity: AlarmSeverity = ("critical" if abs(st.residual_pct) >= OUT_OF_RANGE_CRITICAL_PCT
                    else "warning")
        self.alarms.set(
            "hopper_scale.out_of_range", True,
            f"hopper scale finds the discharge x{st.estimate or 1.0:.3f} of the model "
            f"(SE {(st.standard_error or 0.0) * 100:.1f} %), outside the correction range "
            f"±{bound:g} %: sowing {st.residual_pct:+.1f} % off target; do a rotation test",
            severity,
        )

    def mass_kg(self, now: float) -> float | None:
        fresh = [kg for t, kg in self._readings if now - t <= MASS_FRESH_S]
        return statistics.median(fresh) if fresh else None

    def _mass_alarm(self, now: float) -> None:
        mass = self.mass_kg(now)
        low = mass is not None and mass < self.section.warn_below_kg
        tte = time_to_empty_min(mass, self._flow_g_min)
        when = "" if tte is None else f", empty in {tte:.0f} min at this rate"
        self.alarms.set(
            "hopper_scale.low", low,
            f"hopper {mass or 0.0:.0f} kg, below {self.section.warn_below_kg:g} kg{when}",
            "warning",
        )

    def state(self, now: float) -> HopperState:
        st = self.estimator.state()
        mass = self.mass_kg(now)
        return HopperState(
            mass_kg=mass,
            time_to_empty_min=time_to_empty_min(mass, self._flow_g_min),
            discharge_correction=st.factor,
            correction_estimate=st.estimate,
            correction_standard_error=st.standard_error,
            correction_applied=st.applied,
            scale_sigma_kg=st.sigma_kg,
            windows=st.windows,
            refills=st.refills,
        )
