"""Field calibrations override the config file at start-up.

``sowgate calibrate`` (and the HMI "zero" button) write ``calibration.json`` in the state
directory; the fitter's config keeps the factory values. At start the daemon lays the
calibrations over the config so a refitted machine sows with its own curves, and the
``undo`` of a bad calibration is a restart away.

A calibration saved while the daemon runs is applied by it too (``gateway.app.live_calibration``
re-applies the file onto the config when it changes), the seed position calibration
included (the seed recorder's positioner takes the new ``[positioning]``). The daemon passes a
``vet`` (``gateway.app.calibration_check.working_speed_problem``): a calibration that would
make a channel sow nothing or run flat out over the machine's working speeds is refused, the
config value kept, and ``calibration.refused`` raised naming the key and why.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gateway.calibration.fits import CalibrationError, CalibrationStore
from gateway.calibration.lots import active_lots, effective_entries
from gateway.config import Settings
from gateway.core.alarms import AlarmBoard

log = logging.getLogger(__name__)

REFUSED_ALARM = "calibration.refused"

# (settings before the entry, settings with it, key) -> why it must not be used, or None
Vet = Callable[[Settings, Settings, str], str | None]


def apply_calibrations(settings: Settings, state_dir: Path, *, vet: Vet | None = None,
                       alarms: AlarmBoard | None = None) -> list[str]:
    """Apply what ``calibration.json`` holds to ``settings`` in place; returns what changed.

    An unreadable file or an entry that no longer fits the config is reported and skipped:
    the daemon starts on the config's values rather than not at all. Each entry is first
    applied to a copy and, with a ``vet``, checked: an entry it objects to is refused (the
    config value stays), logged, listed as ``<key>: refused (...)`` and, with ``alarms``,
    raised as ``calibration.refused``.
    """
    try:
        doc = CalibrationStore(state_dir).load()
    except CalibrationError as exc:
        log.error("calibrations not applied: %s", exc)
        return [f"calibration file ignored: {exc}"]
    current = effective_entries(settings, doc["current"], active_lots(doc))
    applied, refused = apply_entries(settings, current, vet=vet)
    if alarms is not None and refused:
        alarms.raise_(REFUSED_ALARM, refused_message(refused), "warning")
    return applied


def refused_message(refused: list[str]) -> str:
    return "calibration refused, config value used: " + "; ".join(refused)


def apply_entries(settings: Settings, current: dict[str, Any], *,
                  vet: Vet | None = None) -> tuple[list[str], list[str]]:
    """Apply the entries of ``current`` (a calibration file's ``current``, its seed lots
    resolved by ``lots.effective_entries``) to ``settings``;
    (notes on what changed, ``<key> <why>`` of each entry the ``vet`` refused)."""
    applied: list[str] = []
    refused: list[str] = []
    for key, entry in sorted(current.items()):
        try:
            result = entry.get("result", {})
            candidate = settings.model_copy(deep=True)
            _apply_one(candidate, key, result, entry)
            problem = vet(settings, candidate, key) if vet is not None else None
            if problem is None:
                note = _apply_one(settings, key, result, entry)
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            log.error("calibration %s not applied: %s", key, exc)
            applied.append(f"{key}: not applied ({exc})")
            continue
        if problem is not None:
            log.error("calibration %s refused, the config value is used: %s", key, problem)
            applied.append(f"{key}: refused ({problem})")
            refused.append(f"{key} {problem}")
            continue
        if note:
            applied.append(note)
            log.info("calibration applied: %s", note)
    return applied, refused


def _paper_a_crop(settings: Settings, name: str) -> str | None:
    """A paper-A rotation test is stored per crop, or per pwm_modbus channel (its product)."""
    if name in settings.control.crops:
        return name
    for ch in settings.channel:
        if ch.name == name and ch.drive == "pwm_modbus":
            return ch.product
    return None


def _apply_one(settings: Settings, key: str, result: dict[str, Any], entry: dict[str, Any]) -> str:
    kind, _, name = key.partition(".")
    if kind == "speed":
        factor = float(result["factor"])
        settings.speed.correction = {**settings.speed.correction, name: factor}
        return f"{name} speed x{factor:.4f}"
    if kind == "tilt" and name == "inclinometer":
        parts = []
        if result.get("zero_offset_deg") is not None:
            settings.inclinometer.zero_offset_deg = float(result["zero_offset_deg"])
            parts.append(f"zero {settings.inclinometer.zero_offset_deg:+.2f} deg")
        if result.get("critical_angle_deg") is not None:
            crit = float(result["critical_angle_deg"]) - settings.inclinometer.zero_offset_deg
            settings.inclinometer.critical_angle_deg = crit
            parts.append(f"critical {crit:+.2f} deg")
        return "tilt " + ", ".join(parts)
    if kind == "rotation":
        model = entry.get("model")
        crop = _paper_a_crop(settings, name) if model == "paper_a" else None
        if crop is not None:
            old = settings.control.crops[crop]
            lo, hi = result["omega_range"]
            new = old.model_validate(
                {
                    **old.model_dump(),
                    "motor_slope": result["motor"]["slope"],
                    "motor_intercept": result["motor"]["intercept"],
                    "meter_a": result["meter"]["a"],
                    "meter_b": result["meter"]["b"],
                    "meter_c": result["meter"]["c"],
                    "omega_min_rpm": lo,
                    "omega_max_rpm": hi,
                    # the drill's own curves (rotation tests of >= 5 set points); older
                    # files hold none and sow on the line and quadratic above
                    "meter_curve": result.get("meter_curve"),
                    "motor_curve": result.get("motor_curve"),
                }
            )
            settings.control.crops = {**settings.control.crops, crop: new}
            via = "" if crop == name else f" (channel {name})"
            shape = " (its own monotone curve)" if result.get("meter_curve") else ""
            return f"{crop} metering model refitted{shape}{via}"
        if model == "grams_per_rev":
            for channel in settings.channel:
                if channel.name == name:
                    channel.grams_per_rev = float(result["grams_per_rev"])
                    # g/rev against shaft speed (>= 5 speeds); older files: none, constant
                    curve = result.get("grams_per_rev_curve")
                    channel.grams_per_rev_curve = (
                        None if curve is None else [(float(n), float(g)) for n, g in curve])
                    return f"{name} {channel.grams_per_rev:.2f} g/rev"
        raise ValueError(f"no crop or channel named {name!r} in the config")
    if kind == "positions":
        # sowgate calibrate positions (gateway.app.position_calibration): absolute values
        pos = settings.positioning
        lateral = [float(x) for x in result["row_lateral_m"]]
        if len(lateral) != settings.machine.rows:
            raise ValueError(
                f"fitted for {len(lateral)} rows, machine.rows is {settings.machine.rows}"
            )
        pos.delay_correction_ms = float(result["delay_correction_ms"])
        pos.outlet_behind_antenna_m = float(result["outlet_behind_antenna_m"])
        pos.row_lateral_m = lateral
        table = result.get("fall_time_table")  # with a fitted delay slope (absent before)
        if table is not None:
            pos.fall_time_table = [(float(v), float(t)) for v, t in table]
        behind_hitch = result.get("outlets_behind_hitch_m")
        if behind_hitch is not None and pos.hitch is not None:
            pos.hitch = pos.hitch.model_copy(
                update={"outlets_behind_hitch_m": float(behind_hitch)}
            )
        return (f"seed positions: outlets {pos.outlet_behind_antenna_m:.3f} m behind the "
                f"antenna, delay {pos.delay_correction_ms:+.1f} ms (surveyed seeds)")
    raise ValueError(f"unknown calibration {key!r}")
