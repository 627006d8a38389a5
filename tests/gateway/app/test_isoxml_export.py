"""``sowgate export --format isoxml`` on small stores made here: the DDIs are the data
dictionary's, the files are where a terminal looks, the time log follows the rows' sections,
and a bad request changes nothing on disk. (The simulated run, read by isoxml-js and the
Python ``isoxml`` package, is tests/integration/test_isoxml_export.py.)"""

from __future__ import annotations

import argparse
import xml.etree.ElementTree as ET
import zipfile
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from gateway.app.cli import main as sowgate
from gateway.app.isoxml_device import DDIS, ROW_DDIS, Ddi
from gateway.app.isoxml_export import SECTION_OFF_AFTER_S, write_taskdata
from gateway.config import parse_config
from gateway.core.records import SeedDrop, utc_to_us
from gateway.recording.export import EXIT_USAGE
from gateway.recording.store import RecordStore
from protocol.isoxml_tlg import (
    MAX_VALUES_PER_RECORD,
    TimeLogRecord,
    decode_records,
    parse_header_xml,
    tlg_time_to_utc_us,
)

T0 = datetime(2026, 5, 2, 6, 0, tzinfo=UTC)


def drops(rows: int = 6, seconds: int = 4, gap_after: int | None = None) -> list[SeedDrop]:
    """Every row drops a seed each 0.1 s (0.2 m apart at 7.2 km/h); after ``gap_after``
    seconds the machine stops for 10 s."""
    out = []
    for k in range(seconds * 10):
        pause = 10.0 if gap_after is not None and k >= gap_after * 10 else 0.0
        for row in range(1, rows + 1):
            out.append(SeedDrop(
                row=row, utc=T0 + timedelta(seconds=k * 0.1 + row * 0.001 + pause),
                lat=45.75 + k * 1.8e-6, lon=126.63 + row * 1e-5, fix="rtk_fixed",
                speed_kmh=7.2, heading_deg=0.0, heading_source="dual_antenna",
                extrapolated=False, spacing_m=None if k == 0 else 0.2,
            ))
    return out


def make_store(tmp_path: Path, seeds: list[SeedDrop], config: str = "") -> Path:
    state = tmp_path / "state"
    store = RecordStore(state / "records.sqlite3", "seeder-01")
    store.add_seeds(seeds)
    store.flush()
    store.close()
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(f'[store]\npath = "{state}/records.sqlite3"\n{config}')
    return cfg


def export(cfg: Path, out: Path, *extra: str) -> int:
    return sowgate(["export", "--config", str(cfg), "--format", "isoxml", "--output", str(out),
                    *extra])


def logs(folder: Path) -> dict[str, tuple[list[tuple[int, str]], list[TimeLogRecord]]]:
    found = {}
    for header in sorted(folder.glob("TLG*.XML")):
        layout, values = parse_header_xml(header.read_bytes())
        records = list(decode_records(layout, header.with_suffix(".BIN").read_bytes()))
        found[header.stem] = ([(v.ddi, v.det_id) for v in values], records)
    return found


# ---------------------------------------------------------------- the data dictionary


def _dictionary_unit(ddi: int) -> str:
    from isoxml.models.ddi_entities import DDEntity

    e = DDEntity.from_id(ddi)
    return e.unit if e.bit_resolution == 1 else f"{e.bit_resolution:g} {e.unit}"


@pytest.mark.parametrize("ddi", DDIS, ids=lambda d: f"{d.number:04X}")
def test_every_ddi_is_the_iso_11783_11_entry_of_that_number(ddi: Ddi) -> None:
    """Names and units as isobus.net's data dictionary has them (the copy the Python
    ``isoxml`` package ships, extracted from isoxml-js's DDEntities.ts)."""
    from isoxml.models.ddi_entities import DDEntity

    entry = DDEntity.from_id(ddi.number)
    assert entry.name.strip() == ddi.name
    assert _dictionary_unit(ddi.number) == ddi.unit


# ---------------------------------------------------------------- the files


def test_a_folder_export_is_taskdata_xml_with_its_time_log(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, drops(), "[positioning]\ntarget_spacing_m = 0.2\n")
    assert export(cfg, tmp_path / "usb") == 0
    folder = tmp_path / "usb" / "TASKDATA"
    assert sorted(p.name for p in folder.iterdir()) == [
        "TASKDATA.XML", "TLG00001.BIN", "TLG00001.XML"]
    root = ET.parse(folder / "TASKDATA.XML").getroot()
    assert root.tag == "ISO11783_TaskData"
    assert (root.get("VersionMajor"), root.get("VersionMinor")) == ("4", "3")
    assert root.find("CTR") is None and root.find("PFD") is None  # no [farm]: task alone
    tsk = root.find("TSK")
    assert tsk is not None and tsk.get("G") == "4" and tsk.get("C") is None
    tim = tsk.find("TIM")
    assert tim is not None and tim.get("A") == "2026-05-02T06:00:00Z"
    tlg = tsk.find("TLG")
    assert tlg is not None and tlg.get("A") == "TLG00001" and tlg.get("C") == "1"
    assert int(tlg.get("B", "")) == (folder / "TLG00001.BIN").stat().st_size
    assert [p.name for p in (tmp_path / "usb").iterdir()] == ["TASKDATA"]  # no temp left


def test_farm_names_become_customer_farm_and_field(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, drops(), '[farm]\ncustomer = "Jane Doe"\nfarm = "Hill"\n'
                     'field = "North 12"\nfield_area_ha = 12.5\n')
    assert export(cfg, tmp_path / "out") == 0
    root = ET.parse(tmp_path / "out" / "TASKDATA" / "TASKDATA.XML").getroot()
    assert root.find("CTR").attrib == {"A": "CTR-1", "B": "Jane Doe"}  # type: ignore[union-attr]
    assert root.find("FRM").attrib == {"A": "FRM-1", "B": "Hill", "I": "CTR-1"}  # type: ignore[union-attr]
    assert root.find("PFD").attrib == {  # type: ignore[union-attr]
        "A": "PFD-1", "C": "North 12", "D": "125000", "E": "CTR-1", "F": "FRM-1"}
    tsk = root.find("TSK")
    assert tsk is not None
    assert (tsk.get("C"), tsk.get("D"), tsk.get("E")) == ("CTR-1", "FRM-1", "PFD-1")


def test_zip_holds_the_taskdata_folder(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, drops())
    assert export(cfg, tmp_path / "task.zip", "--zip") == 0
    with zipfile.ZipFile(tmp_path / "task.zip") as z:
        assert sorted(z.namelist()) == [
            "TASKDATA/TASKDATA.XML", "TASKDATA/TLG00001.BIN", "TASKDATA/TLG00001.XML"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sowgate.toml", "state", "task.zip"]


# ---------------------------------------------------------------- the time log


def test_each_seed_is_a_record_at_its_time_and_place(tmp_path: Path) -> None:
    seeds = drops()
    cfg = make_store(tmp_path, seeds)
    assert export(cfg, tmp_path / "out") == 0
    ((keys, records),) = logs(tmp_path / "out" / "TASKDATA").values()
    by_time = {tlg_time_to_utc_us(r.ms_of_day, r.days_since_1980): r for r in records}
    for d in seeds:
        r = by_time[utc_to_us(d.utc) // 1000 * 1000]
        assert r.position[:3] == (round(d.lat * 1e7), round(d.lon * 1e7), 4)  # RTK fixed
        values = {keys[i]: v for i, v in r.values}
        if d.spacing_m is not None:
            assert values[(0x0011, f"DET-{2 + d.row}")] == 200  # mm
            # 0.2 m apart on rows 2 m / 6 apart: 15 seeds/m², in 0.001/m²
            assert values[(0x000C, f"DET-{2 + d.row}")] == 15_000


def test_rows_close_after_a_pause_and_reopen_with_the_next_seed(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, drops(rows=2, seconds=4, gap_after=2), "[machine]\nrows = 2\n")
    assert export(cfg, tmp_path / "out") == 0
    ((keys, records),) = logs(tmp_path / "out" / "TASKDATA").values()
    work = keys.index((0x008D, "DET-1"))
    condensed = keys.index((0x00A1, "DET-2"))
    width = keys.index((0x0043, "DET-2"))
    changes = []
    for r in records:
        values = dict(r.values)
        if work in values:
            changes.append((tlg_time_to_utc_us(r.ms_of_day, r.days_since_1980),
                            values[work], values.get(condensed, 0) & 0xF,
                            values.get(width)))
    times = [tlg_time_to_utc_us(r.ms_of_day, r.days_since_1980) for r in records]
    assert times == sorted(times)  # the closing records are in time order too
    t0 = utc_to_us(T0)
    off = round(SECTION_OFF_AFTER_S * 1e6)
    last_before_pause = t0 + 1_900_000 + 2_000  # k = 19, row 2
    first_after = t0 + 2_000_000 + 10_000_000 + 1_000  # k = 20 + 10 s, row 1
    last = t0 + 3_900_000 + 10_000_000 + 2_000
    assert changes == [
        (t0 + 1_000, 1, 0b0001, 1000),  # row 1 on: 1 of 2 rows of 2 m / 2
        (last_before_pause + off, 0, 0b0000, 0),  # both closed 2 s after their last seed
        (first_after, 1, 0b0001, 1000),
        (last + off, 0, 0b0000, 0),
    ]


def test_a_wide_planter_is_split_over_time_logs_of_at_most_255_values(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, drops(rows=48, seconds=2),
                     "[machine]\nrows = 48\nworking_width_m = 36\n")
    assert export(cfg, tmp_path / "out") == 0
    folder = tmp_path / "out" / "TASKDATA"
    found = logs(folder)
    assert list(found) == ["TLG00001", "TLG00002"]
    for keys, _ in found.values():
        assert len(keys) <= MAX_VALUES_PER_RECORD
        assert (0x008D, "DET-1") in keys  # every log has the machine's state
    row_dets = [{det for ddi, det in keys if ddi == ROW_DDIS[0].number}
                for keys, _ in found.values()]
    assert row_dets[0].isdisjoint(row_dets[1])
    assert row_dets[0] | row_dets[1] == {f"DET-{2 + r}" for r in range(1, 49)}
    for (keys, records), dets in zip(found.values(), row_dets, strict=True):
        # each seed with a spacing is in its own row's log, once
        spaced = [r for r in records if any(keys[i][0] == 0x0011 for i, _ in r.values)]
        assert len(spaced) == len(dets) * 19
    tsk = ET.parse(folder / "TASKDATA.XML").getroot().find("TSK")
    assert tsk is not None and [t.get("A") for t in tsk.findall("TLG")] == [
        "TLG00001", "TLG00002"]


def test_since_and_until_keep_the_records_in_the_window(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, drops(seconds=4))
    assert export(cfg, tmp_path / "out", "--since", "2026-05-02T06:00:01Z",
                  "--until", "2026-05-02T06:00:02Z") == 0
    ((_, records),) = logs(tmp_path / "out" / "TASKDATA").values()
    seeds = [r for r in records if r.values]
    times = [tlg_time_to_utc_us(r.ms_of_day, r.days_since_1980) for r in seeds]
    t0 = utc_to_us(T0)
    assert min(times) == t0 + 1_000_000 + 1_000
    # the last seed at 1.9 s; the rows close 2 s later
    assert max(times) == t0 + 1_900_000 + 6_000 + round(SECTION_OFF_AFTER_S * 1e6)


def test_an_empty_store_gives_a_task_without_a_time_log(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, [])
    assert export(cfg, tmp_path / "out") == 0
    folder = tmp_path / "out" / "TASKDATA"
    assert [p.name for p in folder.iterdir()] == ["TASKDATA.XML"]
    tsk = ET.parse(folder / "TASKDATA.XML").getroot().find("TSK")
    assert tsk is not None and tsk.find("TLG") is None and tsk.find("TIM") is None


def test_reposition_exports_the_same_seeds(tmp_path: Path) -> None:
    cfg = make_store(tmp_path, drops())
    assert export(cfg, tmp_path / "out", "--reposition") == 0
    ((_, records),) = logs(tmp_path / "out" / "TASKDATA").values()
    assert len(records) >= len(drops())


# ---------------------------------------------------------------- refusals


def test_an_existing_taskdata_is_not_overwritten(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = make_store(tmp_path, drops())
    old = tmp_path / "usb" / "TASKDATA"
    old.mkdir(parents=True)
    (old / "TASKDATA.XML").write_text("the farmer's plan")
    assert export(cfg, tmp_path / "usb") == EXIT_USAGE
    assert "TASKDATA exists" in capsys.readouterr().err
    assert (old / "TASKDATA.XML").read_text() == "the farmer's plan"
    assert [p.name for p in (tmp_path / "usb").iterdir()] == ["TASKDATA"]


@pytest.mark.parametrize(
    ("output", "extra", "message"),
    [
        ("-", (), "writes a folder"),
        ("state", ("--zip",), "is a folder"),
        ("sowgate.toml", (), "not a folder"),
    ],
)
def test_impossible_outputs_are_usage_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], output: str, extra: tuple[str, ...],
    message: str,
) -> None:
    cfg = make_store(tmp_path, drops())
    before = sorted(p.name for p in tmp_path.iterdir())
    target = output if output == "-" else str(tmp_path / output)
    assert sowgate(["export", "--config", str(cfg), "--format", "isoxml", "--output", target,
                    *extra]) == EXIT_USAGE
    assert message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_failed_export_leaves_nothing_behind(tmp_path: Path) -> None:
    """A seed of a row the machine does not have (the config changed since): refused, and
    the half-written folder is gone."""
    cfg = make_store(tmp_path, drops(rows=8), "[machine]\nrows = 6\n")
    out = tmp_path / "out"
    args = argparse.Namespace(config=cfg, state_dir=None, output=str(out), since=None,
                              until=None, rows=None, reposition=False, zip=False)
    from gateway.app.isoxml_export import main_export_isoxml

    assert main_export_isoxml(args) == EXIT_USAGE
    assert list(out.iterdir()) == []


def test_the_writer_can_be_fed_without_a_store(tmp_path: Path) -> None:
    """``write_taskdata`` takes the store's chunks and as-applied events: a day's worth is
    streamed through it, never listed."""
    settings = parse_config({})

    def chunks() -> Iterator[list[tuple[object, ...]]]:
        for i, d in enumerate(drops()):
            yield [(i + 1, utc_to_us(d.utc), d.row, d.lat, d.lon, d.fix, d.speed_kmh, 0.0,
                    "dual_antenna", 0, "interpolated", d.spacing_m, None, None, None, None,
                    None, None)]

    result = write_taskdata(tmp_path, settings, chunks(), iter(()), "test")
    assert (result.seeds, result.applied, result.logs) == (len(drops()), 0, 1)


def test_as_applied_rows_of_an_unknown_channel_are_counted_and_left_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from gateway.metering.prescription import AsAppliedLog, AsAppliedRow

    cfg = make_store(tmp_path, drops(), '[[channel]]\nname = "seed"\ntarget_rate_kg_ha = 150\n'
                     f'[prescription]\nas_applied_path = "{tmp_path}/applied.csv"\n'
                     "enabled = false\n")
    log = AsAppliedLog(tmp_path / "applied.csv")
    for k, channel in enumerate(["seed", "fert", "seed"]):
        log.record(AsAppliedRow((T0 + timedelta(seconds=k)).isoformat(), 126.63, 45.75,
                                channel, "x", 150.0, 149.0))
    assert export(cfg, tmp_path / "out") == 0
    err = capsys.readouterr().err
    assert "240 seed records and 2 as-applied rows" in err
    assert "left out 1 as-applied rows of channels that are not in the configuration" in err
    ((keys, records),) = logs(tmp_path / "out" / "TASKDATA").values()
    rates = [dict(r.values)[keys.index((0x0007, "DET-3"))] for r in records
             if keys.index((0x0007, "DET-3")) in dict(r.values)]
    assert rates == [14900, 14900]  # 149 kg/ha in mg/m²


@pytest.fixture
def full_disk(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Path | None]:
    """A 2 MiB tmpfs with its last bytes taken; None when the test already ran (and passed)
    in a mount namespace (tests/tiny_disk.py)."""
    from tests.tiny_disk import fill, may_mount, run_in_mount_namespace, tiny_tmpfs

    if not may_mount():
        run_in_mount_namespace(request)
        yield None
        return
    with tiny_tmpfs(tmp_path / "usb") as path:
        fill(path)
        yield path


@pytest.mark.parametrize("as_zip", [False, True], ids=["folder", "zip"])
def test_an_export_to_a_full_disk_fails_and_leaves_no_half_task(
    tmp_path: Path, full_disk: Path | None, as_zip: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    if full_disk is None:
        return
    cfg = make_store(tmp_path, drops(seconds=20))
    before = sorted(p.name for p in full_disk.iterdir())
    target = full_disk / "task.zip" if as_zip else full_disk
    assert export(cfg, target, *(["--zip"] if as_zip else [])) == 1
    assert "No space left on device" in capsys.readouterr().err
    assert sorted(p.name for p in full_disk.iterdir()) == before  # no TASKDATA, no temp


def test_a_damaged_as_applied_log_fails_naming_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = make_store(tmp_path, drops(), '[[channel]]\nname = "seed"\ntarget_rate_kg_ha = 150\n'
                     f'[prescription]\nas_applied_path = "{tmp_path}/applied.csv"\n'
                     "enabled = false\n")
    (tmp_path / "applied.csv").write_text(
        "time,lon,lat,channel,product,target_kg_ha,applied_kg_ha\n"
        "2026-05-02T06:00:00+00:00,126.63,45.75,seed,x,150,149\n"
        "2026-05-02T06:00:01+00:00,126.63,45.75,seed,x,lots,149\n")
    assert export(cfg, tmp_path / "out") == 1
    assert "applied.csv:3: not an as-applied row" in capsys.readouterr().err
    assert list((tmp_path / "out").iterdir()) == []
