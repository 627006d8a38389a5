"""This seeder as an ISO 11783-10 device (``DVC``), and the DDIs its time log uses.

A time log names each value by a DDI (what it is, from the ISO 11783-11 data dictionary) and a
device element (``DET``: which part of the machine it is of). sowgate's device is:

- ``DET-1`` the seeder (type 1, device): actual work state, actual speed, total area;
- ``DET-2`` the seed boom (type 2, function): actual working width, the condensed work states
  of the rows (16 rows a DDI) and, with ``positioning.target_spacing_m``, the setpoint count
  per area and spacing;
- one function element per ``[[channel]]`` (a metering unit): setpoint and actual mass per
  area from the as-applied log;
- one section element (type 4) per row, under the boom, with its geometry as properties
  (``DPT`` offset X/Y and width) and its per-seed values: actual spacing, actual count per
  area, seeds counted, and the ISO 7256-1 quality sowgate computes (singulation, skips,
  multiples, CV: the "Average ..." DDIs 416..424, over the export so far).

Every DDI used is in ``DDIS`` with its data-dictionary name and unit, and a test checks them
against the dictionary as the ``isoxml`` package ships it (docs/isoxml.md has the table).
The XML is written with ``xml.etree``: the device is a fixed shape, and the typed models of
the ``isoxml`` package would add numpy, shapely and xsdata to the cab box for it.
"""

from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from decimal import Decimal

from gateway.config import Settings

CONDENSED_ROWS = 16  # rows (sections) per condensed work state DDI, 2 bits each


@dataclass(frozen=True, slots=True)
class Ddi:
    number: int
    name: str  # as in the ISO 11783-11 data dictionary (isobus.net)
    unit: str  # the unit of one count of the logged integer


# The ISO 11783-11 entries sowgate logs (names and units as the dictionary has them).
SETPOINT_MASS_PER_AREA = Ddi(0x0006, "Setpoint Mass Per Area Application Rate", "mg/m²")
ACTUAL_MASS_PER_AREA = Ddi(0x0007, "Actual Mass Per Area Application Rate", "mg/m²")
SETPOINT_COUNT_PER_AREA = Ddi(0x000B, "Setpoint Count Per Area Application Rate", "0.001 /m²")
ACTUAL_COUNT_PER_AREA = Ddi(0x000C, "Actual Count Per Area Application Rate", "0.001 /m²")
SETPOINT_SPACING = Ddi(0x0010, "Setpoint Spacing Application Rate", "mm")
ACTUAL_SPACING = Ddi(0x0011, "Actual Spacing Application Rate", "mm")
ACTUAL_WORKING_WIDTH = Ddi(0x0043, "Actual Working Width", "mm")
TOTAL_COUNT = Ddi(0x0052, "Application Total Count", "#")
TOTAL_AREA = Ddi(0x0074, "Total Area", "m²")
OFFSET_X = Ddi(0x0086, "Device Element Offset X", "mm")
OFFSET_Y = Ddi(0x0087, "Device Element Offset Y", "mm")
ACTUAL_WORK_STATE = Ddi(0x008D, "Actual Work State", "n.a.")
CONDENSED_WORK_STATE_FIRST = 0x00A1  # "Actual Condensed Work State (1-16)" .. (241-256) 0x00B0
ACTUAL_SPEED = Ddi(0x018D, "Actual Speed", "mm/s")
AVERAGE_SINGULATION = Ddi(0x01A0, "Average Seed Singulation Percentage", "ppm")
AVERAGE_SKIP = Ddi(0x01A2, "Average Seed Skip Percentage", "ppm")
AVERAGE_MULTIPLE = Ddi(0x01A4, "Average Seed Multiple Percentage", "ppm")
AVERAGE_CV = Ddi(0x01A8, "Average Coefficient of Variation of Seed Spacing Percentage", "ppm")


def condensed_work_state(k: int) -> Ddi:
    """DDI 161 + k: the work states of rows 16k+1 .. 16k+16."""
    first = CONDENSED_ROWS * k + 1
    return Ddi(CONDENSED_WORK_STATE_FIRST + k,
               f"Actual Condensed Work State ({first}-{first + CONDENSED_ROWS - 1})", "n.a.")


DDIS: tuple[Ddi, ...] = (
    SETPOINT_MASS_PER_AREA, ACTUAL_MASS_PER_AREA, SETPOINT_COUNT_PER_AREA,
    ACTUAL_COUNT_PER_AREA, SETPOINT_SPACING, ACTUAL_SPACING, ACTUAL_WORKING_WIDTH, TOTAL_COUNT,
    TOTAL_AREA, OFFSET_X, OFFSET_Y, ACTUAL_WORK_STATE, ACTUAL_SPEED, AVERAGE_SINGULATION,
    AVERAGE_SKIP, AVERAGE_MULTIPLE, AVERAGE_CV,
    *(condensed_work_state(k) for k in range(16)),
)
ROW_DDIS = (ACTUAL_SPACING, ACTUAL_COUNT_PER_AREA, TOTAL_COUNT, AVERAGE_SINGULATION,
            AVERAGE_SKIP, AVERAGE_MULTIPLE, AVERAGE_CV)


@dataclass(frozen=True, slots=True)
class Presentation:
    """A ``DVP``: shown value = (logged + offset) x scale, with ``decimals`` and ``unit``."""

    scale: float
    decimals: int
    unit: str
    offset: int = 0


KG_HA = Presentation(0.01, 1, "kg/ha")  # mg/m² x 0.01
SEEDS_HA = Presentation(10, 0, "seeds/ha")  # 0.001/m² x 10
CM = Presentation(0.1, 1, "cm")
M = Presentation(0.001, 2, "m")
KMH = Presentation(0.0036, 1, "km/h")  # mm/s
HA = Presentation(0.0001, 2, "ha")  # m²
PERCENT = Presentation(0.0001, 1, "%")  # ppm
COUNT = Presentation(1, 0, "seeds")

# DPD property (C) and trigger methods (D), ISO 11783-10
IN_DEFAULT_SET = 1
ON_CHANGE, TOTAL = 8, 16


@dataclass
class Element:
    """A ``DET`` with its logged process data (``DPD``) and fixed properties (``DPT``)."""

    det_id: str
    object_id: int
    kind: int  # 1 device, 2 function, 4 section
    designator: str
    number: int
    parent_object_id: int
    process: list[tuple[Ddi, str, int, Presentation | None]] = field(default_factory=list)
    properties: list[tuple[Ddi, int, str, Presentation | None]] = field(default_factory=list)


class SeederDevice:
    """The ``DVC`` of this machine, built from its configuration."""

    def __init__(self, settings: Settings, software_version: str) -> None:
        self.settings = settings
        self.software_version = software_version
        machine = settings.machine
        self.rows = machine.rows
        self.row_width_m = machine.working_width_m / machine.rows
        self.target_spacing_m = settings.positioning.target_spacing_m
        lateral = settings.positioning.row_lateral_m or []
        behind_mm = round(-settings.positioning.outlet_behind_antenna_m * 1000)
        self.elements: list[Element] = []
        self.device = self._add(1, "sowgate seeder", 0, 0, [
            (ACTUAL_WORK_STATE, "Work state", ON_CHANGE, None),
            (ACTUAL_SPEED, "Speed", ON_CHANGE, KMH),
            (TOTAL_AREA, "Area sown", TOTAL, HA),
        ])
        boom_process: list[tuple[Ddi, str, int, Presentation | None]] = [
            (ACTUAL_WORKING_WIDTH, "Working width", ON_CHANGE, M),
        ]
        boom_process += [
            (condensed_work_state(k), f"Rows {16 * k + 1}-{16 * k + 16} on", ON_CHANGE, None)
            for k in range(self.condensed_count)
        ]
        if self.target_spacing_m is not None:
            boom_process += [
                (SETPOINT_COUNT_PER_AREA, "Target seeds/area", ON_CHANGE, SEEDS_HA),
                (SETPOINT_SPACING, "Target spacing", ON_CHANGE, CM),
            ]
        self.boom = self._add(2, "Seed boom", 1, self.device.object_id, boom_process)
        self.boom.properties.append(
            (ACTUAL_WORKING_WIDTH, round(machine.working_width_m * 1000), "Width", M)
        )
        self.channels: dict[str, Element] = {}
        for c in settings.channel:
            self.channels[c.name] = self._add(2, f"Channel {c.name} ({c.product})",
                                              len(self.elements), self.device.object_id, [
                (SETPOINT_MASS_PER_AREA, "Target rate", ON_CHANGE, KG_HA),
                (ACTUAL_MASS_PER_AREA, "Applied rate", ON_CHANGE, KG_HA),
            ])
        self.row_elements: list[Element] = []
        for r in range(self.rows):
            e = self._add(4, f"Row {r + 1}", len(self.elements), self.boom.object_id, [
                (ACTUAL_SPACING, "Spacing", ON_CHANGE, CM),
                (ACTUAL_COUNT_PER_AREA, "Seeds/area", ON_CHANGE, SEEDS_HA),
                (TOTAL_COUNT, "Seeds", TOTAL, COUNT),
                (AVERAGE_SINGULATION, "Singulation", ON_CHANGE, PERCENT),
                (AVERAGE_SKIP, "Skips", ON_CHANGE, PERCENT),
                (AVERAGE_MULTIPLE, "Multiples", ON_CHANGE, PERCENT),
                (AVERAGE_CV, "Spacing CV", ON_CHANGE, PERCENT),
            ])
            e.properties += [
                (OFFSET_X, behind_mm, "Behind antenna", M),
                (OFFSET_Y, round(lateral[r] * 1000) if r < len(lateral) else 0,
                 "Right of centre", M),
                (ACTUAL_WORKING_WIDTH, round(self.row_width_m * 1000), "Row width", M),
            ]
            self.row_elements.append(e)

    @property
    def condensed_count(self) -> int:
        return -(-self.rows // CONDENSED_ROWS)

    def _add(
        self, kind: int, designator: str, number: int, parent: int,
        process: list[tuple[Ddi, str, int, Presentation | None]],
    ) -> Element:
        n = len(self.elements) + 1
        e = Element(f"DET-{n}", n, kind, designator[:32], number, parent, process)
        self.elements.append(e)
        return e

    @property
    def client_name(self) -> str:
        """An ISO 11783-5 NAME (8 bytes hex): self-configurable, industry group 2
        (agriculture), device class 4 (planters/seeders), manufacturer code 0 (none
        registered), identity number from the machine id."""
        identity = int.from_bytes(
            hashlib.sha256(self.settings.machine.id.encode()).digest()[:3], "big"
        ) & 0x1FFFFF
        name = (1 << 63) | (2 << 60) | (4 << 49) | identity
        return f"{name:016X}"

    def xml(self) -> ET.Element:
        dvc = ET.Element("DVC", {
            "A": "DVC-1",
            "B": "sowgate seeder",
            "C": self.software_version[:32],
            "D": self.client_name,
            "E": self.settings.machine.id[:32],
            "F": _hex_label(f"SG{self.rows:03d}{len(self.channels):02d}"),
            "G": "FF000000006E65",  # localization label: 7 bytes, language "en" in the last two
        })
        presentations: dict[Presentation, int] = {}
        next_object = len(self.elements) + 1
        dpds: list[ET.Element] = []
        dpts: list[ET.Element] = []
        for e in self.elements:
            det = ET.SubElement(dvc, "DET", {
                "A": e.det_id, "B": str(e.object_id), "C": str(e.kind), "D": e.designator,
                "E": str(e.number), "F": str(e.parent_object_id),
            })
            for ddi, designator, triggers, pres in e.process:
                attrs = {"A": str(next_object), "B": f"{ddi.number:04X}",
                         "C": str(IN_DEFAULT_SET), "D": str(triggers), "E": designator[:32]}
                if pres is not None:
                    attrs["F"] = str(presentations.setdefault(pres, 60000 + len(presentations)))
                dpds.append(ET.Element("DPD", attrs))
                ET.SubElement(det, "DOR", {"A": str(next_object)})
                next_object += 1
            for ddi, value, designator, pres in e.properties:
                attrs = {"A": str(next_object), "B": f"{ddi.number:04X}", "C": str(value),
                         "D": designator[:32]}
                if pres is not None:
                    attrs["E"] = str(presentations.setdefault(pres, 60000 + len(presentations)))
                dpts.append(ET.Element("DPT", attrs))
                ET.SubElement(det, "DOR", {"A": str(next_object)})
                next_object += 1
        dvc.extend(dpds)
        dvc.extend(dpts)
        for pres, object_id in presentations.items():
            ET.SubElement(dvc, "DVP", {
                "A": str(object_id), "B": str(pres.offset),
                "C": format(Decimal(str(pres.scale)), "f"),
                "D": str(pres.decimals), "E": pres.unit,
            })
        return dvc


def _hex_label(text: str) -> str:
    """A 7-byte label as hex (the structure label says the device's shape)."""
    raw = text.encode("ascii")[:7].ljust(7, b" ")
    return raw.hex().upper()
