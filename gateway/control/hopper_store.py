"""The hopper correction kept across restarts, keyed to the calibration it corrects.

``hopper_correction.json`` in the state directory holds, per crop, the factor the hopper scale
found, its evidence (``hopper_correction.Evidence``) and the identity of the calibration it
applies to: the crop, the seed lot (``"default"`` until seed lots are named) and the
``saved_at`` of the active rotation calibration of that crop in ``calibration.json`` (None:
the config's fits). A factor measured against one rotation test means nothing against the
next, nor for another seed lot: when the identity differs the correction starts again at 1.0.
Written atomically (``atomic_write_json``); an unreadable file is logged and ignored (the
daemon runs on the model, as with no scale).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gateway.calibration.fits import CalibrationError, CalibrationStore, atomic_write_json
from gateway.control.hopper_correction import Evidence

log = logging.getLogger(__name__)

HOPPER_FILE = "hopper_correction.json"
FILE_VERSION = 1
DEFAULT_SEED_LOT = "default"


@dataclass(frozen=True)
class Identity:
    """The calibration a correction belongs to."""

    crop: str
    seed_lot: str = DEFAULT_SEED_LOT
    rotation_saved_at: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"crop": self.crop, "seed_lot": self.seed_lot,
                "rotation_saved_at": self.rotation_saved_at}


def rotation_saved_at(store: CalibrationStore | None, keys: list[str]) -> str | None:
    """``saved_at`` of the first active rotation calibration among ``keys`` (``rotation.<crop>``
    or ``rotation.<pwm channel>``), None when there is none (or the file is unreadable)."""
    if store is None:
        return None
    try:
        current = store.current()
    except CalibrationError:
        return None
    for key in keys:
        entry = current.get(key)
        if isinstance(entry, dict) and entry.get("saved_at") is not None:
            return str(entry["saved_at"])
    return None


@dataclass(frozen=True)
class Saved:
    factor: float
    evidence: Evidence


class HopperStore:
    def __init__(self, state_dir: Path) -> None:
        self.path = Path(state_dir) / HOPPER_FILE

    def _load(self) -> dict[str, Any]:
        if not self.path.exists():
            return {}
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
            log.error("%s unreadable (%s): hopper correction starts at 1.0", self.path, exc)
            return {}
        crops = doc.get("crops") if isinstance(doc, dict) else None
        return crops if isinstance(crops, dict) else {}

    def load(self, identity: Identity) -> Saved | None:
        """The saved correction for ``identity``'s crop if it was found for that identity."""
        entry = self._load().get(identity.crop)
        if not isinstance(entry, dict):
            return None
        if entry.get("identity") != identity.to_dict():
            log.info(
                "hopper correction for %s was found for %s, the calibration is now %s: "
                "reset to 1.0", identity.crop, entry.get("identity"), identity.to_dict(),
            )
            return None
        try:
            factor = float(entry["factor"])
            evidence = Evidence.from_dict(entry["evidence"])
        except (KeyError, TypeError, ValueError) as exc:
            log.error("%s: %s entry unusable (%s): reset to 1.0", self.path, identity.crop, exc)
            return None
        if not 0.5 <= factor <= 1.5:
            log.error("%s: %s factor %r implausible: reset to 1.0", self.path, identity.crop,
                      factor)
            return None
        return Saved(factor, evidence)

    def save(self, identity: Identity, factor: float, evidence: Evidence,
             standard_error: float | None) -> None:
        crops = self._load()
        crops[identity.crop] = {
            "identity": identity.to_dict(),
            "factor": factor,
            "standard_error": standard_error,
            "evidence": evidence.to_dict(),
        }
        atomic_write_json(self.path, {"version": FILE_VERSION, "crops": crops})
