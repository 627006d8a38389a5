"""``sowgate export --format isoxml`` on the store of a real (short) simulated run, read back by
two independent ISO-XML readers (isoxml-js, the Python ``isoxml`` package) and by our own time
log decoder, and checked against ``sowgate export``'s GeoJSON of the same records: every seed
and every as-applied row is a time log record at its position (within 1e-7 degree) and UTC
time (to the millisecond), with its rates (within 0.1 %)."""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from gateway.app.cli import main as sowgate
from gateway.app.isoxml_device import DDIS, ROW_DDIS
from gateway.config import load_config
from gateway.core.records import utc_to_us
from gateway.recording.store import RecordStore
from protocol.isoxml_tlg import (
    DataLogValue,
    TimeLogRecord,
    decode_records,
    parse_header_xml,
    tlg_time_to_utc_us,
)
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from tests.helpers import eventually
from tests.integration.conftest import running

MACHINE_ID = "seeder-01"
SEEDS = 400
CHANNEL = {"name": "seed", "product": "rapeseed", "drive": "pwm_modbus",
           "target_rate_kg_ha": 6.0}
FARM = {"customer": "Jane Doe", "farm": "Hill farm", "field": "North 12", "field_area_ha": 12.5}
NODE_READER = Path(__file__).parents[1] / "isoxml_js" / "read_taskdata.js"


@dataclass(frozen=True)
class Run:
    state: Path
    config: Path
    seeds: int
    rows: int
    width_m: float


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    """The real daemon sows (GNSS, seed tubes, a PWM metering channel) for a while."""
    tmp = tmp_path_factory.mktemp("isoxml")
    drive = Drive(legs=[Leg(3.0, 0.0), Leg(40.0, 8.0), Leg(600.0, 0.0)], dt=0.02)
    machine = SimulatedMachine(drive=drive, with_gnss=True, with_seed_tubes=True)
    overrides: dict[str, Any] = {
        "control": {"start_working": True},
        "channel": [CHANNEL],
        "farm": FARM,
    }

    async def sow() -> None:
        async with running(tmp, machine, **overrides) as rig:
            tubes = rig.machine.seed_tubes
            assert tubes is not None
            await eventually(lambda: len(tubes.truth) >= SEEDS, 40.0, f"{SEEDS} seeds dropped")
            as_applied = tmp / "state" / "as_applied.csv"
            await eventually(lambda: as_applied.exists() and len(
                as_applied.read_text().splitlines()) > 3, 20.0, "as-applied rows logged")
            await rig.stop()
            machine.write_config(tmp / "sowgate.toml", **overrides)

    asyncio.run(sow())
    state = tmp / "state"
    with RecordStore.open_readonly(state / "records.sqlite3", MACHINE_ID) as store:
        n = sum(1 for _ in store.query_seeds())
    assert n >= SEEDS
    settings = load_config(tmp / "sowgate.toml")
    yield Run(state, tmp / "sowgate.toml", n, settings.machine.rows,
              settings.machine.working_width_m)


def export(run: Run, out: Path, *extra: str) -> int:
    return sowgate(["export", "--config", str(run.config), "--state-dir", str(run.state),
                    "--output", str(out), *extra])


def geojson(run: Run, out: Path, *extra: str) -> dict[str, Any]:
    assert export(run, out, *extra) == 0
    doc: dict[str, Any] = json.loads(out.read_text())
    return doc


@dataclass
class Log:
    values: list[DataLogValue]
    records: list[TimeLogRecord]

    def named(self, record: TimeLogRecord) -> dict[tuple[int, str], int]:
        return {(self.values[i].ddi, self.values[i].det_id): v for i, v in record.values}


def read_logs(folder: Path) -> dict[str, Log]:
    """Every TLG of the folder through our own decoder (protocol.isoxml_tlg)."""
    logs = {}
    for header in sorted(folder.glob("TLG*.XML")):
        layout, values = parse_header_xml(header.read_bytes())
        assert layout.position_fields == ("A", "B", "D", "H", "I")
        binary = header.with_suffix(".BIN").read_bytes()
        logs[header.stem] = Log(values, list(decode_records(layout, binary)))
    return logs


def us_of(text: str) -> int:
    return utc_to_us(datetime.fromisoformat(text.replace("Z", "+00:00")))


def by_place(logs: dict[str, Log]) -> dict[tuple[int, int, int], list[tuple[Log, TimeLogRecord]]]:
    """Records by (UTC ms, north, east)."""
    index: dict[tuple[int, int, int], list[tuple[Log, TimeLogRecord]]] = defaultdict(list)
    for log in logs.values():
        for r in log.records:
            ms = tlg_time_to_utc_us(r.ms_of_day, r.days_since_1980) // 1000
            index[(ms, r.position[0], r.position[1])].append((log, r))
    return index


def find(index: dict[tuple[int, int, int], list[tuple[Log, TimeLogRecord]]], us: int,
         lat: float, lon: float) -> list[tuple[Log, TimeLogRecord]]:
    """The records at this time whose position is within 1e-7 degree of (lat, lon)."""
    ms = us // 1000
    north, east = round(lat * 1e7), round(lon * 1e7)
    found = []
    for dn in (-1, 0, 1):
        for de in (-1, 0, 1):
            for log, r in index.get((ms, north + dn, east + de), []):
                north_ok = abs(r.position[0] / 1e7 - lat) <= 1e-7
                if north_ok and abs(r.position[1] / 1e7 - lon) <= 1e-7:
                    found.append((log, r))
    return found


@pytest.fixture(scope="module")
def exported(run: Run, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("export")
    assert export(run, out, "--format", "isoxml") == 0
    return out / "TASKDATA"


def test_every_seed_is_a_time_log_record_at_its_place_and_utc_time(
    run: Run, exported: Path, tmp_path: Path
) -> None:
    doc = geojson(run, tmp_path / "seeds.geojson")
    assert len(doc["features"]) == run.seeds
    logs = read_logs(exported)
    index = by_place(logs)
    row_width = run.width_m / run.rows
    for f in doc["features"]:
        p = f["properties"]
        found = find(index, us_of(p["utc"]), p["lat"], p["lon"])
        assert found, f"seed {p['id']} at {p['utc']} is in the time log"
        det = f"DET-{3 + p['row']}"  # device, boom, one channel, then the rows
        values = [log.named(r) for log, r in found]
        spacing = p["spacing_m"]
        if spacing is None:
            continue
        # (a double seeds a second record at the same instant and place: either may be it)
        mine = [v for v in values if v.get((0x0011, det)) == round(spacing * 1000)]
        assert mine, f"seed {p['id']}: its row's spacing is logged"
        expected = 1 / (spacing * row_width) if spacing > 0 else None
        if expected is not None and expected * 1000 < 2**31:  # else it does not fit an int32
            per_m2 = mine[0][(0x000C, det)] / 1000  # 0.001 seeds/m²: to half of that
            assert per_m2 == pytest.approx(expected, rel=1e-3, abs=0.0005)
        else:
            assert (0x000C, det) not in mine[0]
    # and the record's GPS time is its time: a reader that takes either gets UTC
    for log in logs.values():
        for r in log.records:
            assert r.position[3:] == (r.ms_of_day, r.days_since_1980)


def test_every_as_applied_row_is_a_record_with_its_rates(
    run: Run, exported: Path, tmp_path: Path
) -> None:
    doc = geojson(run, tmp_path / "applied.geojson", "--what", "as-applied")
    assert len(doc["features"]) >= 3
    index = by_place(read_logs(exported))
    for f in doc["features"]:
        p = f["properties"]
        lon, lat = f["geometry"]["coordinates"]
        found = find(index, us_of(p["time"]), lat, lon)
        rates = [log.named(r) for log, r in found if (0x0006, "DET-3") in log.named(r)]
        assert rates, f"as-applied row at {p['time']} is in the time log"
        target_kg_ha = rates[0][(0x0006, "DET-3")] / 100  # mg/m² -> kg/ha
        assert target_kg_ha == pytest.approx(p["target_kg_ha"], rel=1e-3, abs=0.005)
        if p["applied_kg_ha"] is not None:
            applied = rates[0][(0x0007, "DET-3")] / 100
            assert applied == pytest.approx(p["applied_kg_ha"], rel=1e-3, abs=0.005)


def test_the_last_state_is_the_exports_quality_and_the_machine_stopped(
    run: Run, exported: Path, tmp_path: Path
) -> None:
    doc = geojson(run, tmp_path / "seeds.geojson")
    (log,) = read_logs(exported).values()
    last: dict[tuple[int, str], int] = {}
    for r in log.records:
        last.update(log.named(r))
    assert last[(0x008D, "DET-1")] == 0  # not working after the last seed
    assert last[(0x0043, "DET-2")] == 0
    assert last[(0x00A1, "DET-2")] & 0xFFFFFFFF == 0xFFFFF000  # rows 1-6 off, 7-16 absent
    for row, q in doc["quality"].items():
        det = f"DET-{3 + int(row)}"
        assert last[(0x0052, det)] == sum(
            1 for f in doc["features"] if f["properties"]["row"] == int(row))
        for ddi, name in ((0x01A0, "quality_of_feed_index"), (0x01A2, "miss_index"),
                          (0x01A4, "multiples_index"), (0x01A8, "precision")):
            if q[name] is not None:
                assert last[(ddi, det)] == round(q[name] * 10_000), (row, name)


def isoxml_js(path: Path) -> dict[str, Any]:
    node = shutil.which("node")
    modules = NODE_READER.parent / "node_modules" / "isoxml"
    assert node is not None and modules.is_dir(), (
        "isoxml-js is not installed: run `make isoxml-js` (needs node and npm)")
    p = subprocess.run([node, str(NODE_READER), str(path)], capture_output=True, text=True,
                       timeout=120, check=False)
    assert p.returncode == 0, p.stderr
    doc: dict[str, Any] = json.loads(p.stdout)
    return doc


def test_isoxml_js_reads_the_zip_as_a_task_with_our_records(
    run: Run, exported: Path, tmp_path: Path
) -> None:
    zipped = tmp_path / "task.zip"
    assert export(run, zipped, "--format", "isoxml", "--zip") == 0
    doc = isoxml_js(zipped)
    # isoxml-js looks for lower-case .bin/.xml and only warns about the standard's upper case
    assert [w for w in doc["warnings"] if "Letter case of filename" not in w] == []
    assert doc["version"] == 4
    assert doc["customers"] == ["Jane Doe"] and doc["farms"] == ["Hill farm"]
    assert doc["partfields"] == [{"designator": "North 12", "area": 125_000}]
    assert doc["products"] == ["rapeseed"]
    (device,) = doc["devices"]
    assert [e["designator"] for e in device["elements"]] == [
        "sowgate seeder", "Seed boom", "Channel seed (rapeseed)",
        *(f"Row {r}" for r in range(1, run.rows + 1))]
    (task,) = doc["tasks"]
    assert task["status"] == "4" and task["partfield"] == "PFD-1"
    (tlg,) = task["timeLogs"]
    assert tlg["parsingErrors"] == []
    (ours,) = read_logs(exported).values()
    assert len(tlg["records"]) == len(ours.records) > run.seeds
    for js, r in zip(tlg["records"], ours.records, strict=True):
        assert js["time"] == tlg_time_to_utc_us(r.ms_of_day, r.days_since_1980) // 1000
        assert js["north"] == pytest.approx(r.position[0] / 1e7, abs=1e-9)
        assert js["east"] == pytest.approx(r.position[1] / 1e7, abs=1e-9)
        assert js["values"] == {f"{d:04X}_{e}": v for (d, e), v in ours.named(r).items()}
    first = min(js["time"] for js in tlg["records"])
    start = datetime.fromtimestamp(first // 1000, UTC).strftime("%Y-%m-%dT%H:%M:%S")
    assert task["times"][0]["start"].startswith(start)
    units = {v["ddi"]: v["unit"] for v in tlg["values"]}
    assert units["0007"] == "kg/ha" and units["000C"] == "seeds/ha" and units["018D"] == "km/h"


def test_the_python_isoxml_package_reads_the_folder(run: Run, exported: Path) -> None:
    from isoxml.models.base.v4 import TaskStatus
    from isoxml.util.isoxml_io import isoxml_from_path

    root, refs = isoxml_from_path(exported)
    (task,) = root.tasks
    assert task.status == TaskStatus.Completed
    assert [t.filename for t in task.time_logs] == ["TLG00001"]
    assert refs["TLG00001"] == (exported / "TLG00001.BIN").read_bytes()
    assert [c.last_name for c in root.customers] == ["Jane Doe"]
    (device,) = root.devices
    assert len(device.elements) == 3 + run.rows
    logged = {bytes(p.ddi).hex().upper() for p in device.process_data}
    assert logged <= {f"{d.number:04X}" for d in DDIS}
    assert {f"{d.number:04X}" for d in ROW_DDIS} <= logged
