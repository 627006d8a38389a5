"""``sowgate calibrate positions --survey`` and ``sowgate export --reposition`` on a store of
seeds positioned with a lever arm 5 cm off and no delay correction: the fit is saved like
the other calibrations (undo restores), the daemon starts with it, export re-positions."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import tomli_w

from gateway.app.cli import main
from gateway.app.daemon import Daemon
from gateway.calibration.fits import CalibrationStore
from gateway.config import load_config
from gateway.core.records import SeedDrop
from gateway.recording.positioning.survey import MIN_SURVEY_SEEDS, reposition
from gateway.recording.store import RecordStore
from tests.gateway.recording.test_positioning import FRAME, LATENCY_S, ROW_LATERAL_M
from tests.gateway.recording.test_positioning_survey import (
    CONFIGURED,
    EDGES,
    TRUE,
    TWO_SPEEDS,
    drops_of,
    survey,
)

MACHINE_ID = "seeder-01"


@pytest.fixture
def field(tmp_path: Path) -> tuple[Path, Path, list[SeedDrop]]:
    """(config file, state dir, the stored drops): the fitter's config and its records."""
    config = tmp_path / "sowgate.toml"
    config.write_text(tomli_w.dumps({"positioning": {
        "gnss_output_latency_ms": LATENCY_S * 1000.0,
        "outlet_behind_antenna_m": CONFIGURED.outlet_behind_antenna_m,
        "row_lateral_m": CONFIGURED.lateral_offsets(),
    }}))
    state = tmp_path / "state"
    drops = drops_of(CONFIGURED, TWO_SPEEDS, EDGES, until=10.0)
    with RecordStore(state / "records.sqlite3", MACHINE_ID) as store:
        store.append_seeds(drops)
        store.flush()
    return config, state, drops


def write_survey(path: Path, drops: list[SeedDrop], ids: list[int]) -> Path:
    points = survey(drops)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "lat", "lon", "row"])
        for i in ids:
            w.writerow([i, f"{points[i - 1][0]:.9f}", f"{points[i - 1][1]:.9f}",
                        drops[i - 1].row])
    return path


def calibrate(config: Path, state: Path, *args: str) -> int:
    return main(["calibrate", "--config", str(config), "--state-dir", str(state), *args])


def test_a_survey_fit_is_saved_shown_used_at_start_and_undone(
    field: tuple[Path, Path, list[SeedDrop]], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    config, state, drops = field
    csv_file = write_survey(tmp_path / "survey.csv", drops, list(range(1, len(drops) + 1, 2)))
    assert calibrate(config, state, "positions", "--survey", str(csv_file)) == 0
    out = capsys.readouterr().out
    assert "before" in out and "after" in out and "CV" in out and "saved positions.survey" in out
    result = CalibrationStore(state).get("positions.survey")["result"]  # type: ignore[index]
    assert result["outlet_behind_antenna_m"] == pytest.approx(1.2, abs=0.01)
    assert result["row_lateral_m"][0] == pytest.approx(ROW_LATERAL_M[0], abs=0.005)

    # the daemon positions new seeds with it from its start
    settings = load_config(config)
    settings.gnss.enabled = settings.seed_sensors.enabled = True
    settings.hmi.enabled = settings.rs485.enabled = False
    settings.speed.source = ["gnss"]
    daemon = Daemon(settings, state)
    try:
        recorder = daemon.parts.seeds
        assert recorder is not None
        assert recorder.positioner.offsets[0].behind_m == pytest.approx(1.2, abs=0.01)
        assert any("seed positions" in note for note in daemon.calibrations)
    finally:
        for close in daemon.closers:
            close()

    assert calibrate(config, state, "undo", "--key", "positions.survey") == 0
    assert CalibrationStore(state).get("positions.survey") is None


def test_export_reposition_moves_stored_seeds_to_the_fitted_model(
    field: tuple[Path, Path, list[SeedDrop]], tmp_path: Path,
) -> None:
    config, state, drops = field
    csv_file = write_survey(tmp_path / "survey.csv", drops, list(range(2, len(drops) + 1, 2)))
    assert calibrate(config, state, "positions", "--survey", str(csv_file)) == 0
    for flag, worst in ((["--reposition"], 0.012), ([], None)):
        out = tmp_path / f"seeds{len(flag)}.csv"
        common = ["--config", str(config), "--state-dir", str(state), "--output", str(out)]
        assert main(["export", *common, *flag]) == 0
        with out.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        errors = []
        for row, drop in zip(rows, drops, strict=True):
            e, n, _ = FRAME.to_enu(float(row["lat"]), float(row["lon"]))
            te, tn, _ = FRAME.to_enu(*reposition(drop, TRUE))
            errors.append(math.hypot(e - te, n - tn))
        if worst is None:
            assert min(errors) > 0.03  # as stored: the wrong lever arm
        else:
            assert max(errors) < worst  # the fit's residual error, seeds it never saw too


def test_too_few_surveyed_seeds_are_refused_and_nothing_is_saved(
    field: tuple[Path, Path, list[SeedDrop]], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    config, state, drops = field
    csv_file = write_survey(tmp_path / "s.csv", drops, list(range(1, MIN_SURVEY_SEEDS)))
    assert calibrate(config, state, "positions", "--survey", str(csv_file)) == 1
    assert f"at least {MIN_SURVEY_SEEDS}" in capsys.readouterr().out
    assert CalibrationStore(state).get("positions.survey") is None


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("id,lat,lon\n1,52.1,13.2\n2,north,13.2\n", "survey.csv:3: lat is not a number"),
        ("id,lat,lon\n1,95,13.2\n", "survey.csv:2: lat outside -90..90"),
        ("seed,lat,lon\n1,52.1,13.2\n", "header must name id (or utc), lat and lon"),
        ("id,lat,lon\n9999,52.1,13.2\n" * 1, "no stored record with id 9999"),
    ],
)
def test_a_bad_survey_file_is_named_line_by_line(
    field: tuple[Path, Path, list[SeedDrop]], tmp_path: Path, text: str, problem: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    config, state, _ = field
    f = tmp_path / "survey.csv"
    f.write_text(text)
    assert calibrate(config, state, "positions", "--survey", str(f)) == 1
    assert problem in capsys.readouterr().out


def test_surveyed_seeds_can_be_matched_by_landing_time_and_row(
    field: tuple[Path, Path, list[SeedDrop]], tmp_path: Path,
) -> None:
    config, state, drops = field
    points = survey(drops)
    f = tmp_path / "by_utc.csv"
    with f.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["utc", "row", "lat", "lon"])
        for d, (lat, lon) in list(zip(drops, points, strict=True))[::2]:
            w.writerow([d.utc.isoformat().replace("+00:00", "Z"), d.row, lat, lon])
    assert calibrate(config, state, "positions", "--survey", str(f)) == 0
    result = CalibrationStore(state).get("positions.survey")["result"]  # type: ignore[index]
    assert result["outlet_behind_antenna_m"] == pytest.approx(1.2, abs=0.01)


def test_a_survey_that_cannot_tell_the_parameters_apart_is_warned_with_what_to_survey_next(
    field: tuple[Path, Path, list[SeedDrop]], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The stored drive goes one way (heading 37°): the fit is saved, with a warning naming
    the heading to survey next (tests/gateway/recording: the speed band, one side)."""
    config, state, drops = field
    csv_file = write_survey(tmp_path / "survey.csv", drops, list(range(1, len(drops) + 1, 2)))
    assert calibrate(config, state, "positions", "--survey", str(csv_file)) == 0
    out = capsys.readouterr().out
    assert "warning:" in out and "driving one way (heading 37°)" in out
    assert "pass driven the other way (heading 217°)" in out
    result = CalibrationStore(state).get("positions.survey")["result"]  # type: ignore[index]
    assert result["fall_time_table"]  # what the daemon applies (a fitted slope goes in it)
