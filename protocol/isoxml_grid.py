"""ISO 11783-10 grids (``GRDnnnnn.BIN``): prescription maps as cells, pure and sans-I/O.

A task's ``GRD`` element places a regular lon/lat grid: ``A``/``B`` the south-west corner
(minimum north and east, WGS84 degrees), ``C``/``D`` the cell size in degrees, ``E`` columns
and ``F`` rows. The binary holds the cells row by row, **row 0 at the south** and rows running
north, columns running east (isoxml-js ``Grid.toGeoJSON``, isoxml-py ``np_grid``):

- type 1: one uint8 per cell, the code of the ``TZN`` (treatment zone) whose ``PDV`` values
  apply there;
- type 2: ``n`` little-endian int32 per cell, one for each ``PDV`` of the grid's treatment zone
  (``GRD J``), in the DDI's unit (0x000B: 0.001 seeds/m²; 0x0006: mg/m²).

This module turns bytes into cells and back and finds the cell of a position; reading the XML
and converting units is the caller's.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass

from protocol.errors import FrameError, ProtocolError


class GridError(ProtocolError):
    """A grid that cannot be read or written: wrong size, bad geometry, a value out of range."""


@dataclass(frozen=True, slots=True)
class GridGeometry:
    """``GRD`` A..F: the south-west corner, the cell size (degrees) and the cell counts."""

    min_north: float
    min_east: float
    cell_north: float
    cell_east: float
    columns: int
    rows: int

    def __post_init__(self) -> None:
        if not (self.cell_north > 0 and self.cell_east > 0):
            raise GridError(
                f"grid cell size must be > 0 degrees, got {self.cell_north} x {self.cell_east}"
            )
        if not (self.columns >= 1 and self.rows >= 1):
            raise GridError(f"grid needs >= 1 column and row, got {self.columns} x {self.rows}")
        north = self.min_north + self.rows * self.cell_north
        east = self.min_east + self.columns * self.cell_east
        if not (-90 <= self.min_north < north <= 90 and -180 <= self.min_east < east <= 180):
            raise GridError(
                f"grid ({self.min_north}, {self.min_east}) + {self.rows} x {self.cell_north} "
                f"by {self.columns} x {self.cell_east} degrees is not on the globe"
            )

    @property
    def cells(self) -> int:
        return self.rows * self.columns

    def cell_of(self, lat: float, lon: float) -> tuple[int, int] | None:
        """(row, column) of the cell holding the position, None outside the grid. A point on
        a cell border belongs to the cell north/east of it (the last row and column keep
        their outer border)."""
        row = math.floor((lat - self.min_north) / self.cell_north)
        col = math.floor((lon - self.min_east) / self.cell_east)
        if row == self.rows and lat <= self.min_north + self.rows * self.cell_north:
            row -= 1
        if col == self.columns and lon <= self.min_east + self.columns * self.cell_east:
            col -= 1
        if 0 <= row < self.rows and 0 <= col < self.columns:
            return row, col
        return None

    def cell_bounds(self, row: int, col: int) -> tuple[float, float, float, float]:
        """(west, south, east, north) of a cell, degrees."""
        south = self.min_north + row * self.cell_north
        west = self.min_east + col * self.cell_east
        return west, south, west + self.cell_east, south + self.cell_north


def decode_type1(data: bytes, geometry: GridGeometry) -> list[bytes]:
    """The treatment zone codes, one ``bytes`` of ``columns`` codes per row, south first."""
    _check_size(data, geometry.cells, "type 1 (1 byte a cell)")
    c = geometry.columns
    return [data[r * c:(r + 1) * c] for r in range(geometry.rows)]


def encode_type1(codes: Sequence[Sequence[int]], geometry: GridGeometry) -> bytes:
    _check_shape(codes, geometry)
    out = bytearray()
    for r, row in enumerate(codes):
        for c, code in enumerate(row):
            if not 0 <= code <= 255:
                raise GridError(f"type 1 cell ({r}, {c}): zone code {code} is not 0..255")
            out.append(code)
    return bytes(out)


def decode_type2(
    data: bytes, geometry: GridGeometry, values_per_cell: int
) -> list[list[tuple[int, ...]]]:
    """The cells' values: ``[row][column] -> (value per PDV)``, south row first."""
    if values_per_cell < 1:
        raise GridError(f"a type 2 grid needs >= 1 value a cell, got {values_per_cell}")
    _check_size(data, geometry.cells * values_per_cell * 4,
                f"type 2 ({values_per_cell} int32 a cell)")
    flat = struct.unpack(f"<{geometry.cells * values_per_cell}i", data)
    n, c = values_per_cell, geometry.columns
    return [
        [tuple(flat[(r * c + col) * n:(r * c + col + 1) * n]) for col in range(c)]
        for r in range(geometry.rows)
    ]


def encode_type2(
    values: Sequence[Sequence[Sequence[int]]], geometry: GridGeometry, values_per_cell: int
) -> bytes:
    _check_shape(values, geometry)
    flat: list[int] = []
    for r, row in enumerate(values):
        for c, cell in enumerate(row):
            if len(cell) != values_per_cell:
                raise GridError(
                    f"type 2 cell ({r}, {c}) has {len(cell)} values, expected {values_per_cell}"
                )
            for v in cell:
                if not -(2**31) <= v < 2**31:
                    raise GridError(f"type 2 cell ({r}, {c}): {v} does not fit an int32")
            flat.extend(cell)
    return struct.pack(f"<{len(flat)}i", *flat)


def _check_size(data: bytes, expected: int, what: str) -> None:
    if len(data) != expected:
        raise FrameError(
            f"grid binary of {len(data)} bytes, a {what} grid of these rows and columns has "
            f"{expected}"
        )


def _check_shape(cells: Sequence[Sequence[object]], geometry: GridGeometry) -> None:
    if len(cells) != geometry.rows or any(len(row) != geometry.columns for row in cells):
        raise GridError(
            f"cells must be {geometry.rows} rows of {geometry.columns} columns"
        )
