"""``sowgate export --format isoxml``: the records as an ISO 11783-10 TaskData (v4.3).

``DIR/TASKDATA/TASKDATA.XML`` holds the customer, farm and field from ``[farm]`` (when set),
the device (``gateway.app.isoxml_device``) and one completed task spanning the records, with
its time log(s) ``TLG00001.XML/.BIN``; ``--zip`` writes the same ``TASKDATA/`` folder into a
zip file instead. Any ISOBUS terminal or farm software that reads ISO-XML can open it.

The time log is made of two streams merged in time order:

- each seed record is one TLG record at the seed's position and UTC time, with the row's
  actual spacing and count per area, the speed, and whatever machine state changed since the
  log's last record (work state, the rows' condensed work states, working width, totals,
  each row's quality once a second);
- each as-applied row (the metering channels' log) is one record at its outlet's position
  with the channel's setpoint and actual mass per area.

A row counts as sowing from its first seed until ``SECTION_OFF_AFTER_S`` passes without one;
the machine works while any row sows. The log's state changes are recorded at those
instants, so a viewer's coverage map stops where the seeds stop.

A time log names at most 255 values (its DLV index is one byte). The device and channel
values go in every log; the rows' values are split over as many logs as they need
(``TLG00001`` rows 1..k, ``TLG00002`` the next, ...), each seed in its row's log.

Streamed: the store is read a chunk at a time and the binaries are written as they go; what
is held is one state value per DLV and one quality accumulator per row (as ``export``). The
folder is built under a temporary name and renamed at the end, so a failed export leaves no
half task behind.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import heapq
import os
import shutil
import sys
import tempfile
import xml.etree.ElementTree as ET
import zipfile
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

from gateway.app.isoxml_device import (
    ACTUAL_COUNT_PER_AREA,
    ACTUAL_MASS_PER_AREA,
    ACTUAL_SPACING,
    ACTUAL_SPEED,
    ACTUAL_WORK_STATE,
    ACTUAL_WORKING_WIDTH,
    AVERAGE_CV,
    AVERAGE_MULTIPLE,
    AVERAGE_SINGULATION,
    AVERAGE_SKIP,
    CONDENSED_ROWS,
    ROW_DDIS,
    SETPOINT_COUNT_PER_AREA,
    SETPOINT_MASS_PER_AREA,
    SETPOINT_SPACING,
    TOTAL_AREA,
    TOTAL_COUNT,
    Ddi,
    SeederDevice,
    condensed_work_state,
)
from gateway.config import ConfigError, Settings, as_applied_path, load_config, parse_config
from gateway.core.records import utc_to_us
from gateway.recording.export import (
    EXIT_FAILED,
    ExportError,
    chunks_of_records,
    export_failed,
    parse_rows,
    parse_time,
)
from gateway.recording.spacing_quality import RowQualityAccumulator
from gateway.recording.store import STORED_SEED_COLUMNS, StoredSeedRow
from protocol.isoxml_tlg import (
    MAX_VALUES_PER_RECORD,
    DataLogValue,
    TimeLogError,
    TimeLogLayout,
    TimeLogRecord,
    degrees_to_tlg,
    encode_record,
    header_xml,
    utc_us_to_tlg_time,
)

SECTION_OFF_AFTER_S = 2.0  # a row with no seed for this long is off (its section closed)
# PTN: north, east, status, GpsUtcTime, GpsUtcDate in every record
LAYOUT = TimeLogLayout(("A", "B", "D", "H", "I"))
# ISO 11783-10 PositionStatus for sowgate's fix qualities (the NMEA GGA numbering)
POSITION_STATUS = {"none": 0, "single": 1, "dgps": 2, "rtk_fixed": 4, "rtk_float": 5}
STATUS_NOT_AVAILABLE = 15
NOT_INSTALLED, ON, OFF = 0b11, 0b01, 0b00
_US, _ROW, _LAT, _LON, _FIX, _SPEED, _SPACING = (
    STORED_SEED_COLUMNS.index(n)
    for n in ("utc_us", "row", "lat", "lon", "fix", "speed_kmh", "spacing_m")
)

Key = tuple[int, str]  # (DDI, DET id): one logged value


class AsAppliedLogError(ExportError):
    """The as-applied log has a row that is not one (a damaged file, not a bad request)."""

    exit_code = EXIT_FAILED


@dataclass
class TimeLogFile:
    """One ``TLGnnnnn``: its DLVs and the binary being written."""

    name: str
    values: list[DataLogValue]
    out: BinaryIO
    index: dict[Key, int] = field(default_factory=dict)
    pending: set[int] = field(default_factory=set)  # state values changed since last record
    records: int = 0
    size: int = 0

    def __post_init__(self) -> None:
        self.index = {(v.ddi, v.det_id): i for i, v in enumerate(self.values)}

    def write(self, utc_us: int, position: tuple[int, int, int], values: list[tuple[int, int]]
              ) -> None:
        ms, days = utc_us_to_tlg_time(utc_us)
        pos = (*position, ms, days)
        for start in range(0, max(len(values), 1), MAX_VALUES_PER_RECORD):
            data = encode_record(LAYOUT, TimeLogRecord(
                ms, days, pos, tuple(values[start:start + MAX_VALUES_PER_RECORD])))
            self.out.write(data)
            self.size += len(data)
            self.records += 1


class TimeLogWriter:
    """Turns seed records and as-applied rows into the time log records (module docstring)."""

    def __init__(self, device: SeederDevice, outs: Iterator[tuple[str, BinaryIO]]) -> None:
        self.device = device
        d = device
        common: list[Key] = [
            (ACTUAL_WORK_STATE.number, d.device.det_id),
            (ACTUAL_SPEED.number, d.device.det_id),
            (TOTAL_AREA.number, d.device.det_id),
            (ACTUAL_WORKING_WIDTH.number, d.boom.det_id),
            *((condensed_work_state(k).number, d.boom.det_id)
              for k in range(d.condensed_count)),
        ]
        if d.target_spacing_m is not None:
            common += [(SETPOINT_COUNT_PER_AREA.number, d.boom.det_id),
                       (SETPOINT_SPACING.number, d.boom.det_id)]
        channels: list[Key] = [
            (ddi.number, e.det_id) for e in d.channels.values()
            for ddi in (SETPOINT_MASS_PER_AREA, ACTUAL_MASS_PER_AREA)
        ]
        room = MAX_VALUES_PER_RECORD - len(common) - len(channels)
        per_log = room // len(ROW_DDIS)
        if per_log < 1:
            raise ExportError(
                f"{len(channels) // 2} channels leave no room for a row in a time log "
                f"(at most {MAX_VALUES_PER_RECORD} values)"
            )
        self.logs: list[TimeLogFile] = []
        self.log_of_row: list[TimeLogFile] = []
        for first in range(0, d.rows, per_log):
            rows = range(first, min(first + per_log, d.rows))
            keys = list(common) + (channels if first == 0 else []) + [
                (ddi.number, d.row_elements[r].det_id) for r in rows for ddi in ROW_DDIS
            ]
            name, out = next(outs)
            log = TimeLogFile(name, [DataLogValue(ddi, det) for ddi, det in keys], out)
            self.logs.append(log)
            self.log_of_row += [log] * len(rows)
        self.state: dict[Key, int] = {}
        self.where: dict[Key, list[TimeLogFile]] = {}
        for log in self.logs:
            for key in log.index:
                self.where.setdefault(key, []).append(log)
        self.row_keys = [
            {ddi: (ddi.number, e.det_id) for ddi in ROW_DDIS} for e in d.row_elements
        ]
        self.channel_keys = {
            name: ((SETPOINT_MASS_PER_AREA.number, e.det_id),
                   (ACTUAL_MASS_PER_AREA.number, e.det_id))
            for name, e in d.channels.items()
        }
        self.speed_key = (ACTUAL_SPEED.number, d.device.det_id)
        self.quality = [RowQualityAccumulator(d.target_spacing_m) for _ in range(d.rows)]
        self.seeds = [0] * d.rows
        self.sown_m = 0.0  # the rows' spacings summed: distance sown, row by row
        self.quality_dirty: set[int] = set()
        self.row_last_us: dict[int, int] = {}  # the rows sowing, with their last seed's time
        self.position = (0, 0, STATUS_NOT_AVAILABLE)
        self.first_us: int | None = None
        self.last_us: int | None = None
        self._second = -1
        self._off_us = round(SECTION_OFF_AFTER_S * 1_000_000)
        self._recent: deque[tuple[int, int]] = deque()
        self._put_value((ACTUAL_WORK_STATE.number, d.device.det_id), 0)
        self._sections_changed()
        if d.target_spacing_m is not None:
            self._put_value((SETPOINT_COUNT_PER_AREA.number, d.boom.det_id),
                            round(1000 / (d.target_spacing_m * d.row_width_m)))
            self._put_value((SETPOINT_SPACING.number, d.boom.det_id),
                            round(d.target_spacing_m * 1000))

    # ------------------------------------------------------------ state

    def _put_value(self, key: Key, value: int) -> None:
        if self.state.get(key) != value:
            self.state[key] = value
            for log in self.where.get(key, ()):
                log.pending.add(log.index[key])

    def _sections_changed(self) -> None:
        d = self.device
        for k in range(d.condensed_count):
            word = 0
            for i in range(CONDENSED_ROWS):
                row = k * CONDENSED_ROWS + i
                bits = NOT_INSTALLED if row >= d.rows else (ON if row in self.row_last_us
                                                            else OFF)
                word |= bits << (2 * i)
            signed = word - (1 << 32) if word >= 1 << 31 else word
            self._put_value((condensed_work_state(k).number, d.boom.det_id), signed)
        self._put_value((ACTUAL_WORKING_WIDTH.number, d.boom.det_id),
                  round(len(self.row_last_us) * d.row_width_m * 1000))
        self._put_value((ACTUAL_WORK_STATE.number, d.device.det_id), 1 if self.row_last_us else 0)

    def _update_quality(self) -> None:
        d = self.device
        for row in self.quality_dirty:
            q = self.quality[row].result()
            keys = self.row_keys[row]
            for ddi, percent in ((AVERAGE_SINGULATION, q.quality_of_feed_index),
                                 (AVERAGE_SKIP, q.miss_index),
                                 (AVERAGE_MULTIPLE, q.multiples_index),
                                 (AVERAGE_CV, q.precision)):
                if percent is not None:
                    self._put_value(keys[ddi], round(percent * 10_000))
            self._put_value(keys[TOTAL_COUNT], self.seeds[row])
        self.quality_dirty.clear()
        self._put_value((TOTAL_AREA.number, d.device.det_id), round(self.sown_m * d.row_width_m))

    def _close_idle(self, now_us: int) -> None:
        """Rows without a seed for ``SECTION_OFF_AFTER_S`` close, each with a record at the
        instant it did (before the record at ``now_us``, so the log stays in time order).

        ``_recent`` holds every seed's (time, row) in arrival order: a row's entry that is no
        longer its last seed is stale and dropped; each seed is queued and dropped once."""
        recent, off = self._recent, self._off_us
        while recent and recent[0][0] + off <= now_us:
            us, row = recent.popleft()
            if self.row_last_us.get(row) != us:
                continue
            del self.row_last_us[row]
            self._sections_changed()
            for log in self.logs:
                if log.pending:
                    self._write(log, us + off, [])

    def _advance(self, us: int) -> None:
        self.first_us = us if self.first_us is None else min(self.first_us, us)
        self.last_us = us if self.last_us is None else max(self.last_us, us)
        self._close_idle(us)
        second = us // 1_000_000
        if second > self._second:  # the rows' quality, once a second of record time
            self._second = second
            self._update_quality()

    def _write(self, log: TimeLogFile, us: int, values: list[tuple[int, int]]) -> None:
        if log.pending:
            state = self.state
            dlvs = log.values
            values = values + [
                (i, state[(dlvs[i].ddi, dlvs[i].det_id)]) for i in sorted(log.pending)
            ]
            log.pending.clear()
        log.write(us, self.position, values)

    # ------------------------------------------------------------ events

    def seed(self, r: StoredSeedRow) -> None:
        us, row = r[_US], r[_ROW] - 1
        if not 0 <= row < self.device.rows:
            raise ExportError(f"a seed of row {row + 1}, the machine has {self.device.rows}")
        self._advance(us)
        self.position = (degrees_to_tlg(r[_LAT]), degrees_to_tlg(r[_LON]),
                         POSITION_STATUS.get(r[_FIX], STATUS_NOT_AVAILABLE))
        was_on = row in self.row_last_us
        self.row_last_us[row] = us
        self._recent.append((us, row))
        if not was_on:
            self._sections_changed()
        self._put_value(self.speed_key, round(r[_SPEED] / 3.6 * 1000))
        self.seeds[row] += 1
        self.quality_dirty.add(row)
        log = self.log_of_row[row]
        keys = self.row_keys[row]
        values: list[tuple[int, int]] = []
        spacing = r[_SPACING]
        if spacing is not None:
            self.quality[row].add(spacing)
            self.sown_m += spacing
            values.append((log.index[keys[ACTUAL_SPACING]], round(spacing * 1000)))
            if spacing > 0:
                per_area = 1000 / (spacing * self.device.row_width_m)
                if per_area < 2**31:
                    values.append((log.index[keys[ACTUAL_COUNT_PER_AREA]], round(per_area)))
        self._write(log, us, values)

    def applied(self, us: int, lat: float, lon: float, channel: str, target_kg_ha: float,
                applied_kg_ha: float | None) -> bool:
        """Log one as-applied row; False (not logged) for a channel the configuration no
        longer has: there is no device element to log it against."""
        keys = self.channel_keys.get(channel)
        if keys is None:
            return False
        self._advance(us)
        status = self.position[2]
        self.position = (degrees_to_tlg(lat), degrees_to_tlg(lon), status)
        log = self.logs[0]
        values = [(log.index[keys[0]], round(target_kg_ha * 100))]
        if applied_kg_ha is not None:
            values.append((log.index[keys[1]], round(applied_kg_ha * 100)))
        self._write(log, us, values)
        return True

    def finish(self) -> None:
        """Close every row at its end, with the final quality and totals."""
        if self.last_us is None:
            return
        self._close_idle(self.end_us)
        self._update_quality()
        for log in self.logs:
            if log.pending:
                self._write(log, self.end_us, [])

    @property
    def end_us(self) -> int:
        """When the last row closed: the export's end."""
        assert self.last_us is not None
        return self.last_us + self._off_us


# ---------------------------------------------------------------- sources


def seed_events(chunks: Iterable[Sequence[StoredSeedRow]]) -> Iterator[tuple[int, int, Any]]:
    for chunk in chunks:
        for r in chunk:
            yield r[_US], 0, r


def applied_events(
    path: Path, since: datetime | None, until: datetime | None
) -> Iterator[tuple[int, int, Any]]:
    """The as-applied log, a row at a time (none when there is no log)."""
    try:
        fh = path.open(encoding="utf-8", newline="")
    except FileNotFoundError:
        return
    lo = None if since is None else utc_to_us(since)
    hi = None if until is None else utc_to_us(until)
    with fh:
        for n, rec in enumerate(csv.DictReader(fh), start=2):
            try:
                when = parse_time(rec["time"], "time")
                assert when is not None
                us = utc_to_us(when)
                applied = rec["applied_kg_ha"]
                row = (float(rec["lat"]), float(rec["lon"]), rec["channel"],
                       float(rec["target_kg_ha"]),
                       float(applied) if applied not in ("", None) else None)
            except (KeyError, TypeError, ValueError, ExportError) as exc:
                raise AsAppliedLogError(f"{path}:{n}: not an as-applied row ({exc})") from None
            if (lo is None or us >= lo) and (hi is None or us < hi):
                yield us, 1, row


# ---------------------------------------------------------------- TASKDATA.XML


def _utc_text(us: int) -> str:
    return datetime.fromtimestamp(us // 1_000_000, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def taskdata_xml(
    settings: Settings, device: SeederDevice, writer: TimeLogWriter, version: str
) -> bytes:
    root = ET.Element("ISO11783_TaskData", {
        "VersionMajor": "4", "VersionMinor": "3",
        "ManagementSoftwareManufacturer": "sowgate", "ManagementSoftwareVersion": version[:32],
        "TaskControllerManufacturer": "sowgate", "TaskControllerVersion": version[:32],
        "DataTransferOrigin": "2",  # from the machine (MICS), not from an FMIS
    })
    farm = settings.farm
    task: dict[str, str] = {"A": "TSK-1"}
    if farm.customer:
        ET.SubElement(root, "CTR", {"A": "CTR-1", "B": farm.customer})
        task["C"] = "CTR-1"
    root.append(device.xml())
    if farm.farm:
        attrs = {"A": "FRM-1", "B": farm.farm}
        if farm.customer:
            attrs["I"] = "CTR-1"
        ET.SubElement(root, "FRM", attrs)
        task["D"] = "FRM-1"
    if farm.field:
        attrs = {"A": "PFD-1", "C": farm.field, "D": str(round(farm.field_area_ha * 10_000))}
        if farm.customer:
            attrs["E"] = "CTR-1"
        if farm.farm:
            attrs["F"] = "FRM-1"
        ET.SubElement(root, "PFD", attrs)
        task["E"] = "PFD-1"
    products: dict[str, str] = {}
    for c in settings.channel:
        if c.product not in products:
            products[c.product] = f"PDT-{len(products) + 1}"
            ET.SubElement(root, "PDT", {"A": products[c.product], "B": c.product[:32]})
    day = "" if writer.first_us is None else " " + _utc_text(writer.first_us)[:10]
    task["B"] = f"Sowing {settings.machine.id}{day}"[:32]
    task["G"] = "4"  # completed
    tsk = ET.SubElement(root, "TSK", task)
    if writer.first_us is not None:
        ET.SubElement(tsk, "TIM", {"A": _utc_text(writer.first_us),
                                   "B": _utc_text(writer.end_us), "D": "4"})
    ET.SubElement(tsk, "DAN", {"A": device.client_name, "C": "DVC-1"})
    for c in settings.channel:
        ET.SubElement(tsk, "PAN", {"A": products[c.product], "E": device.channels[c.name].det_id})
    for log in writer.logs:
        if log.records:
            ET.SubElement(tsk, "TLG", {"A": log.name, "B": str(log.size), "C": "1"})
    ET.indent(root)
    return b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root) + b"\n"


# ---------------------------------------------------------------- the command


@dataclass
class IsoxmlResult:
    seeds: int = 0
    applied: int = 0
    records: int = 0
    logs: int = 0
    unknown_channel: int = 0  # as-applied rows of channels no longer configured (left out)


def write_taskdata(
    folder: Path,
    settings: Settings,
    chunks: Iterable[Sequence[StoredSeedRow]],
    applied: Iterable[tuple[int, int, Any]],
    version: str,
) -> IsoxmlResult:
    """Write ``TASKDATA.XML`` and the time logs into ``folder`` (which exists and is empty)."""
    device = SeederDevice(settings, version)
    files: list[BinaryIO] = []

    def outs() -> Iterator[tuple[str, BinaryIO]]:
        n = 0
        while True:
            n += 1
            f = (folder / f"TLG{n:05d}.BIN").open("wb", buffering=1 << 20)
            files.append(f)
            yield f"TLG{n:05d}", f

    result = IsoxmlResult()
    try:
        writer = TimeLogWriter(device, outs())
        for us, kind, payload in heapq.merge(seed_events(chunks), applied, key=_event_time):
            if kind == 0:
                writer.seed(payload)
                result.seeds += 1
            elif writer.applied(us, *payload):
                result.applied += 1
            else:
                result.unknown_channel += 1
        writer.finish()
    except TimeLogError as exc:
        raise ExportError(f"a value does not fit the time log: {exc}") from None
    finally:
        for f in files:
            f.close()
    for log in writer.logs:
        if log.records:
            (folder / f"{log.name}.XML").write_bytes(header_xml(LAYOUT, log.values))
            result.records += log.records
            result.logs += 1
        else:
            (folder / f"{log.name}.BIN").unlink()
    (folder / "TASKDATA.XML").write_bytes(taskdata_xml(settings, device, writer, version))
    return result


def _event_time(event: tuple[int, int, Any]) -> tuple[int, int]:
    return event[0], event[1]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sowgate")
    except PackageNotFoundError:
        return "0"


def main_export_isoxml(args: argparse.Namespace) -> int:
    """``sowgate export --format isoxml --output DIR [--zip]``: exit code as ``export``."""
    from gateway.recording.store import StoreError

    try:
        config = getattr(args, "config", None)
        settings = load_config(config) if config is not None else parse_config({})
        state = getattr(args, "state_dir", None)
        state = Path(state) if state is not None else None
        since = parse_time(getattr(args, "since", None), "since")
        until = parse_time(getattr(args, "until", None), "until")
        if since is not None and until is not None and until <= since:
            raise ExportError("--until must be later than --since")
        rows = parse_rows(getattr(args, "rows", None), settings.machine.rows)
        if args.output == "-":
            raise ExportError("--format isoxml writes a folder (or --zip a file), not to -")
        output = Path(args.output)
        as_zip = bool(getattr(args, "zip", False))
        from gateway.config import store_path

        moved = None
        if getattr(args, "reposition", False):
            from gateway.app.position_calibration import Repositioner, calibrated_settings

            moved = Repositioner(calibrated_settings(settings, state))
        from gateway.recording.export import database_options
        from gateway.recording.source import open_source

        database, machine = database_options(args)
        with open_source(store_path(settings, state), settings.machine.id, database,
                         machine) as st:
            chunks: Iterable[Sequence[StoredSeedRow]] = st.query_seed_rows(since, until, rows)
            if moved is not None:
                chunks = chunks_of_records(moved(st.query_seeds(since, until, rows)))
            # the as-applied log is the cab's own file: from the database, seeds only
            applied = (applied_events(as_applied_path(settings, state), since, until)
                       if database is None else iter(()))
            with _taskdata_folder(output, as_zip) as folder:
                result = write_taskdata(folder, settings, chunks, applied, _version())
    except (ConfigError, ExportError, StoreError, OSError) as exc:
        return export_failed(exc)
    where = output if as_zip else output / "TASKDATA"
    print(
        f"wrote {result.seeds} seed records and {result.applied} as-applied rows as "
        f"{result.records} time log records ({result.logs} time logs) to {where} (ISO-XML)",
        file=sys.stderr,
    )
    if result.unknown_channel:
        print(
            f"left out {result.unknown_channel} as-applied rows of channels that are not in "
            "the configuration ([[channel]] name): the device has no element for them",
            file=sys.stderr,
        )
    return 0


@contextlib.contextmanager
def _taskdata_folder(output: Path, as_zip: bool) -> Iterator[Path]:
    """A temporary ``TASKDATA`` folder that becomes ``output/TASKDATA`` (or the zip
    ``output``) only when the block succeeds."""
    parent = output.parent if as_zip else output
    if as_zip:
        if output.is_dir():
            raise ExportError(f"--zip: {output} is a folder; name the zip file to write")
    else:
        if output.exists() and not output.is_dir():
            raise ExportError(f"--output {output}: not a folder (use --zip for a zip file)")
        if (output / "TASKDATA").exists():
            raise ExportError(
                f"{output / 'TASKDATA'} exists: a terminal reads one TASKDATA per folder; "
                "move it away or choose another --output"
            )
        output.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".TASKDATA.", dir=parent))
    staging.chmod(0o755)  # mkdtemp's 0700 would hide the task from the user's other tools
    try:
        yield staging
        if as_zip:
            fd, tmp = tempfile.mkstemp(prefix=f".{output.name}.", dir=parent)
            try:
                with os.fdopen(fd, "wb") as raw, zipfile.ZipFile(
                    raw, "w", zipfile.ZIP_DEFLATED
                ) as z:
                    for f in sorted(staging.iterdir()):
                        z.write(f, f"TASKDATA/{f.name}")
                os.replace(tmp, output)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
        else:
            os.replace(staging, output / "TASKDATA")
    finally:
        shutil.rmtree(staging, ignore_errors=True)


__all__ = ["Ddi", "TimeLogWriter", "main_export_isoxml", "taskdata_xml", "write_taskdata"]
