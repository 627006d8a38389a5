"""Seed lots: a crop's rotation-test fits kept per named seed lot, one of them active.

Another seed lot of the same crop (another size, coating, humidity) moves the discharge per
revolution by 5-10 %: a farmer switching between two lots on one drill should not have to
repeat a rotation test at every switch. So a rotation test is saved for a lot
(``sowgate calibrate rotation --seed-lot NAME``) and each crop has one active lot, chosen
from MQTT (``cmd/seed_lot``), the touchscreen (F=08) or the CLI; the daemon applies that lot's
fits (``effective_entries``).

Keys: the lot ``default`` keeps the key calibration files have always had,
``rotation.<name>``; another lot's is ``rotation.<name>@<lot>``. A file written before lots
existed is therefore the default lot of every crop, unchanged. Every new entry also carries
``crop``, ``seed_lot`` and ``saved_at`` (``active_rotation`` reads them back), and
``calibration.json`` holds the active lot per crop under ``seed_lots`` (absent: ``default``).

Which crop a rotation entry belongs to comes from the config: a paper-A entry is named after
its crop, or after the ``pwm_modbus`` channel whose ``product`` it is; a paper-B entry after
its channel, whose crop is that channel's ``product``.
"""

from __future__ import annotations

import re
from typing import Any

from gateway.calibration.fits import CalibrationError, CalibrationStore, atomic_write_json
from gateway.config import Settings

DEFAULT_LOT = "default"
LOT_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,32}$")
SEED_LOTS_KEY = "seed_lots"  # calibration.json: crop -> active lot


def check_lot_name(lot: str) -> str:
    if not isinstance(lot, str) or not LOT_NAME.fullmatch(lot):
        raise CalibrationError(
            f"seed lot name {lot!r}: 1 to 32 letters, digits, '.', '_' or '-'"
        )
    return lot


def rotation_key(name: str, lot: str = DEFAULT_LOT) -> str:
    """The calibration key of ``name``'s rotation test for ``lot``."""
    return f"rotation.{name}" if lot == DEFAULT_LOT else f"rotation.{name}@{lot}"


def split_rotation_key(key: str) -> tuple[str, str] | None:
    """(name, lot) of a rotation key, None for any other key."""
    kind, _, rest = key.partition(".")
    if kind != "rotation" or not rest:
        return None
    name, at, lot = rest.partition("@")
    return name, (lot if at else DEFAULT_LOT)


def crop_of(settings: Settings, name: str) -> str | None:
    """The crop a rotation entry named ``name`` calibrates (None: not in this config)."""
    if name in settings.control.crops:
        return name
    ch = next((c for c in settings.channel if c.name == name), None)
    return None if ch is None else ch.product


def crops(settings: Settings) -> list[str]:
    """Every crop a lot can be chosen for: paper A's crops and the channels' products."""
    return sorted({*settings.control.crops, *(c.product for c in settings.channel)})


def active_lots(doc: dict[str, Any]) -> dict[str, str]:
    """The active lot per crop held in a calibration file (crops not listed: default)."""
    raw = doc.get(SEED_LOTS_KEY)
    if not isinstance(raw, dict):
        return {}
    return {c: lot for c, lot in raw.items()
            if isinstance(c, str) and isinstance(lot, str) and LOT_NAME.fullmatch(lot)}


def lots_of(settings: Settings, current: dict[str, Any], crop: str) -> list[str]:
    """The lots ``crop`` can be switched to: ``default`` first, then those with a rotation
    test of their own, by name (the touchscreen's lot numbers are positions in this list)."""
    found: set[str] = set()
    for key in current:
        split = split_rotation_key(key)
        if split is not None and split[1] != DEFAULT_LOT and crop_of(settings, split[0]) == crop:
            found.add(split[1])
    return [DEFAULT_LOT, *sorted(found)]


def effective_entries(settings: Settings, current: dict[str, Any],
                      lots: dict[str, str]) -> dict[str, Any]:
    """The entries the daemon applies: every non-rotation entry, and for each rotation test
    the entry of its crop's active lot, under the plain key ``rotation.<name>``. A crop whose
    active lot has no test of its own for a name gets the config's values for it (no entry):
    the default lot's fit belongs to another seed."""
    out: dict[str, Any] = {}
    for key, entry in current.items():
        split = split_rotation_key(key)
        if split is None:
            out[key] = entry
            continue
        name, lot = split
        crop = crop_of(settings, name)
        wanted = lots.get(crop, DEFAULT_LOT) if crop is not None else DEFAULT_LOT
        if lot == wanted:
            out[rotation_key(name)] = entry
    return out


def active_rotation(settings: Settings, current: dict[str, Any], lots: dict[str, str],
                    name: str) -> dict[str, Any] | None:
    """The rotation-test entry in force for ``name`` (a crop or channel), with its ``crop``,
    ``seed_lot`` and ``saved_at`` (filled in for entries older than lots); None: the config's
    values are in force."""
    entry = effective_entries(settings, current, lots).get(rotation_key(name))
    if not isinstance(entry, dict):
        return None
    crop = crop_of(settings, name)
    return {"crop": crop, "seed_lot": lots.get(crop or "", DEFAULT_LOT), **entry}


def select_lot(store: CalibrationStore, crop: str, lot: str) -> None:
    """Make ``lot`` the active lot of ``crop`` in the calibration file (not an undo step)."""
    check_lot_name(lot)
    doc = store.load()
    chosen = active_lots(doc)
    chosen[crop] = lot
    doc[SEED_LOTS_KEY] = dict(sorted(chosen.items()))
    atomic_write_json(store.path, doc)
