"""The running daemon applies a saved calibration at its next look at the file, with the
start-up vet; seed-lot switches are refused for what does not exist."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.app.daemon import Daemon
from gateway.calibration import fits as cal
from gateway.calibration.presence import WATCH_S
from gateway.core.errors import CommandError
from tests.helpers import wheat_drill


def save_gpr(state: Path, per_outlet: float, key: str = "rotation.seed") -> None:
    runs = [cal.RotationRun(n, 30.0, per_outlet * n / 2) for n in (20.0, 40.0, 60.0)]
    cal.CalibrationStore(state).save(key, cal.to_entry(
        cal.grams_per_rev(runs), channel="seed", model="grams_per_rev"))


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def daemon_at(state: Path, clock: Clock) -> Daemon:
    daemon = Daemon(wheat_drill(), state, clock=clock)
    for close in daemon.closers:
        close()
    return daemon


def test_a_save_is_applied_at_the_next_look_not_before(tmp_path: Path) -> None:
    clock = Clock()
    daemon = daemon_at(tmp_path, clock)
    save_gpr(tmp_path, 11.6)
    daemon.live_calibration.poll()
    assert daemon.settings.channel[0].grams_per_rev == 11.2  # not looked yet
    clock.t += WATCH_S
    daemon.live_calibration.poll()
    assert daemon.settings.channel[0].grams_per_rev == pytest.approx(11.6)
    reloads = daemon.live_calibration.reloads
    clock.t += WATCH_S
    daemon.live_calibration.poll()
    assert daemon.live_calibration.reloads == reloads  # unchanged file: not applied again


def test_a_calibration_that_would_sow_nothing_is_refused_live_and_the_alarm_clears(
    tmp_path: Path,
) -> None:
    daemon = daemon_at(tmp_path, Clock())
    save_gpr(tmp_path, 287.6)  # all 24 outlets' catch as one outlet's
    daemon.live_calibration.reload()
    assert daemon.settings.channel[0].grams_per_rev == 11.2
    assert daemon.alarms.is_active("calibration.refused")
    save_gpr(tmp_path, 11.5)
    daemon.live_calibration.reload()
    assert daemon.settings.channel[0].grams_per_rev == pytest.approx(11.5)
    assert not daemon.alarms.is_active("calibration.refused")


def test_a_seed_lot_switch_is_refused_for_an_unknown_crop_or_lot(tmp_path: Path) -> None:
    save_gpr(tmp_path, 11.5, "rotation.seed@2026-B")
    live = daemon_at(tmp_path, Clock()).live_calibration
    with pytest.raises(CommandError, match="unknown crop 'barley'"):
        live.select_lot("barley", "2026-B")
    with pytest.raises(CommandError, match=r"no rotation test for seed lot '2026-C'.*2026-B"):
        live.select_lot("wheat", "2026-C")
    with pytest.raises(CommandError, match="seed lot name"):
        live.select_lot("wheat", "a/b")
    assert live.lot_of("wheat") == "default"
    reply = live.select_lot("wheat", "2026-B")
    assert reply.startswith("wheat: seed lot 2026-B") and "11.50 g/rev" in reply
    assert live.live.channel[0].grams_per_rev == pytest.approx(11.5)
