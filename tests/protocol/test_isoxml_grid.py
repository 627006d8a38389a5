"""ISO 11783-10 grid binaries: cells round-trip, row 0 is the south, sizes are checked, and
the bytes are the ones the Python ``isoxml`` package reads and writes."""

from __future__ import annotations

import shutil
import struct
import subprocess
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.errors import FrameError
from protocol.isoxml_grid import (
    GridError,
    GridGeometry,
    decode_type1,
    decode_type2,
    encode_type1,
    encode_type2,
)

INT32 = st.integers(-(2**31), 2**31 - 1)
TOOLS = Path(__file__).parents[1] / "isoxml_js"


@st.composite
def geometries(draw: st.DrawFn) -> GridGeometry:
    return GridGeometry(
        draw(st.floats(-60, 60)), draw(st.floats(-170, 170)),
        draw(st.floats(1e-6, 0.01)), draw(st.floats(1e-6, 0.01)),
        draw(st.integers(1, 12)), draw(st.integers(1, 12)),
    )


@given(geometries(), st.data())
def test_type1_codes_round_trip(g: GridGeometry, data: st.DataObject) -> None:
    codes = [[data.draw(st.integers(0, 255)) for _ in range(g.columns)] for _ in range(g.rows)]
    decoded = decode_type1(encode_type1(codes, g), g)
    assert [list(row) for row in decoded] == codes


@given(geometries(), st.integers(1, 3), st.data())
def test_type2_values_round_trip(g: GridGeometry, n: int, data: st.DataObject) -> None:
    values = [[tuple(data.draw(INT32) for _ in range(n)) for _ in range(g.columns)]
              for _ in range(g.rows)]
    assert decode_type2(encode_type2(values, g, n), g, n) == values


@given(geometries(), st.data())
def test_the_centre_of_each_cell_is_in_that_cell(g: GridGeometry, data: st.DataObject) -> None:
    row = data.draw(st.integers(0, g.rows - 1))
    col = data.draw(st.integers(0, g.columns - 1))
    west, south, east, north = g.cell_bounds(row, col)
    assert g.cell_of((south + north) / 2, (west + east) / 2) == (row, col)


def test_row_zero_is_the_south_and_columns_run_east() -> None:
    g = GridGeometry(48.0, 15.0, 0.001, 0.002, columns=3, rows=2)
    data = struct.pack("<6i", 10, 11, 12, 20, 21, 22)
    cells = decode_type2(data, g, 1)
    assert cells[0] == [(10,), (11,), (12,)]  # the southern row first
    assert g.cell_of(48.0005, 15.0001) == (0, 0)
    assert g.cell_of(48.0015, 15.0055) == (1, 2)
    assert g.cell_of(48.002, 15.006) == (1, 2)  # the north-east corner is still in
    assert g.cell_of(47.9999, 15.001) is None
    assert g.cell_of(48.0021, 15.001) is None
    assert g.cell_of(48.001, 15.0061) is None


def test_a_binary_of_the_wrong_size_is_refused() -> None:
    g = GridGeometry(48.0, 15.0, 0.001, 0.001, columns=4, rows=3)
    with pytest.raises(FrameError, match=r"47 bytes.*has 48"):
        decode_type2(bytes(47), g, 1)
    with pytest.raises(FrameError, match=r"13 bytes.*has 12"):
        decode_type1(bytes(13), g)
    with pytest.raises(GridError, match=">= 1 value"):
        decode_type2(b"", g, 0)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((48.0, 15.0, 0.0, 0.001, 4, 3), "cell size"),
        ((48.0, 15.0, 0.001, 0.001, 0, 3), ">= 1 column"),
        ((89.99, 15.0, 0.01, 0.001, 4, 3), "not on the globe"),
    ],
)
def test_impossible_geometry_is_refused(args: tuple[float, float, float, float, int, int],
                                        message: str) -> None:
    with pytest.raises(GridError, match=message):
        GridGeometry(*args)


def test_cells_of_the_wrong_shape_or_range_are_refused() -> None:
    g = GridGeometry(48.0, 15.0, 0.001, 0.001, columns=2, rows=1)
    with pytest.raises(GridError, match="1 rows of 2 columns"):
        encode_type1([[1]], g)
    with pytest.raises(GridError, match="zone code 256"):
        encode_type1([[1, 256]], g)
    with pytest.raises(GridError, match="2 values, expected 1"):
        encode_type2([[(1,), (1, 2)]], g, 1)
    with pytest.raises(GridError, match="does not fit an int32"):
        encode_type2([[(1,), (2**31,)]], g, 1)


def test_the_python_isoxml_package_reads_and_writes_the_same_bytes() -> None:
    import numpy as np
    from isoxml.converter.np_grid import from_numpy_array, to_numpy_array
    from isoxml.models.base import v4 as iso

    g = GridGeometry(48.12674, 15.14615, 0.0001, 0.0001, columns=4, rows=3)
    grd2 = iso.Grid(minimum_north_position=48.12674, minimum_east_position=15.14615,
                    cell_north_size=0.0001, cell_east_size=0.0001, maximum_column=4,
                    maximum_row=3, filename="GRD00001", type=iso.GridType.GridType2,
                    treatment_zone_code=4)
    values = [[(7000 + 100 * (4 * r + c),) for c in range(4)] for r in range(3)]
    ours = encode_type2(values, g, 1)
    theirs = to_numpy_array(ours, grd2)
    assert theirs.shape == (3, 4)
    assert theirs[0, 0] == 7000 and theirs[2, 3] == 8100  # row 0, column 0 first
    assert from_numpy_array(np.array(theirs, dtype=np.int32), grd2) == ours
    grd1 = iso.Grid(minimum_north_position=48.12674, minimum_east_position=15.14615,
                    cell_north_size=0.0001, cell_east_size=0.0001, maximum_column=4,
                    maximum_row=3, filename="GRD00002", type=iso.GridType.GridType1)
    codes = [[(r + c) % 3 + 1 for c in range(4)] for r in range(3)]
    assert from_numpy_array(np.array(codes, dtype=np.uint8), grd1) == encode_type1(codes, g)


def test_a_grid_isoxml_js_made_from_geojson_reads_south_row_first(tmp_path: Path) -> None:
    """isoxml-js (an independent writer) rasterises two zones, the southern half at 7000 and
    the northern at 9000 (0.001 seeds/m²); our codec finds each at its place."""
    node = shutil.which("node")
    assert node is not None and (TOOLS / "node_modules" / "isoxml").is_dir(), (
        "isoxml-js is not installed: run `make isoxml-js` (needs node and npm)")
    out = tmp_path / "grid.zip"
    subprocess.run([node, str(TOOLS / "make_grid.js"), str(out)], check=True, timeout=120)
    with zipfile.ZipFile(out) as z:
        root = ET.fromstring(z.read("TASKDATA/TASKDATA.XML"))
        grd = root.find("TSK/GRD")
        assert grd is not None and grd.get("I") == "2"
        g = GridGeometry(float(grd.get("A", "")), float(grd.get("B", "")),
                         float(grd.get("C", "")), float(grd.get("D", "")),
                         int(grd.get("E", "")), int(grd.get("F", "")))
        cells = decode_type2(z.read(f"TASKDATA/{grd.get('G')}.bin"), g, 1)
    assert int(grd.get("H", "")) == g.cells * 4
    for lat, lon, rate in ((48.1003, 15.1020, 7000), (48.1017, 15.1020, 9000)):
        cell = g.cell_of(lat, lon)
        assert cell is not None
        assert cells[cell[0]][cell[1]] == (rate,), (lat, lon)
    assert cells[0][g.columns // 2] == (7000,) and cells[-1][g.columns // 2] == (9000,)
