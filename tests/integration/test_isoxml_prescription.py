"""An ISO-XML TaskData prescription (polygon zones, or a type 2 grid) drives a CAN channel's
target rate from the GNSS position, end to end, as a GeoJSON map does
(tests/integration/test_prescription_metering.py): the same two zones, 150 kg/ha up to 12 m
north of the start and 300 kg/ha beyond, written as an FMIS writes them."""

from __future__ import annotations

import asyncio
import contextlib
import uuid
from pathlib import Path

import pymap3d
import pytest

from drivers.can_bus import CanBus
from protocol.isoxml_grid import GridGeometry, encode_type2
from simulator.can_pid import MeteringControllerSim, MeterPlant
from simulator.machine import ORIGIN_LAT, ORIGIN_LON, SimulatedMachine
from simulator.plant import Drive, Leg
from tests.integration.conftest import running

HEAD = """<?xml version="1.0" encoding="UTF-8"?>
<ISO11783_TaskData VersionMajor="4" VersionMinor="3" ManagementSoftwareManufacturer="FMIS"
    ManagementSoftwareVersion="1" DataTransferOrigin="1">
  <PDT A="PDT1" B="wheat"/>
"""


def _latlon(east: float, north: float) -> tuple[float, float]:
    lat, lon, _ = pymap3d.enu2geodetic(east, north, 0.0, ORIGIN_LAT, ORIGIN_LON, 100.0)
    return float(lat), float(lon)


def _zone(code: int, north_from: float, north_to: float, mg_m2: int) -> str:
    corners = [(-50.0, north_from), (50.0, north_from), (50.0, north_to), (-50.0, north_to)]
    points = "".join(f'<PNT A="2" C="{lat:.9f}" D="{lon:.9f}"/>'
                     for lat, lon in (_latlon(e, n) for e, n in corners))
    return (f'<TZN A="{code}"><PLN A="2"><LSG A="1">{points}</LSG></PLN>'
            f'<PDV A="0006" B="{mg_m2}" C="PDT1"/></TZN>')


def polygon_plan(folder: Path) -> Path:
    (folder / "TASKDATA.XML").write_text(
        HEAD + '<TSK A="TSK1" G="1">' + _zone(1, -20.0, 12.0, 15000)
        + _zone(2, 12.0, 200.0, 30000) + "</TSK></ISO11783_TaskData>\n")
    return folder


def grid_plan(folder: Path) -> Path:
    """A type 2 grid: one column 100 m wide, rows of 2 m from 20 m south of the start."""
    south, west = _latlon(-50.0, -20.0)
    north, east = _latlon(50.0, 200.0)
    rows = 110
    g = GridGeometry(south, west, (north - south) / rows, east - west, columns=1, rows=rows)
    values = [[(15000 if -20.0 + 2.0 * r < 12.0 else 30000,)] for r in range(rows)]
    (folder / "GRD00001.BIN").write_bytes(encode_type2(values, g, 1))
    (folder / "TASKDATA.XML").write_text(
        HEAD + '<TSK A="TSK1" G="1" H="1"><TZN A="1"><PDV A="0006" B="22500" C="PDT1"/></TZN>'
        f'<GRD A="{south:.9f}" B="{west:.9f}" C="{g.cell_north:.12f}" D="{g.cell_east:.12f}" '
        f'E="1" F="{rows}" G="GRD00001" H="{rows * 4}" I="2" J="1"/></TSK>'
        "</ISO11783_TaskData>\n")
    return folder


@pytest.mark.parametrize("make_plan", [polygon_plan, grid_plan], ids=["polygons", "grid"])
async def test_the_channel_follows_the_taskdata_zones(tmp_path: Path, make_plan: object) -> None:
    assert callable(make_plan)
    folder = tmp_path / "TASKDATA"
    folder.mkdir()
    plan = make_plan(folder)
    can_channel = f"rx-{uuid.uuid4().hex[:8]}"
    config = {
        "control": {"start_working": True},
        "can": {"enabled": True, "interface": "virtual", "channel": can_channel},
        "channel": [{"name": "seed", "product": "wheat", "target_rate_kg_ha": 225.0,
                     "node_id": 1, "grams_per_rev": 11.2, "prescription_attribute": "wheat"}],
        "prescription": {"enabled": True, "path": str(plan), "lookahead_s": 0.5},
    }
    drive = Drive(legs=[Leg(1.0, 0.0), Leg(120.0, 7.0)], dt=0.02)
    async with CanBus("virtual", can_channel) as bus:
        sim_task = asyncio.create_task(
            MeteringControllerSim(bus, {1: MeterPlant(grams_per_rev=11.2)}).run(), name="pid")
        try:
            machine = SimulatedMachine(drive=drive, with_gnss=True)
            async with running(tmp_path, machine, **config) as rig:

                def target() -> float | None:
                    return rig.daemon.parts.metering.status().channels["seed"].target_rate_kg_ha

                await rig.until(lambda: target() == 150.0, timeout=10.0, what="zone A rate")
                await rig.until(lambda: target() == 300.0, timeout=15.0, what="zone B rate")
                assert machine.pose().north > 8.0  # switched near the border, not at the start
                assert not [a for a in rig.daemon.alarms.active if a.code.startswith("presc")]
        finally:
            sim_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sim_task
