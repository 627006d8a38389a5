"""The fleet view: any field and day from the farm server's PostgreSQL, beside the live machines.

``sowgate dashboard`` with ``[farm_server] database_url`` (or ``--database``) answers four GET
requests, behind the same guard as the rest of the page (allowed hosts, the page's own Origin,
the password):

- ``/api/history/days``: the days the database holds (its day partitions), newest first;
- ``/api/history/field?day=YYYY-MM-DD[&machine=ID,...]``: every machine's seeds of that day on
  one map, thinned on the server: the seeds are counted on a square grid of ``GRID_CELLS``
  cells across the field (SQL ``GROUP BY`` of the cell), and each occupied cell comes back
  once, with its machine and the spacing class most of its seeds have. A million seeds are a
  few hundred thousand cells at most, whatever the number of seeds; per machine, the seed
  count, the time span, and the gaps ingest knows (ids below the highest committed one that
  are not in the database: ``seed_coverage``);
- ``/api/history/quality?day=...&machine=ID``: that machine's per-row ISO 7256-1 spacing
  quality over the day, with the accumulators ``sowgate export`` uses (the config's target
  spacing for this machine, else each row's recent median, as export does);
- ``/api/history/alarms?day=...``: the alarm events of the day, every machine, for the timeline.

Every parameter is parsed and checked before a query (a bad one is a 400 saying which and
why) and reaches PostgreSQL as a bound parameter: no SQL is built from request text. The
queries run in a worker thread on their own read-only connection, so a long one never holds
up the live WebSocket.
"""

from __future__ import annotations

import collections
import math
import re
import statistics
from dataclasses import dataclass
from datetime import UTC, date, datetime, timedelta
from typing import Any

import psycopg
from psycopg.rows import TupleRow

from gateway.recording.id_ranges import IdRanges
from gateway.recording.spacing_quality import MISS_LIMIT, MULTIPLE_LIMIT, RowQualityAccumulator

GRID_CELLS = 600  # cells across the longer side of the field: about one per screen pixel
MAX_MACHINES = 100  # machines one request may name
MAX_ALARMS = 5000  # alarm events one day returns (the rest are counted)
PREVIEW_ROWS = 40_000  # rows (about) of a preview's page sample (the first draw of a big day)
SAMPLE_ROWS = 20_000  # rows (about) of the page sample giving the extent and the medians
R_EARTH_M = 6_371_008.8
MACHINE = re.compile(r"[A-Za-z0-9_.-]{1,64}")
DAY = re.compile(r"\d{4}-\d{2}-\d{2}")
CLASS_UNKNOWN, CLASS_MULTIPLE, CLASS_GOOD, CLASS_MISS = 0, 1, 2, 3


class BadRequest(ValueError):
    """A query parameter that is not what the endpoint takes (the 400's message)."""


@dataclass(frozen=True)
class Window:
    day: date
    since: datetime
    until: datetime


def parse_day(params: dict[str, str]) -> Window:
    text = params.get("day")
    if text is None:
        raise BadRequest("day: required, a date as YYYY-MM-DD (UTC), e.g. day=2026-04-20")
    if not DAY.fullmatch(text):
        raise BadRequest(f"day: not a date as YYYY-MM-DD: {text[:40]!r}")
    try:
        day = date.fromisoformat(text)
    except ValueError as exc:
        raise BadRequest(f"day: not a calendar date: {text!r} ({exc})") from None
    since = datetime(day.year, day.month, day.day, tzinfo=UTC)
    return Window(day, since, since + timedelta(days=1))


def parse_machines(params: dict[str, str], required: bool = False) -> list[str] | None:
    text = params.get("machine")
    if text is None or text == "":
        if required:
            raise BadRequest("machine: required, a machine id ([A-Za-z0-9_.-], 1..64)")
        return None
    ids = text.split(",")
    if len(ids) > MAX_MACHINES:
        raise BadRequest(f"machine: at most {MAX_MACHINES} machine ids (got {len(ids)})")
    bad = [m for m in ids if not MACHINE.fullmatch(m)]
    if bad:
        raise BadRequest(f"machine: not a machine id ([A-Za-z0-9_.-], 1..64 characters): "
                         f"{bad[0][:70]!r}")
    if required and len(ids) != 1:
        raise BadRequest("machine: one machine id")
    return ids


def check_params(params: dict[str, str], allowed: set[str]) -> None:
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise BadRequest(f"{unknown[0][:40]}: not a parameter of this request "
                         f"(it takes {', '.join(sorted(allowed)) or 'none'})")


def gaps_text(machine_id: str, gaps: list[tuple[int, int]]) -> str:
    """``seeder-03: records 18 200–18 340 not received yet`` (as ``sowgate ingest`` logs)."""
    if not gaps:
        return f"{machine_id}: every record up to the newest received"

    def n(i: int) -> str:
        return f"{i:,}".replace(",", " ")
    runs = ", ".join(n(lo) if lo == hi else f"{n(lo)}–{n(hi)}" for lo, hi in gaps[:10])
    more = f" and {len(gaps) - 10} more runs" if len(gaps) > 10 else ""
    return f"{machine_id}: records {runs}{more} not received yet"


class History:
    """The farm database, read for the page (each call its own short read-only connection)."""

    def __init__(self, url: str, target_spacing: dict[str, float] | None = None) -> None:
        self.url = url
        self.target_spacing = target_spacing or {}  # machine id -> configured target (m)

    def _connect(self) -> psycopg.Connection[TupleRow]:
        conn = psycopg.connect(self.url, connect_timeout=10, options="-c TimeZone=UTC")
        conn.read_only = True
        return conn

    def days(self) -> list[str]:
        with self._connect() as conn:
            names = conn.execute(
                "SELECT c.relname FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid "
                "WHERE i.inhparent = 'seed_records'::regclass").fetchall()
        days = sorted({f"{m[1]}-{m[2]}-{m[3]}" for (name,) in names
                       if (m := re.fullmatch(r"seed_records_(\d{4})(\d{2})(\d{2})", name))},
                      reverse=True)
        return days

    def field(self, window: Window, machines: list[str] | None,
              preview: bool = False) -> dict[str, Any]:
        """Every machine's seeds of the day as grid cells, and each machine's figures.

        One pass over the day's rows: a small page sample (``TABLESAMPLE SYSTEM``, about
        ``SAMPLE_ROWS`` rows) gives the field's extent, hence the cell size, and each
        machine's median spacing (its reference without a configured target); then one
        ``GROUP BY`` of the cell counts the seeds per cell and class, with each cell's first
        and last time, from which the machines' counts and spans are summed. A machine the
        sample missed (a few seeds that day) gets its own exact reference and pass.

        ``preview``: on a day of more than ``2 * PREVIEW_ROWS`` rows, the cells of a page
        sample of about ``PREVIEW_ROWS`` rows only (``complete`` false, ``sample_pct``): the
        page draws it at once and asks for the whole day next (``_preview``)."""
        if preview:
            quick = self._preview(window, machines)
            if quick is not None:
                return quick
        p: dict[str, Any] = {"since": window.since, "until": window.until,
                             "machines": machines}
        where = ("utc >= %(since)s AND utc < %(until)s AND "
                 "(%(machines)s::text[] IS NULL OR machine_id = ANY(%(machines)s))")
        out: dict[str, Any] = {"day": window.day.isoformat(), "machines": [], "cells": [],
                               "cell_m": None, "origin": None, "extent_cells": [0, 0],
                               "seeds": 0, "complete": True, "sample_pct": 100.0}
        with self._connect() as conn:
            row = conn.execute(
                b"SELECT reltuples FROM pg_class WHERE oid = to_regclass(%s)",
                (f"seed_records_{window.day:%Y%m%d}",)).fetchone()
            if row is None:
                return out  # no partition: nothing on that day
            rows = float(row[0])
            pct = 100.0 if rows < 2 * SAMPLE_ROWS else max(0.5, 100.0 * SAMPLE_ROWS / rows)
            sample = self._sample(conn, where, p, pct)
            cut = 100.0
            if not sample and pct < 100:
                sample = self._sample(conn, where, p, 100.0)
            if not sample:
                return out
            lat0 = min(s[1] for s in sample.values())
            lon0 = min(s[3] for s in sample.values())
            ky = math.pi / 180 * R_EARTH_M
            kx = ky * math.cos(math.radians(lat0))
            extent = max(max((s[2] - lat0) * ky, (s[4] - lon0) * kx) for s in sample.values())
            cell = max(0.05, 1.02 * extent / GRID_CELLS)
            grid = {"lon0": lon0, "lat0": lat0, "kx": kx / cell, "ky": ky / cell}
            refs = {mid: self.target_spacing.get(mid, s[5]) for mid, s in sample.items()}
            cells = self._cells(conn, where, {**p, **grid}, refs, others=True, pct=cut)
            missed = sorted({c[2] for c in cells} - set(refs))
            if missed:  # machines the sample missed: exact reference, their own pass
                cells = [c for c in cells if c[2] in refs]
                q = {**p, "machines": missed}
                for mid, s in self._sample(conn, where, q, 100.0).items():
                    refs[mid] = self.target_spacing.get(mid, s[5])
                cells += self._cells(conn, where, {**q, **grid}, refs, others=False,
                                     pct=cut)
            ids = sorted(refs)
            coverage: dict[str, list[tuple[int, int]]] = {mid: [] for mid in ids}
            for mid, lo, hi in conn.execute(
                    b"SELECT machine_id, lo, hi FROM seed_coverage "
                    b"WHERE machine_id = ANY(%s) ORDER BY machine_id, lo", (ids,)):
                coverage[mid].append((int(lo), int(hi)))
        index = {mid: k for k, mid in enumerate(ids)}
        ix0 = min(c[0] for c in cells)
        iy0 = min(c[1] for c in cells)
        flat: list[int] = []
        per: dict[str, list[Any]] = {}
        for ix, iy, mid, cls, n, first, last in cells:
            flat.extend((ix - ix0, iy - iy0, index[mid], cls))
            m = per.get(mid)
            if m is None:
                per[mid] = [n, first, last]
            else:
                m[0] += n
                m[1] = min(m[1], first)
                m[2] = max(m[2], last)
        out.update(cells=flat, cell_m=cell, complete=cut >= 100, sample_pct=cut,
                   origin=[lat0 + iy0 * cell / ky, lon0 + ix0 * cell / kx],
                   extent_cells=[max(c[0] for c in cells) - ix0,
                                 max(c[1] for c in cells) - iy0],
                   seeds=sum(m[0] for m in per.values()))
        for mid in ids:
            n, first, last = per[mid]
            covered = coverage[mid]  # ingest's committed ids: what is missing below the top
            gaps = list(IdRanges(covered).gaps(0, covered[-1][1])) if covered else []
            out["machines"].append({
                "machine_id": mid, "seeds": int(n),
                "first_utc": _iso(first), "last_utc": _iso(last),
                "x_ref_m": refs[mid], "target_configured": mid in self.target_spacing,
                "gaps": [[lo, hi] for lo, hi in gaps[:100]], "gap_runs": len(gaps),
                "gaps_text": gaps_text(mid, gaps),
            })
        return out

    def _preview(self, window: Window, machines: list[str] | None) -> dict[str, Any] | None:
        """A big day's first draw: one read of a page sample of about ``PREVIEW_ROWS`` rows
        (``TABLESAMPLE SYSTEM``: only those pages are read, so its cost does not grow with
        the day), gridded and classed here. None when the day is small enough to be read
        whole at once (or the sample came back empty)."""
        p: dict[str, Any] = {"since": window.since, "until": window.until,
                             "machines": machines}
        with self._connect() as conn:
            row = conn.execute(
                b"SELECT reltuples FROM pg_class WHERE oid = to_regclass(%s)",
                (f"seed_records_{window.day:%Y%m%d}",)).fetchone()
            if row is None or float(row[0]) < 2 * PREVIEW_ROWS:
                return None
            pct = max(0.5, 100.0 * PREVIEW_ROWS / float(row[0]))
            with conn.cursor(binary=True) as cur:
                cur.execute((
                    "SELECT machine_id, lat, lon, spacing_m FROM seed_records "
                    f"TABLESAMPLE SYSTEM ({pct:.3f}) REPEATABLE (1) WHERE utc >= %(since)s "
                    "AND utc < %(until)s AND (%(machines)s::text[] IS NULL OR "
                    "machine_id = ANY(%(machines)s))").encode(), p)
                sample = cur.fetchall()
        if not sample:
            return None
        lat0 = min(r[1] for r in sample)
        lon0 = min(r[2] for r in sample)
        ky = math.pi / 180 * R_EARTH_M
        kx = ky * math.cos(math.radians(lat0))
        extent = max((max(r[1] for r in sample) - lat0) * ky,
                     (max(r[2] for r in sample) - lon0) * kx)
        cell = max(0.05, 1.02 * extent / GRID_CELLS)
        ids = sorted({r[0] for r in sample})
        index = {mid: k for k, mid in enumerate(ids)}
        spacings: dict[str, list[float]] = {mid: [] for mid in ids}
        for r in sample:
            if r[3] is not None:
                spacings[r[0]].append(r[3])
        refs = {mid: self.target_spacing.get(mid) or (statistics.median(spacings[mid])
                                                      if spacings[mid] else None)
                for mid in ids}
        counts: dict[tuple[int, int, int], list[int]] = {}
        fx, fy = kx / cell, ky / cell
        for mid, lat, lon, spacing in sample:
            key = (math.floor((lon - lon0) * fx), math.floor((lat - lat0) * fy), index[mid])
            c = counts.get(key)
            if c is None:
                c = counts[key] = [0, 0, 0, 0]  # unknown, multiple, good, miss
            ref = refs[mid]
            c[CLASS_UNKNOWN if spacing is None or ref is None else
              CLASS_MULTIPLE if spacing <= MULTIPLE_LIMIT * ref else
              CLASS_MISS if spacing > MISS_LIMIT * ref else CLASS_GOOD] += 1
        flat: list[int] = []
        # the class most of the cell's seeds have (ties: good, miss, multiple, unknown)
        order = (CLASS_GOOD, CLASS_MISS, CLASS_MULTIPLE, CLASS_UNKNOWN)
        for (ix, iy, k), c in counts.items():
            flat.extend((ix, iy, k, max(order, key=lambda cls: (c[cls], -order.index(cls)))))
        per = collections.Counter(r[0] for r in sample)
        return {"day": window.day.isoformat(), "cells": flat, "cell_m": cell,
                "origin": [lat0, lon0], "complete": False, "sample_pct": pct,
                "extent_cells": [max(k[0] for k in counts), max(k[1] for k in counts)],
                "seeds": len(sample),
                "machines": [{"machine_id": mid, "seeds": per[mid], "x_ref_m": refs[mid],
                              "target_configured": mid in self.target_spacing}
                             for mid in ids]}

    @staticmethod
    def _sample(conn: psycopg.Connection[TupleRow], where: str, p: dict[str, Any],
                pct: float) -> dict[str, tuple[Any, ...]]:
        """Per machine: (n, min lat, max lat, min lon, max lon, median spacing) of a sample
        of ``pct`` % of the day's pages (all of them at 100)."""
        sample = "" if pct >= 100 else f"TABLESAMPLE SYSTEM ({float(pct):.3f}) REPEATABLE (1) "
        rows = conn.execute((
            "SELECT machine_id, count(*), min(lat), max(lat), min(lon), max(lon), "
            "percentile_cont(0.5) WITHIN GROUP (ORDER BY spacing_m) "
            f"FROM seed_records {sample}WHERE {where} GROUP BY machine_id "
            f"ORDER BY machine_id LIMIT {MAX_MACHINES}").encode(), p).fetchall()
        return {r[0]: tuple(r[1:]) for r in rows}

    @staticmethod
    def _cells(conn: psycopg.Connection[TupleRow], where: str, p: dict[str, Any],
               refs: dict[str, float | None], *, others: bool,
               pct: float = 100.0) -> list[tuple[Any, ...]]:
        """(ix, iy, machine, class, seeds, first utc, last utc) per occupied cell; with
        ``others`` the machines without a reference come too (classed unknown)."""
        ids = sorted(refs)
        join = "LEFT JOIN" if others else "JOIN"
        sample = "" if pct >= 100 else f"TABLESAMPLE SYSTEM ({float(pct):.3f}) REPEATABLE (2) "
        return conn.execute((
            "WITH refs AS (SELECT * FROM unnest(%(ids)s::text[], %(refs)s::float8[]) "
            "AS r(machine_id, ref)) "
            "SELECT ix, iy, machine_id, CASE "
            " WHEN n - n0 - n1 - n3 >= greatest(n0, n1, n3) THEN 2"
            " WHEN n3 >= greatest(n0, n1) THEN 3 WHEN n1 >= n0 THEN 1 ELSE 0 END, "
            "n, t0, t1 "
            "FROM (SELECT floor((s.lon - %(lon0)s) * %(kx)s)::int AS ix, "
            "floor((s.lat - %(lat0)s) * %(ky)s)::int AS iy, s.machine_id, count(*) AS n, "
            "count(*) FILTER (WHERE s.spacing_m IS NULL OR r.ref IS NULL) AS n0, "
            f"count(*) FILTER (WHERE s.spacing_m <= {MULTIPLE_LIMIT} * r.ref) AS n1, "
            f"count(*) FILTER (WHERE s.spacing_m > {MISS_LIMIT} * r.ref) AS n3, "
            "min(s.utc) AS t0, max(s.utc) AS t1 "
            f"FROM seed_records s {sample}{join} refs r USING (machine_id) WHERE {where} "
            "GROUP BY 1, 2, 3) g").encode(),
            {**p, "ids": ids, "refs": [refs[m] for m in ids]}).fetchall()

    def quality(self, window: Window, machine: str) -> dict[str, Any]:
        """Per-row spacing quality of one machine over the day (export's accumulators)."""
        target = self.target_spacing.get(machine)
        acc: dict[int, RowQualityAccumulator] = {}
        n = 0
        with self._connect() as conn, conn.cursor(name="sowgate_quality") as cur:
            cur.itersize = 20_000
            cur.execute(
                b'SELECT "row", spacing_m FROM seed_records WHERE machine_id = %s AND '
                b"utc >= %s AND utc < %s AND spacing_m IS NOT NULL ORDER BY id",
                (machine, window.since, window.until))
            while chunk := cur.fetchmany(20_000):
                by_row: dict[int, list[float]] = {}
                for row, spacing in chunk:
                    by_row.setdefault(row, []).append(spacing)
                for row, spacings in by_row.items():
                    a = acc.get(row)
                    if a is None:
                        a = acc[row] = RowQualityAccumulator(target)
                    a.add_many(spacings)
                n += len(chunk)
        return {"machine_id": machine, "day": window.day.isoformat(), "spacings": n,
                "x_ref_m": target,
                "rows": {str(r): a.result().as_dict() for r, a in sorted(acc.items())}}

    def alarms(self, window: Window, machines: list[str] | None) -> dict[str, Any]:
        p = {"since": window.since, "until": window.until, "machines": machines}
        with self._connect() as conn:
            rows = conn.execute(
                b"SELECT machine_id, id, utc, code, active, severity, message, "
                b"count(*) OVER () FROM alarm_events WHERE utc >= %(since)s AND "
                b"utc < %(until)s AND (%(machines)s::text[] IS NULL OR "
                b"machine_id = ANY(%(machines)s)) ORDER BY utc, machine_id, id "
                b"LIMIT " + str(MAX_ALARMS).encode(), p).fetchall()
        return {"day": window.day.isoformat(), "total": int(rows[0][7]) if rows else 0,
                "events": [{"machine_id": r[0], "id": r[1], "utc": _iso(r[2]), "code": r[3],
                            "active": r[4], "severity": r[5], "message": r[6]}
                           for r in rows]}


def _iso(t: datetime) -> str:
    return t.astimezone(UTC).isoformat().replace("+00:00", "Z")
