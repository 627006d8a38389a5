"""What the dashboard knows about each machine, built from the MQTT payloads (pure: no I/O).

``Fleet.handle(topic, payload, retained)`` takes every message of docs/mqtt.md as it arrives;
``Fleet.snapshot()`` is everything a page that just connected needs, and
``Fleet.drain_updates()`` what changed since the last call (the server pushes it to the open
pages a few times a second, so 2 000 seeds a second are a few messages, not 2 000).

Delivery is at-least-once: seeds and alarm events are deduplicated by ``(machine_id, id)``
(docs/mqtt.md). Per machine the dashboard keeps the newest ``max_seeds`` seeds; ids below the
oldest one kept are taken as seen (a redelivery is of records the broker never acknowledged,
which are recent), so memory stays bounded on a 70 M-records-a-day planter. At most
``max_machines`` machines are kept: messages of further machine ids are counted
(``machines_refused``) and dropped.

Positions become local metres east/north of the first seed the dashboard saw (of any
machine, so several seeders on one field share a frame). An equirectangular projection: over a
few kilometres its error is far below a seed's spacing, and the page needs no map library.
"""

from __future__ import annotations

import contextlib
import math
import statistics
import time
from array import array
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import orjson
from pydantic import ValidationError

from gateway.core.records import AlarmEvent
from gateway.link.payloads import CommandAck, SeedBatch, StatePayload
from gateway.recording.spacing_quality import (
    MISS_LIMIT,
    MULTIPLE_LIMIT,
    QUALITY_WINDOW,
    RowQualityAccumulator,
)

EARTH_RADIUS_M = 6_371_008.8
# spacing class of a seed on the map (and its colour on the page)
CLASS_UNKNOWN, CLASS_MULTIPLE, CLASS_GOOD, CLASS_MISS = 0, 1, 2, 3
RATE_HISTORY_S = 600.0  # the rate chart's span: the last 10 minutes
ALARM_HISTORY = 200  # raised/cleared alarms listed per machine (newest kept)
# The applied rate is the seed mass over the area between two states. Both are published
# rounded (1 g, 1 m²): a ratio is only drawn once 30 g have gone out over 30 m² (3.3 % at
# most from each rounding; rapeseed at 6 kg/ha: 50 m², about 30 s at 3 km/h with 2 m; wheat
# at 180 kg/ha: a point every ~7 s), or 0.1 ha has been worked (a crop sown by the gram at a
# lower rate). Each second alone (4 m² of wheat) drew ±25 % of rounding noise.
MIN_APPLIED_MASS_KG = 0.03
MIN_APPLIED_SPAN_M2 = 30  # compared in whole m², as published (0.005 ha in floats is 0.00499…)
MIN_APPLIED_AREA_HA = 0.1
MAX_PAYLOAD_BYTES = 8_000_000  # a seed batch is ≤ 500 records (~150 kB); far more is hostile


@dataclass
class AlarmEntry:
    code: str
    severity: str
    message: str
    raised: str | None
    cleared: str | None = None
    active: bool = True
    # a critical alarm stays listed until acknowledged (command ack_alarm), as on the screen
    acknowledged: bool = False
    # "cleared", or "offline": still active when the box went offline (sowgate stopped, or
    # its link to the broker broke); it ends there, not at the box's next start
    ended: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "code": self.code, "severity": self.severity, "message": self.message,
            "raised": self.raised, "cleared": self.cleared, "active": self.active,
            "acknowledged": self.acknowledged, "ended": self.ended,
        }


@dataclass
class MachineView:
    machine_id: str
    max_seeds: int
    x_ref_m: float | None = None  # target spacing when the config gives one, else a median
    status: str | None = None  # "online" / "offline" (retained, last will); None: never heard
    state: dict[str, Any] | None = None
    xs: array[float] = field(default_factory=lambda: array("f"))
    ys: array[float] = field(default_factory=lambda: array("f"))
    rows: array[int] = field(default_factory=lambda: array("H"))
    classes: array[int] = field(default_factory=lambda: array("B"))
    seen: set[int] = field(default_factory=set)
    ids: deque[int] = field(default_factory=deque)
    id_floor: int = 0  # ids at or below were evicted: a repeat of one is ignored
    duplicates: int = 0
    quality: dict[int, RowQualityAccumulator] = field(default_factory=dict)
    recent: dict[int, deque[float]] = field(default_factory=dict)
    rate: deque[tuple[float, float | None, float | None, float | None]] = field(
        default_factory=deque
    )
    last_counter: tuple[float, float, float] | None = None  # (t, area_ha, seed_mass_kg)
    rate_sent_t: float = -math.inf  # the newest rate point already pushed to the pages
    alarms: dict[str, AlarmEntry] = field(default_factory=dict)
    alarm_ids: set[int] = field(default_factory=set)
    acks: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def seed_count(self) -> int:
        return len(self.xs)

    def add_seed(self, rid: int, x: float, y: float, row: int, cls: int) -> bool:
        """Keep one seed unless already seen; False for a repeat."""
        if rid in self.seen or rid <= self.id_floor:
            self.duplicates += 1
            return False
        self.seen.add(rid)
        self.ids.append(rid)
        self.xs.append(x)
        self.ys.append(y)
        self.rows.append(row)
        self.classes.append(cls)
        if len(self.ids) > self.max_seeds + self.max_seeds // 10:
            self._evict(len(self.ids) - self.max_seeds)
        return True

    def _evict(self, n: int) -> None:
        for _ in range(n):
            rid = self.ids.popleft()
            self.seen.discard(rid)
            self.id_floor = max(self.id_floor, rid)
        del self.xs[:n], self.ys[:n], self.rows[:n], self.classes[:n]

    def spacing_ref(self, row: int) -> float | None:
        if self.x_ref_m is not None:
            return self.x_ref_m
        window = self.recent.get(row)
        if not window:
            return None
        median = statistics.median(window)
        return median if median > 0 else None

    def row_quality(self) -> dict[str, dict[str, float | int | None]]:
        return {str(row): acc.result().as_dict() for row, acc in sorted(self.quality.items())}

    def alarm_list(self) -> list[dict[str, Any]]:
        return [a.as_dict() for a in self.alarms.values()]

    def summary(self, *, whole_rate: bool = True) -> dict[str, Any]:
        """Everything but the seeds: the page's machine panel, rows, chart and alarms.

        ``whole_rate`` False: only the rate points not pushed yet (``rate_new``), which the
        page appends to what it has; the 10 minutes of history go once, in the snapshot."""
        if whole_rate:
            rate: dict[str, Any] = {"rate": [list(r) for r in self.rate]}
        else:
            rate = {"rate_new": [list(r) for r in self.rate if r[0] > self.rate_sent_t]}
        if self.rate:
            self.rate_sent_t = self.rate[-1][0]
        return {
            "machine_id": self.machine_id,
            "status": self.status,
            "state": self.state,
            "seed_count": self.seed_count,
            "duplicates": self.duplicates,
            "quality": self.row_quality(),
            **rate,
            "alarms": self.alarm_list(),
            "acks": self.acks,
        }


def classify(spacing_m: float | None, x_ref: float | None) -> int:
    """ISO 7256-1's classes of one spacing against the reference (see spacing_quality)."""
    if spacing_m is None or x_ref is None or not math.isfinite(spacing_m):
        return CLASS_UNKNOWN
    if spacing_m <= MULTIPLE_LIMIT * x_ref:
        return CLASS_MULTIPLE
    if spacing_m > MISS_LIMIT * x_ref:
        return CLASS_MISS
    return CLASS_GOOD


class Fleet:
    """Every machine seen under ``<topic_prefix>/``, keyed by machine id."""

    def __init__(
        self,
        topic_prefix: str = "sowgate",
        *,
        max_seeds: int = 300_000,
        max_machines: int = 64,
        target_spacing: Callable[[str], float | None] = lambda machine_id: None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.prefix = topic_prefix.rstrip("/") + "/"
        self.max_seeds = max_seeds
        self.max_machines = max_machines
        self.machines_refused = 0  # messages of machine ids beyond max_machines, dropped
        self.last_refused_id = ""
        self.target_spacing = target_spacing
        self.clock = clock
        self.machines: dict[str, MachineView] = {}
        self.origin: tuple[float, float] | None = None  # (lat, lon) of the local frame
        self._cos_lat = 1.0
        self.broker_connected = False
        self.broker_error = ""
        self.rejected = 0  # messages that were not what docs/mqtt.md describes
        self._pending: list[dict[str, Any]] = []
        self._dirty: set[str] = set()
        self._new_seeds: dict[str, list[float]] = {}

    # -- input ------------------------------------------------------------------------------

    def machine(self, machine_id: str) -> MachineView:
        view = self.machines.get(machine_id)
        if view is None:
            view = MachineView(machine_id, self.max_seeds, self.target_spacing(machine_id))
            self.machines[machine_id] = view
        return view

    def set_broker(self, connected: bool, error: str = "") -> None:
        self.broker_connected = connected
        self.broker_error = "" if connected else error
        self._pending.append(self.broker_message())

    def broker_message(self) -> dict[str, Any]:
        return {"type": "broker", "connected": self.broker_connected, "error": self.broker_error}

    def handle(self, topic: str, payload: bytes, retained: bool = False) -> bool:
        """One MQTT message; False (and counted) when it is not one the dashboard knows."""
        if not topic.startswith(self.prefix) or len(payload) > MAX_PAYLOAD_BYTES:
            self.rejected += 1
            return False
        parts = topic[len(self.prefix):].split("/")
        if len(parts) < 2 or not parts[0]:
            self.rejected += 1
            return False
        machine_id, kind = parts[0], parts[1:]
        if machine_id not in self.machines and len(self.machines) >= self.max_machines:
            # 20 000 stray ids on the broker must not grow the process: counted, not kept
            self.machines_refused += 1
            self.last_refused_id = machine_id[:64]
            return False
        try:
            if kind == ["status"]:
                return self._status(machine_id, payload)
            if kind == ["state"]:
                return self._state(machine_id, payload)
            if kind == ["seeds"]:
                return self._seeds(machine_id, payload)
            if kind == ["alarms"]:
                return self._alarm(machine_id, payload)
            if len(kind) == 3 and kind[0] == "cmd" and kind[2] == "ack":
                return self._ack(machine_id, kind[1], payload)
        except (ValidationError, ValueError, RecursionError, orjson.JSONDecodeError):
            pass
        else:
            return False  # a command we sent, or a topic of a newer box: not ours to show
        self.rejected += 1
        return False

    def _status(self, machine_id: str, payload: bytes) -> bool:
        text = payload.decode("utf-8", "replace").strip()
        if text not in ("online", "offline"):
            raise ValueError(f"status {text!r}")
        view = self.machine(machine_id)
        view.status = text
        if text == "offline":
            _end_active_alarms(view)
        self._dirty.add(machine_id)
        return True

    def _state(self, machine_id: str, payload: bytes) -> bool:
        state = StatePayload.model_validate_json(payload)
        view = self.machine(machine_id)
        view.state = state.model_dump(mode="json")
        # the box's time: a retained state read late is drawn when it was true, not now
        now = state.utc.timestamp()
        applied = None
        if view.last_counter is not None:
            _, area0, mass0 = view.last_counter
            d_area = state.area_ha - area0
            if d_area < 0 or state.seed_mass_kg < mass0:  # counters reset on the box
                view.last_counter = (now, state.area_ha, state.seed_mass_kg)
            elif d_area >= MIN_APPLIED_AREA_HA or (
                    round(d_area * 1e4) >= MIN_APPLIED_SPAN_M2
                    and state.seed_mass_kg - mass0 >= MIN_APPLIED_MASS_KG):
                applied = round((state.seed_mass_kg - mass0) / d_area, 2)
                view.last_counter = (now, state.area_ha, state.seed_mass_kg)
        else:
            view.last_counter = (now, state.area_ha, state.seed_mass_kg)
        view.rate.append((now, state.target_rate_kg_ha, state.commanded_rate_kg_ha, applied))
        while view.rate and view.rate[0][0] < now - RATE_HISTORY_S:
            view.rate.popleft()
        self._sync_active_alarms(view, state)
        if view.status == "offline":  # a retained state read after the retained "offline"
            _end_active_alarms(view)
        waiting = set(state.unacknowledged)
        for code, entry in view.alarms.items():
            entry.acknowledged = entry.severity != "critical" or code not in waiting
        self._dirty.add(machine_id)
        return True

    def _sync_active_alarms(self, view: MachineView, state: StatePayload) -> None:
        """The retained state lists the active alarms: a dashboard started late (or that
        missed an event) shows them all the same, with their current text."""
        active = {a.code: a for a in state.alarms}
        for code, info in active.items():
            entry = view.alarms.get(code)
            if entry is None or not entry.active:
                view.alarms.pop(code, None)  # listed again as the newest
                view.alarms[code] = AlarmEntry(
                    code, info.severity, info.message, info.since.isoformat()
                )
            else:
                entry.message, entry.severity = info.message, info.severity
        for code in list(view.alarms):
            entry = view.alarms[code]
            if entry.active and code not in active:
                entry.active = False
                entry.cleared = entry.cleared or state.utc.isoformat()
                entry.ended = entry.ended or "cleared"

    def _seeds(self, machine_id: str, payload: bytes) -> bool:
        batch = SeedBatch.model_validate_json(payload)
        view = self.machine(machine_id)
        if not batch.records:
            return True
        if self.origin is None:
            first = batch.records[0]
            self.origin = (first.lat, first.lon)
            self._cos_lat = math.cos(math.radians(first.lat))
        lat0, lon0 = self.origin
        k = math.pi / 180.0 * EARTH_RADIUS_M
        kx = k * self._cos_lat
        records = sorted(batch.records, key=lambda r: r.id)
        fresh = [r for r in records if r.id not in view.seen and r.id > view.id_floor]
        if view.x_ref_m is None:  # the batch's own spacings count for its reference
            for rec in fresh:
                if rec.spacing_m is not None:
                    view.recent.setdefault(rec.row, deque(maxlen=QUALITY_WINDOW)).append(
                        rec.spacing_m
                    )
        refs: dict[int, float | None] = {}
        out = self._new_seeds.setdefault(machine_id, [])
        for rec in records:
            row = rec.row
            if row not in refs:
                refs[row] = view.spacing_ref(row)
            x = round((rec.lon - lon0) * kx, 3)
            y = round((rec.lat - lat0) * k, 3)
            cls = classify(rec.spacing_m, refs[row])
            if not view.add_seed(rec.id, x, y, row, cls):
                continue
            out.extend((x, y, row, cls))
            if rec.spacing_m is not None:
                acc = view.quality.get(row)
                if acc is None:
                    acc = view.quality[row] = RowQualityAccumulator(view.x_ref_m)
                with contextlib.suppress(ValueError):
                    acc.add(rec.spacing_m)
        self._dirty.add(machine_id)
        return True

    def _alarm(self, machine_id: str, payload: bytes) -> bool:
        event = AlarmEvent.model_validate_json(payload)
        view = self.machine(machine_id)
        if event.id:
            if event.id in view.alarm_ids:
                return True  # a redelivery
            view.alarm_ids.add(event.id)
        utc = event.utc.isoformat()
        entry = view.alarms.get(event.code)
        if event.active:
            if entry is None or not entry.active:
                view.alarms.pop(event.code, None)  # re-raised: listed again as the newest
                view.alarms[event.code] = AlarmEntry(event.code, event.severity,
                                                     event.message, utc)
            else:
                entry.severity, entry.message = event.severity, event.message
        elif entry is not None:
            entry.active = False
            entry.cleared = utc
            entry.message = event.message
            entry.ended = "cleared"
        else:
            view.alarms[event.code] = AlarmEntry(
                event.code, event.severity, event.message, None, utc, active=False,
                ended="cleared",
            )
        while len(view.alarms) > ALARM_HISTORY:
            oldest = next((c for c, a in view.alarms.items() if not a.active), None)
            if oldest is None:
                break
            del view.alarms[oldest]
        self._dirty.add(machine_id)
        return True

    def _ack(self, machine_id: str, name: str, payload: bytes) -> bool:
        ack = CommandAck.model_validate_json(payload)
        view = self.machine(machine_id)
        view.acks[name] = {**ack.model_dump(exclude_none=True), "at": self.clock()}
        self._pending.append({"type": "ack", "machine_id": machine_id, "command": name,
                              **view.acks[name]})
        return True

    # -- output -----------------------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """What a page that just connected needs: every machine, all its seeds."""
        return {
            "type": "snapshot",
            "broker": self.broker_message(),
            "origin": self.origin,
            "machines": {
                mid: {**view.summary(), "seeds": _interleave(view)}
                for mid, view in sorted(self.machines.items())
            },
        }

    def drain_updates(self) -> list[dict[str, Any]]:
        """What changed since the last call, as messages for the open pages."""
        out, self._pending = self._pending, []
        if self.origin is not None and self._dirty:
            out.append({"type": "origin", "origin": self.origin})
        for mid in sorted(self._dirty):
            msg: dict[str, Any] = {
                "type": "machine", **self.machines[mid].summary(whole_rate=False)
            }
            seeds = self._new_seeds.pop(mid, None)
            if seeds:
                msg["seeds"] = seeds
            out.append(msg)
        self._dirty.clear()
        self._new_seeds.clear()
        return out


def _interleave(view: MachineView) -> list[float]:
    """Seeds as one flat list x, y, row, class, x, y, ... (the page's format)."""
    out: list[float] = []
    for x, y, row, cls in zip(view.xs, view.ys, view.rows, view.classes, strict=True):
        out.extend((round(x, 3), round(y, 3), row, cls))
    return out


def encode(message: dict[str, Any]) -> str:
    return orjson.dumps(message).decode()


def _end_active_alarms(view: MachineView) -> None:
    """The box went offline: its active alarms end at the last state it sent (or now). An
    alarm active when sowgate stopped is never cleared by an event; listed as active it was
    drawn across the stop and into the next run. If the box comes back with the alarm still
    active (only the link had broken), its state lists it again as active."""
    at = view.state.get("utc") if view.state else None
    ended = str(at) if at else datetime.now(UTC).isoformat()
    for entry in view.alarms.values():
        if entry.active:
            entry.active = False
            entry.cleared = ended
            entry.ended = "offline"
