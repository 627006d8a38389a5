"""ISO-XML TaskData prescriptions (``[prescription] path`` = a TASKDATA folder or zip): the
plans isoxml-js and the Python ``isoxml`` package write, and polygon zones as an FMIS writes
them, give each zone's mass per area in kg/ha; what sowgate cannot sow is refused with why."""

from __future__ import annotations

import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest

from gateway.metering.prescription import PrescriptionError, PrescriptionMap

TOOLS = Path(__file__).parents[2] / "isoxml_js"


def isoxml_js_grid(tmp_path: Path, ddi: str) -> Path:
    """isoxml-js rasterises two zones into a type 2 grid: the southern half 7000, the northern
    9000 (lat 48.100..48.102, lon 15.100..15.104), out of field 0."""
    node = shutil.which("node")
    assert node is not None and (TOOLS / "node_modules" / "isoxml").is_dir(), (
        "isoxml-js is not installed: run `make isoxml-js` (needs node and npm)")
    out = tmp_path / "plan.zip"
    subprocess.run([node, str(TOOLS / "make_grid.js"), str(out), ddi], check=True, timeout=120)
    return out


def test_an_isoxml_js_mass_grid_gives_kg_ha_where_the_cells_are(tmp_path: Path) -> None:
    plan = PrescriptionMap.load(isoxml_js_grid(tmp_path, "0006"), ["0006"])
    assert plan.rate_at(15.102, 48.1003, "0006", 150.0) == pytest.approx(70.0)  # 7000 mg/m²
    assert plan.rate_at(15.102, 48.1017, "0006", 150.0) == pytest.approx(90.0)
    # outside the grid: the task's out-of-field zone (0), not the channel's own rate
    assert plan.rate_at(15.2, 48.2, "0006", 150.0) == 0.0


def test_the_same_plan_unzipped_reads_the_same(tmp_path: Path) -> None:
    with zipfile.ZipFile(isoxml_js_grid(tmp_path, "0006")) as z:
        z.extractall(tmp_path / "stick")
    for path in (tmp_path / "stick", tmp_path / "stick" / "TASKDATA",
                 tmp_path / "stick" / "TASKDATA" / "TASKDATA.XML"):
        plan = PrescriptionMap.load(path, ["0006"])
        assert plan.rate_at(15.102, 48.1017, "0006", 150.0) == pytest.approx(90.0)


def test_a_seeds_per_area_plan_is_refused_with_the_reason(tmp_path: Path) -> None:
    with pytest.raises(PrescriptionError, match=r"seeds per area.*kg/ha"):
        PrescriptionMap.load(isoxml_js_grid(tmp_path, "000B"), ["000B"])


def test_a_type1_grid_written_by_the_python_isoxml_package(tmp_path: Path) -> None:
    import numpy as np
    from isoxml.converter.np_grid import from_numpy_array
    from isoxml.models.base import v4 as iso
    from isoxml.util.isoxml_io import isoxml_to_dir

    grid = iso.Grid(minimum_north_position=48.0, minimum_east_position=15.0,
                    cell_north_size=0.001, cell_east_size=0.001, maximum_column=3,
                    maximum_row=2, filename="GRD00001", type=iso.GridType.GridType1)
    zones = [
        iso.TreatmentZone(code=1, designator="low", process_data_variables=[
            iso.ProcessDataVariable(process_data_ddi=bytes.fromhex("0006"),
                                  process_data_value=12000, product_id_ref="PDT1")]),
        iso.TreatmentZone(code=2, designator="high", process_data_variables=[
            iso.ProcessDataVariable(process_data_ddi=bytes.fromhex("0006"),
                                  process_data_value=18000, product_id_ref="PDT1")]),
        iso.TreatmentZone(code=3, designator="default", process_data_variables=[
            iso.ProcessDataVariable(process_data_ddi=bytes.fromhex("0006"),
                                  process_data_value=15000, product_id_ref="PDT1")]),
    ]
    task = iso.Task(id="TSK1", status=iso.TaskStatus.Planned, treatment_zones=zones,
                    grids=[grid], default_treatment_zone_code=3)
    root = iso.Iso11783TaskData(
        management_software_manufacturer="test", management_software_version="1",
        data_transfer_origin=iso.Iso11783TaskDataDataTransferOrigin.FMIS,
        products=[iso.Product(id="PDT1", designator="wheat")], tasks=[task])
    codes = np.array([[1, 1, 2], [2, 2, 1]], dtype=np.uint8)  # row 0: the south
    folder = tmp_path / "TASKDATA"
    folder.mkdir()
    isoxml_to_dir(folder, root, {"GRD00001": from_numpy_array(codes, grid)})
    plan = PrescriptionMap.load(folder, ["wheat"])
    assert plan.rate_at(15.0005, 48.0005, "wheat", 1.0) == pytest.approx(120.0)
    assert plan.rate_at(15.0025, 48.0005, "wheat", 1.0) == pytest.approx(180.0)
    assert plan.rate_at(15.0005, 48.0015, "wheat", 1.0) == pytest.approx(180.0)
    assert plan.rate_at(15.0025, 48.0015, "wheat", 1.0) == pytest.approx(120.0)
    assert plan.rate_at(16.0, 49.0, "wheat", 1.0) == pytest.approx(150.0)  # the default zone


POLYGONS = """<?xml version="1.0" encoding="UTF-8"?>
<ISO11783_TaskData VersionMajor="4" VersionMinor="3" ManagementSoftwareManufacturer="FMIS"
    ManagementSoftwareVersion="1" DataTransferOrigin="1">
  <PDT A="PDT1" B="maize"/>
  <TSK A="TSK1" B="Sow maize VR zones" G="1" H="1">
    <TZN A="1" B="default"><PDV A="0006" B="2500" C="PDT1"/></TZN>
    <TZN A="3" B="high zone">
      <PLN A="2"><LSG A="1">
        <PNT A="2" C="48.1000" D="15.1000"/><PNT A="2" C="48.1000" D="15.1010"/>
        <PNT A="2" C="48.1010" D="15.1010"/><PNT A="2" C="48.1010" D="15.1000"/>
      </LSG></PLN>
      <PDV A="0006" B="3200" C="PDT1"/>
    </TZN>
  </TSK>
</ISO11783_TaskData>
"""


def test_polygon_zones_with_a_default_zone(tmp_path: Path) -> None:
    (tmp_path / "TASKDATA.XML").write_text(POLYGONS)
    plan = PrescriptionMap.load(tmp_path, ["maize"])
    assert plan.rate_at(15.1005, 48.1005, "maize", 99.0) == pytest.approx(32.0)
    assert plan.rate_at(15.2, 48.2, "maize", 99.0) == pytest.approx(25.0)


@pytest.mark.parametrize(
    ("text", "attribute", "message"),
    [
        (POLYGONS, "wheat", "no mass-per-area rate 'wheat'.*maize"),
        (POLYGONS.replace('<TSK A="TSK1"', '<TSK A="TSK2" G="1"><TZN A="1"><PLN A="2"><LSG A="1">'
                          '<PNT A="2" C="48" D="15"/><PNT A="2" C="48" D="15.1"/>'
                          '<PNT A="2" C="48.1" D="15"/></LSG></PLN></TZN></TSK><TSK A="TSK1"'),
         "maize", "2 tasks with a prescription"),
        (POLYGONS.replace("<PLN A=\"2\">", "<PLN A=\"1\">"), "maize", "no polygon"),
        ("<ISO11783_TaskData", "maize", "not XML"),
        (POLYGONS.replace('B="3200"', 'B="lots"'), "maize", "not a DDI and a value"),
    ],
)
def test_plans_sowgate_cannot_use_are_refused_with_why(
    tmp_path: Path, text: str, attribute: str, message: str
) -> None:
    (tmp_path / "TASKDATA.XML").write_text(text)
    with pytest.raises(PrescriptionError, match=message):
        PrescriptionMap.load(tmp_path, [attribute])


def test_a_grid_binary_of_the_wrong_size_is_refused(tmp_path: Path) -> None:
    with zipfile.ZipFile(isoxml_js_grid(tmp_path, "0006")) as z:
        z.extractall(tmp_path / "stick")
    grd = next((tmp_path / "stick" / "TASKDATA").glob("GRD*"))
    grd.write_bytes(grd.read_bytes()[:-3])
    with pytest.raises(PrescriptionError, match="GRD00001: grid binary of"):
        PrescriptionMap.load(tmp_path / "stick", ["0006"])


LOST = POLYGONS.replace('<TSK A="TSK1" B="Sow maize VR zones" G="1" H="1">',
                        '<TSK A="TSK1" B="Sow maize VR zones" G="1" H="1" I="4">').replace(
    "</TSK>", '<TZN A="4" B="position lost"><PDV A="0006" B="2800" C="PDT1"/></TZN></TSK>')


def test_the_position_lost_zone_is_the_rate_without_a_position(tmp_path: Path) -> None:
    from gateway.config import parse_config
    from gateway.metering.channels import MeteringComponent

    (tmp_path / "TASKDATA.XML").write_text(LOST)
    plan = PrescriptionMap.load(tmp_path, ["maize"])
    assert plan.position_lost == {"maize": pytest.approx(28.0)}
    settings = parse_config({
        "channel": [{"name": "seed", "product": "maize", "target_rate_kg_ha": 30.0,
                     "node_id": 1, "prescription_attribute": "maize"}],
    })
    metering = MeteringComponent(settings, lambda: 5.0, lambda: True, lambda: None,
                                 lambda _alarm: None, prescription=plan)
    (ch,) = metering.channels
    assert metering.target_rate(ch, None) == pytest.approx(28.0)  # not the channel's 30
    (tmp_path / "TASKDATA.XML").write_text(POLYGONS)  # a plan without one: the channel's
    metering.prescription = PrescriptionMap.load(tmp_path, ["maize"])
    assert metering.target_rate(ch, None) == 30.0
