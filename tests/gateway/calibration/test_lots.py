"""Per-crop rotation-test fits are kept per named seed lot; the crop's active lot is the one
applied; a calibration file from before seed lots is every crop's default lot, unchanged."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from gateway.calibration import fits as cal
from gateway.calibration import lots
from gateway.calibration.apply import apply_calibrations
from tests.helpers import calibration_cli, wheat_drill

W = [20.0, 25.0, 30.0, 35.0, 40.0, 45.0]


def gpr_entry(per_outlet: float, **extra: Any) -> dict[str, Any]:
    runs = [cal.RotationRun(n, 30.0, per_outlet * n / 2) for n in (20.0, 40.0, 60.0)]
    return cal.to_entry(cal.grams_per_rev(runs), channel="seed", model="grams_per_rev", **extra)


def test_the_default_lot_keeps_the_key_files_have_always_had() -> None:
    assert lots.rotation_key("seed") == "rotation.seed"
    assert lots.rotation_key("seed", "2026-B") == "rotation.seed@2026-B"
    assert lots.split_rotation_key("rotation.seed") == ("seed", "default")
    assert lots.split_rotation_key("rotation.seed@2026-B") == ("seed", "2026-B")
    assert lots.split_rotation_key("speed.radar") is None


@pytest.mark.parametrize("bad", ["", "a b", "x" * 33, "lot@2", "é"])
def test_a_lot_name_the_screen_and_keys_cannot_carry_is_refused(bad: str) -> None:
    with pytest.raises(cal.CalibrationError, match="seed lot name"):
        lots.check_lot_name(bad)


def test_a_file_from_before_seed_lots_applies_as_the_default_lot(tmp_path: Path) -> None:
    cal.CalibrationStore(tmp_path).save("rotation.seed", gpr_entry(12.0))  # no seed_lot field
    settings = wheat_drill()
    apply_calibrations(settings, tmp_path)
    assert settings.channel[0].grams_per_rev == pytest.approx(12.0)


def test_the_active_lot_of_the_channels_crop_is_the_one_applied(tmp_path: Path) -> None:
    store = cal.CalibrationStore(tmp_path)
    store.save("rotation.seed", gpr_entry(12.0))
    store.save("rotation.seed@2026-B", gpr_entry(10.5, seed_lot="2026-B"))
    settings = wheat_drill()
    apply_calibrations(settings, tmp_path)
    assert settings.channel[0].grams_per_rev == pytest.approx(12.0)  # default active
    lots.select_lot(store, "wheat", "2026-B")  # the channel sows wheat
    settings = wheat_drill()
    apply_calibrations(settings, tmp_path)
    assert settings.channel[0].grams_per_rev == pytest.approx(10.5)
    # the selection is not an undo step: undo still restores the last save's predecessor
    key, _ = store.undo()
    assert key == "rotation.seed@2026-B"
    assert lots.active_lots(store.load()) == {"wheat": "2026-B"}


def test_a_lot_without_its_own_test_of_a_channel_uses_the_config_value(
    tmp_path: Path,
) -> None:
    store = cal.CalibrationStore(tmp_path)
    store.save("rotation.seed", gpr_entry(12.0))
    lots.select_lot(store, "wheat", "other")
    settings = wheat_drill()
    apply_calibrations(settings, tmp_path)
    assert settings.channel[0].grams_per_rev == 11.2  # the default lot's fit is another seed


def test_lots_are_listed_default_first_then_by_name_per_crop() -> None:
    settings = wheat_drill()
    current = {"rotation.seed@b": {}, "rotation.seed@a": {}, "rotation.wheat@x": {},
               "rotation.rapeseed@r": {}, "speed.radar": {}}
    assert lots.lots_of(settings, current, "wheat") == ["default", "a", "b", "x"]
    assert lots.lots_of(settings, current, "rapeseed") == ["default", "r"]


def test_the_active_rotation_entry_carries_crop_lot_and_saved_at(tmp_path: Path) -> None:
    """What the hopper-scale correction is keyed on: (crop, seed_lot, saved_at)."""
    store = cal.CalibrationStore(tmp_path)
    store.save("rotation.seed", gpr_entry(12.0))  # an old entry: crop and lot filled in
    store.save("rotation.seed@2026-B", gpr_entry(10.5, crop="wheat", seed_lot="2026-B"))
    settings = wheat_drill()
    doc = store.load()
    old = lots.active_rotation(settings, doc["current"], {}, "seed")
    assert old is not None and (old["crop"], old["seed_lot"]) == ("wheat", "default")
    assert old["saved_at"] == doc["current"]["rotation.seed"]["saved_at"]
    new = lots.active_rotation(settings, doc["current"], {"wheat": "2026-B"}, "seed")
    assert new is not None and (new["crop"], new["seed_lot"]) == ("wheat", "2026-B")
    assert new["result"]["grams_per_rev"] == pytest.approx(10.5)
    assert lots.active_rotation(settings, doc["current"], {"wheat": "none"}, "seed") is None


# ---- the CLI ------------------------------------------------------------------------------


def rotation(tmp_path: Path, per_outlet: float, *extra: str) -> list[str]:
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text('[machine]\nworking_width_m = 3.0\nrows = 24\n[[channel]]\nname = "seed"\n'
                   'product = "wheat"\ntarget_rate_kg_ha = 225\nnode_id = 3\noutlets = 24\n'
                   "grams_per_rev = 11.2\n")
    masses = ",".join(f"{24 * per_outlet * n / 2:.3f}" for n in (20, 40, 60))
    return ["calibrate", "--config", str(cfg), "--state-dir", str(tmp_path), "rotation",
            "--channel", "seed", "--speeds", "20,40,60", "--no-wait", "--mass", masses, *extra]


def test_a_rotation_test_for_a_lot_is_kept_beside_the_others_and_made_active(
    tmp_path: Path,
) -> None:
    assert calibration_cli(rotation(tmp_path, 11.5))[0] == 0
    code, out = calibration_cli(rotation(tmp_path, 10.8, "--seed-lot", "2026-B"))
    assert code == 0, out
    assert "seed lot 2026-B is now wheat's active lot" in out
    store = cal.CalibrationStore(tmp_path)
    entry = store.get("rotation.seed@2026-B")
    assert entry is not None
    assert (entry["crop"], entry["seed_lot"]) == ("wheat", "2026-B") and entry["saved_at"]
    # a lot's first test is compared with the default lot's saved value, not the config's
    assert entry["replaces"] == {"grams_per_rev": pytest.approx(11.5),
                                 "from": "calibration (lot default)"}
    default = store.get("rotation.seed")
    assert default is not None and default["seed_lot"] == "default"
    assert default["result"]["grams_per_rev"] == pytest.approx(11.5)
    assert lots.active_lots(store.load()) == {"wheat": "2026-B"}


def test_seed_lot_command_switches_and_refuses_a_lot_never_calibrated(tmp_path: Path) -> None:
    assert calibration_cli(rotation(tmp_path, 10.8, "--seed-lot", "2026-B"))[0] == 0
    cfg = str(tmp_path / "sowgate.toml")
    base = ["calibrate", "--config", cfg, "--state-dir", str(tmp_path), "seed-lot",
            "--crop", "wheat"]
    code, out = calibration_cli([*base, "--lot", "2026-C"])
    assert code == 1 and "no rotation test for seed lot '2026-C'" in out
    assert "default, 2026-B" in out
    code, out = calibration_cli([*base, "--lot", "default"])
    assert code == 0 and "wheat: seed lot default is the active lot" in out, out
    assert lots.active_lots(cal.CalibrationStore(tmp_path).load()) == {"wheat": "default"}
