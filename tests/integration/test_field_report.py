"""``sowgate report`` on the store of a real (short) simulated run: the daemon records the
simulated planter's seeds, then the report is made from that store as a farmer would, and its
numbers are checked against ``sowgate export`` on the same records."""

from __future__ import annotations

import asyncio
import base64
import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from gateway.app.cli import main as sowgate
from gateway.recording.field_stats import MAP_POINTS_MAX
from gateway.recording.store import RecordStore
from gateway.report.command import EXIT_NO_RECORDS, EXIT_USAGE
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from tests.helpers import eventually, run_sowgate, sowgate_env
from tests.integration.conftest import running

MACHINE_ID = "seeder-01"
SEEDS = 600


@dataclass(frozen=True)
class Run:
    state: Path
    config: Path
    seeds: int


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    """The real daemon sows for a while on the simulated machine (GNSS and seed tubes)."""
    tmp = tmp_path_factory.mktemp("field")
    drive = Drive(legs=[Leg(3.0, 0.0), Leg(40.0, 8.0), Leg(600.0, 0.0)], dt=0.02)
    machine = SimulatedMachine(drive=drive, with_gnss=True, with_seed_tubes=True)

    async def sow() -> None:
        async with running(tmp, machine, control={"start_working": True}) as rig:
            tubes = rig.machine.seed_tubes
            assert tubes is not None
            await eventually(lambda: len(tubes.truth) >= SEEDS, 40.0, f"{SEEDS} seeds dropped")
            await rig.stop()
            # the config the daemon ran with, as a file for the command line
            machine.write_config(tmp / "sowgate.toml", control={"start_working": True})

    asyncio.run(sow())
    state = tmp / "state"
    with RecordStore.open_readonly(state / "records.sqlite3", MACHINE_ID) as store:
        n = sum(1 for _ in store.query_seeds())
    assert n >= SEEDS
    yield Run(state, tmp / "sowgate.toml", n)


def report(run: Run, out: Path, *extra: str) -> int:
    return sowgate(["report", "--config", str(run.config), "--state-dir", str(run.state),
                    "--output", str(out), *extra])


def report_data(path: Path) -> dict[str, object]:
    text = path.read_text(encoding="utf-8")
    m = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', text,
                  re.S)
    assert m is not None, "the report embeds its numbers"
    data: dict[str, object] = json.loads(m.group(1).replace("<\\/", "</"))
    return data


def export_geojson(run: Run, out: Path, *extra: str) -> dict[str, object]:
    code = sowgate(["export", "--config", str(run.config), "--state-dir", str(run.state),
                    "--output", str(out), *extra])
    assert code == 0
    doc: dict[str, object] = json.loads(out.read_text())
    return doc


def test_the_reports_numbers_equal_exports_for_the_same_records(run: Run, tmp_path: Path) -> None:
    assert report(run, tmp_path / "report.html") == 0
    data = report_data(tmp_path / "report.html")
    doc = export_geojson(run, tmp_path / "seeds.geojson")
    features = doc["features"]
    assert isinstance(features, list)
    assert data["seeds"] == len(features) == run.seeds
    assert data["quality"] == doc["quality"]  # every index of every row, exactly
    by_row: dict[str, int] = {}
    for f in features:
        key = str(f["properties"]["row"])
        by_row[key] = by_row.get(key, 0) + 1
    assert data["seeds_by_row"] == by_row
    fixes = [f["properties"]["fix"] for f in features]
    assert data["rtk_fixed_share"] == pytest.approx(fixes.count("rtk_fixed") / len(fixes))
    extrapolated = [f["properties"]["extrapolated"] for f in features]
    assert data["extrapolated"] == sum(extrapolated)
    # the map classes every seed: those with a spacing are rated against their row's target
    classes = data["map_classes"]
    assert isinstance(classes, dict)
    assert sum(classes.values()) == run.seeds
    spaced = sum(1 for f in features if f["properties"]["spacing_m"] is not None)
    assert classes["no spacing"] == run.seeds - spaced


def test_the_html_report_is_one_self_contained_file(run: Run, tmp_path: Path) -> None:
    out = tmp_path / "report.html"
    assert report(run, out) == 0
    text = out.read_text(encoding="utf-8")
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", text, re.I)
    assert "<link" not in text and "url(" not in text and "<iframe" not in text
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(images) == 5  # map, histograms, rate along the drive, against speed, alarms
    for b64 in images:
        assert base64.b64decode(b64).startswith(b"\x89PNG\r\n\x1a\n")
    for heading in ("Seed map", "Spacing quality per row (ISO 7256-1)", "Alarm timeline",
                    "Applied rate along the drive", "Applied rate against speed", "Summary"):
        assert f"<h2>{heading}</h2>" in text
    assert MACHINE_ID in text


def test_pdf_gives_the_same_report_as_a_valid_pdf(run: Run, tmp_path: Path) -> None:
    out = tmp_path / "report.pdf"
    assert report(run, out) == 0  # the extension picks the format
    data = out.read_bytes()
    assert data.startswith(b"%PDF-") and data.rstrip().endswith(b"%%EOF")
    # a summary page with the quality table, then the five plots
    assert len(re.findall(rb"/Type\s*/Page\b", data)) == 6
    forced = tmp_path / "report.bin"
    assert report(run, forced, "--format", "pdf") == 0
    assert forced.read_bytes().startswith(b"%PDF-")


def test_rows_filter_reports_only_those_rows_with_exports_numbers(
    run: Run, tmp_path: Path
) -> None:
    assert report(run, tmp_path / "r.html", "--rows", "1,3") == 0
    data = report_data(tmp_path / "r.html")
    doc = export_geojson(run, tmp_path / "r.geojson", "--rows", "1,3")
    assert set(data["quality"]) == {"1", "3"}  # type: ignore[arg-type]
    assert data["quality"] == doc["quality"]
    assert data["seeds"] == len(doc["features"]) < run.seeds  # type: ignore[arg-type,operator]


def test_an_empty_time_window_says_so_and_writes_nothing(run: Run, tmp_path: Path) -> None:
    out = tmp_path / "r.html"
    p = run_sowgate("report", "--config", str(run.config), "--state-dir", str(run.state),
                    "--output", str(out), "--since", "2090-01-01T00:00:00Z",
                    env=sowgate_env(clean=True))
    assert p.returncode == EXIT_NO_RECORDS
    assert "nothing to report: no seed records" in p.stderr and "since 2090" in p.stderr
    assert "Traceback" not in p.stderr
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary file left either


def test_bad_times_are_clear_usage_errors(run: Run, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "r.html"
    assert report(run, out, "--since", "yesterday") == EXIT_USAGE
    assert "--since: not an ISO 8601 time: 'yesterday'" in capsys.readouterr().err
    assert report(run, out, "--since", "2026-05-02T08:00", "--until", "2026-05-02T07:00") \
        == EXIT_USAGE
    assert "--until must be later than --since" in capsys.readouterr().err
    assert report(run, out, "--rows", "0,99") == EXIT_USAGE
    assert not out.exists()


def test_help_documents_the_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        sowgate(["report", "--help"])
    text = capsys.readouterr().out
    assert f"{EXIT_NO_RECORDS}  nothing to report" in text
    assert "--since" in text and "--rows" in text and "--format" in text
    # the documented point count is the one the map uses
    assert f"every seed up to {MAP_POINTS_MAX:,} seeds".replace(",", " ") in text
