"""ISO-XML TaskData prescriptions: a task's treatment zones as rate polygons.

An FMIS hands a variable-rate sowing plan to a terminal as a ``TASKDATA`` folder (or a zip of
it): a ``TSK`` whose treatment zones (``TZN``) carry process data values (``PDV``: a DDI, a
value in that DDI's unit, the product). The zones are either polygons (``PLN A="2"``) or the
cells of a grid (``GRD``, type 1: a zone code per cell; type 2: the values per cell, in the
order of the PDVs of the zone ``GRD J``). ``PrescriptionMap.load`` reads them through here:

- every mass-per-area PDV (DDI 0x0006, Setpoint Mass Per Area Application Rate, mg/m²)
  becomes a rate in kg/ha (÷ 100) under the product's name (``PDT B``) and under ``"0006"``;
  a channel takes it by ``[[channel]] prescription_attribute = "<product>"``;
- the task's default zone (``TSK H``) and out-of-field zone (``TSK J``) give the rate outside
  every zone (out-of-field first: a position outside the zones and the grid is outside the
  field the plan covers), its position-lost zone (``TSK I``) the rate while there is no
  position; without them the channel's ``target_rate_kg_ha`` applies, as for a GeoJSON map;
- a count-per-area plan (0x000B, seeds per area) is refused with the reason: sowgate's
  channels meter mass (kg/ha), and seeds/ha need the lot's thousand-kernel weight to become
  that, which the plan does not carry.

Refused with the reason: more than one task with zones (the file must say which to sow),
grids that do not match their ``GRD`` (size, type, zone), zones without a polygon or cell.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway.core.errors import GatewayError
from protocol.isoxml_grid import GridError, GridGeometry, decode_type1, decode_type2

MASS_PER_AREA = 0x0006  # Setpoint Mass Per Area Application Rate, mg/m²
COUNT_PER_AREA = 0x000B  # Setpoint Count Per Area Application Rate, 0.001 /m²
MG_M2_PER_KG_HA = 100.0
MAX_GRID_CELLS = 1_000_000


class TaskDataError(GatewayError):
    """A TaskData prescription sowgate cannot use; the message says which element and why."""


@dataclass
class TaskDataMap:
    """What ``PrescriptionMap`` is built from: (GeoJSON geometry, rates) pairs and the rates
    outside every zone."""

    features: list[tuple[dict[str, Any], dict[str, float]]] = field(default_factory=list)
    outside: dict[str, float] = field(default_factory=dict)
    position_lost: dict[str, float] = field(default_factory=dict)


def is_taskdata(path: Path) -> bool:
    """A folder, a zip, or a file named TASKDATA.XML."""
    return path.is_dir() or path.suffix.lower() == ".zip" or path.name.upper() == "TASKDATA.XML"


def read_taskdata(path: Path) -> TaskDataMap:
    """The prescription of the TaskData at ``path``; ``TaskDataError`` says what is wrong."""
    source = str(path)
    read = _reader(path)
    try:
        root = ET.fromstring(read("TASKDATA.XML"))
    except ET.ParseError as exc:
        raise TaskDataError(f"{source}: TASKDATA.XML is not XML: {exc}") from None
    if root.tag != "ISO11783_TaskData":
        raise TaskDataError(f"{source}: root <{root.tag}> is not ISO11783_TaskData")
    products = {p.get("A", ""): p.get("B", "") for p in root.iter("PDT")}
    tasks = [t for t in root.findall("TSK")
             if t.find("GRD") is not None or t.find("TZN/PLN") is not None]
    if not tasks:
        raise TaskDataError(f"{source}: no task with treatment zones (polygons) or a grid")
    if len(tasks) > 1:
        names = ", ".join(f"{t.get('A')} {t.get('B', '')!r}" for t in tasks)
        raise TaskDataError(
            f"{source}: {len(tasks)} tasks with a prescription ({names}); export the one to "
            "sow on its own"
        )
    task = tasks[0]
    where = f"{source}: {task.get('A')}"
    zones = {z.get("A", ""): z for z in task.findall("TZN")}
    rates = {code: _zone_rates(z, products, f"{where} TZN {code}") for code, z in zones.items()}
    out = TaskDataMap()
    for code_attr in ("H", "J"):  # default, then out-of-field: the latter wins outside
        code = task.get(code_attr)
        if code is not None and code in rates:
            out.outside.update(rates[code])
    lost = task.get("I")
    if lost is not None and lost in rates:
        out.position_lost.update(rates[lost])
    for code, zone in zones.items():
        for pln in zone.findall("PLN"):
            if pln.get("A") != "2":
                continue
            out.features.append((_polygon(pln, f"{where} TZN {code}"), rates[code]))
    grd = task.find("GRD")
    if grd is not None:
        _grid(grd, zones, rates, products, read, where, out, task.get("J"))
    ddis = {_pdv(p, where)[0] for p in task.iter("PDV")}
    if COUNT_PER_AREA in ddis and MASS_PER_AREA not in ddis:
        raise TaskDataError(
            f"{where}: the plan gives seeds per area (DDI 000B); sowgate's channels meter "
            "kg/ha and the plan gives no seed weight to convert it: export it as mass per "
            "area (DDI 0006)"
        )
    if not out.features:
        raise TaskDataError(f"{where}: its zones have no polygon (PLN A=\"2\") and no grid cell")
    return out


def _reader(path: Path) -> Callable[[str], bytes]:
    """The TaskData's files by name, whatever their letter case (terminals and FMIS differ)."""
    if not path.exists():
        raise TaskDataError(f"{path}: prescription not found")
    if path.suffix.lower() == ".zip":
        try:
            z = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, OSError) as exc:
            raise TaskDataError(f"{path}: not a zip file ({exc})") from None
        with z:
            names = {n.rsplit("/", 1)[-1].upper(): n for n in z.namelist() if not n.endswith("/")}
            files = {k: z.read(v) for k, v in names.items()}

        def from_zip(name: str) -> bytes:
            try:
                return files[name.upper()]
            except KeyError:
                raise TaskDataError(f"{path}: no {name} in the zip") from None

        return from_zip
    folder = path.parent if path.is_file() else path
    if not path.is_file() and not any(p.name.upper() == "TASKDATA.XML" for p in folder.iterdir()):
        inner = [p for p in folder.iterdir() if p.is_dir() and p.name.upper() == "TASKDATA"]
        folder = inner[0] if inner else folder
    by_name = {p.name.upper(): p for p in folder.iterdir() if p.is_file()}

    def from_folder(name: str) -> bytes:
        p = by_name.get(name.upper())
        if p is None:
            raise TaskDataError(f"{folder}: no {name}")
        return p.read_bytes()

    return from_folder


def _zone_rates(zone: ET.Element, products: Mapping[str, str], where: str) -> dict[str, float]:
    rates: dict[str, float] = {}
    for pdv in zone.findall("PDV"):
        ddi, value = _pdv(pdv, where)
        if ddi == MASS_PER_AREA:
            kg_ha = value / MG_M2_PER_KG_HA
            if kg_ha < 0:
                raise TaskDataError(f"{where}: mass per area {value} mg/m² is negative")
            rates["0006"] = kg_ha
            product = products.get(pdv.get("C", ""))
            if product:
                rates[product] = kg_ha
    return rates


def _pdv(pdv: ET.Element, where: str) -> tuple[int, int]:
    try:
        return int(pdv.get("A", ""), 16), int(pdv.get("B", ""))
    except ValueError:
        raise TaskDataError(
            f"{where}: PDV A={pdv.get('A')!r} B={pdv.get('B')!r} is not a DDI and a value"
        ) from None


def _polygon(pln: ET.Element, where: str) -> dict[str, Any]:
    rings: list[list[list[float]]] = []
    for lsg in pln.findall("LSG"):
        ring = []
        for pnt in lsg.findall("PNT"):
            try:
                ring.append([float(pnt.get("D", "")), float(pnt.get("C", ""))])
            except ValueError:
                raise TaskDataError(f"{where}: a PNT without a numeric C/D") from None
        if len(ring) < 3:
            raise TaskDataError(f"{where}: a polygon ring of {len(ring)} points")
        if ring[0] != ring[-1]:
            ring.append(ring[0])  # ISO-XML v3 rings are open; v4 closes them
        if lsg.get("A") == "1":
            rings.insert(0, ring)  # the exterior first
        else:
            rings.append(ring)
    if not rings:
        raise TaskDataError(f"{where}: a polygon without a line string")
    return {"type": "Polygon", "coordinates": rings}


def _grid(
    grd: ET.Element, zones: Mapping[str, ET.Element], rates: Mapping[str, dict[str, float]],
    products: Mapping[str, str], read: Callable[[str], bytes], where: str, out: TaskDataMap,
    out_of_field: str | None,
) -> None:
    try:
        geometry = GridGeometry(
            float(grd.get("A", "")), float(grd.get("B", "")), float(grd.get("C", "")),
            float(grd.get("D", "")), int(grd.get("E", "")), int(grd.get("F", "")),
        )
    except ValueError:
        raise TaskDataError(f"{where}: GRD A..F are not numbers") from None
    except GridError as exc:
        raise TaskDataError(f"{where}: GRD: {exc}") from None
    if geometry.cells > MAX_GRID_CELLS:
        raise TaskDataError(f"{where}: a grid of {geometry.cells} cells (at most "
                            f"{MAX_GRID_CELLS})")
    data = read(f"{grd.get('G')}.BIN")
    kind = grd.get("I")
    try:
        if kind == "1":
            cells: list[list[dict[str, float] | None]] = [
                [None if str(code) == out_of_field else rates.get(str(code)) for code in row]
                for row in decode_type1(data, geometry)
            ]
        elif kind == "2":
            layout = zones.get(grd.get("J", ""))
            if layout is None:
                raise TaskDataError(f"{where}: GRD J={grd.get('J')!r} names no TZN")
            pdvs = [(_pdv(p, where)[0], products.get(p.get("C", ""))) for p in
                    layout.findall("PDV")]
            values = decode_type2(data, geometry, len(pdvs))
            cells = [[_cell_rates(cell, pdvs) for cell in row] for row in values]
        else:
            raise TaskDataError(f"{where}: GRD I={kind!r} is not grid type 1 or 2")
    except (GridError, ValueError) as exc:  # FrameError is a ValueError
        raise TaskDataError(f"{where}: {grd.get('G')}: {exc}") from None
    for r, row in enumerate(cells):  # a run of equal cells along a row is one rectangle
        c = 0
        while c < geometry.columns:
            here = row[c]
            end = c + 1
            while end < geometry.columns and row[end] == here:
                end += 1
            if here:
                west, south, _, north = geometry.cell_bounds(r, c)
                east = geometry.cell_bounds(r, end - 1)[2]
                ring = [[west, south], [east, south], [east, north], [west, north],
                        [west, south]]
                out.features.append(({"type": "Polygon", "coordinates": [ring]}, here))
            c = end


def _cell_rates(cell: tuple[int, ...], pdvs: list[tuple[int, str | None]]) -> dict[str, float]:
    rates: dict[str, float] = {}
    for value, (ddi, product) in zip(cell, pdvs, strict=True):
        if ddi == MASS_PER_AREA:
            rates["0006"] = value / MG_M2_PER_KG_HA
            if product:
                rates[product] = value / MG_M2_PER_KG_HA
    return rates


def count_per_area_products(path: Path) -> list[str]:
    """The products (or "000B") a count-per-area plan gives, for the refusal's message."""
    try:
        root = ET.fromstring(_reader(path)("TASKDATA.XML"))
    except (TaskDataError, ET.ParseError):
        return []
    products = {p.get("A", ""): p.get("B", "") for p in root.iter("PDT")}
    return sorted({products.get(p.get("C", ""), "000B") or "000B" for p in root.iter("PDV")
                   if p.get("A", "").upper() == f"{COUNT_PER_AREA:04X}"})
