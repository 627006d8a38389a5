"""The fleet view: a day of 1 000 000 seeds from the farm database, first draw in chromium.

A fresh PostgreSQL database gets the farm server's schema (``sowgate ingest``'s migration) and
a field of ``SEEDS`` seed records, four machines side by side (12 rows at 0.75 m, 15 cm
spacing with a few percent multiples and misses), loaded with COPY as ingest would have left
them, with ingest's coverage (one machine has a gap). Then the real ``sowgate dashboard``
process with ``[farm_server] database_url`` serves it and a headless Debian chromium
(Playwright, software rendering) opens ``/?day=…``: the time from navigation to the first
canvas frame holding the whole day (``sowgate.history.draws``, ``performance.now()`` whose
origin is the navigation start) is the first draw. The server thins the day to one cell per
grid square in SQL (``gateway/dashboard/history.py``), so the page draws cells, not seeds.

Baseline, same run, same database: a plain ``SELECT lat, lon, row, spacing_m`` of the same
day's rows into Python (psycopg, binary), i.e. only fetching what an unthinned page would
need, before any JSON, transfer or drawing. ``python -m benchmarks.bench_fleet_dashboard
--quick`` runs the same with 50 000 seeds and one page load.
"""

from __future__ import annotations

import asyncio
import math
import random
import statistics
import sys
import tempfile
import time
import uuid
from datetime import UTC, date, datetime, timedelta
from pathlib import Path
from typing import Any

import psycopg

from gateway.farm_server.db import SEED_COLUMNS, migrate
from tests.browser import DashboardProcess, browser_page

SEEDS = 1_000_000
QUICK_SEEDS = 50_000
MACHINES = 4
ROWS = 12
ROW_WIDTH_M = 0.75
SPACING_M = 0.15
PASS_M = 500.0
RUNS = 5  # page loads: median and slowest are reported
TARGET_S = 2.0
DAY = date(2026, 4, 20)
LAT0, LON0 = 52.1, 13.2
K = math.pi / 180 * 6_371_008.8
ADMIN_URL = "postgresql://postgres@127.0.0.1:5432/postgres"


def rows_of(count: int) -> list[tuple[Any, ...]]:
    """``count`` seed rows in SEED_COLUMNS order (machines side by side on one field)."""
    rnd = random.Random(1)
    cos = math.cos(math.radians(LAT0))
    per_machine = count // MACHINES
    per_pass = int(PASS_M / SPACING_M)
    t0 = datetime(DAY.year, DAY.month, DAY.day, 6, tzinfo=UTC)
    out: list[tuple[Any, ...]] = []
    for m in range(MACHINES):
        mid = f"seeder-{m + 1:02d}"
        for i in range(per_machine):
            j, row = divmod(i, ROWS)
            p, k = divmod(j, per_pass)
            north = k * SPACING_M if p % 2 == 0 else PASS_M - k * SPACING_M
            east = (m * 20 + p) * ROWS * ROW_WIDTH_M + row * ROW_WIDTH_M
            spacing = rnd.choice([0.05] + [SPACING_M] * 30 + [0.3]) * rnd.gauss(1, 0.06)
            out.append((
                mid, i + 1, row + 1, t0 + timedelta(milliseconds=5 * i),
                LAT0 + north / K, LON0 + east / (K * cos), "rtk_fixed", 8.0,
                0.0 if p % 2 == 0 else 180.0, "dual_antenna", False, "interpolated",
                max(0.0, spacing), "none", None, None,
            ))
    return out


def load(url: str, count: int) -> float:
    """COPY the field into seed_records (and ingest's coverage); returns rows/s."""
    data = rows_of(count)
    names = ", ".join(f'"{n}"' for n, _ in SEED_COLUMNS)
    t0 = time.perf_counter()
    with psycopg.connect(url) as conn:
        conn.execute("SELECT sowgate_ensure_day(%s)", (DAY,))
        conn.execute(b"CREATE TEMP TABLE staging (LIKE seed_records)")
        conn.execute(b"ALTER TABLE staging DROP COLUMN geom, DROP COLUMN ingested_at")
        with conn.cursor() as cur:
            with cur.copy(f"COPY staging ({names}) FROM STDIN (FORMAT BINARY)".encode()) as cp:
                cp.set_types([kind for _, kind in SEED_COLUMNS])
                for r in data:
                    cp.write_row(r)
            cur.execute(f"INSERT INTO seed_records ({names}, geom) SELECT {names}, "
                        "ST_SetSRID(ST_MakePoint(lon, lat), 4326) FROM staging".encode())
            per = count // MACHINES
            cover = []
            for m in range(MACHINES):
                mid = f"seeder-{m + 1:02d}"
                if m == 1:  # one machine lost a stretch on the way
                    cover += [(mid, 1, 1000), (mid, 1201, per)]
                else:
                    cover.append((mid, 1, per))
            cur.executemany("INSERT INTO seed_coverage (machine_id, lo, hi) "
                            "VALUES (%s, %s, %s)", cover)
        conn.commit()
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute(b"VACUUM ANALYZE seed_records")
    return count / (time.perf_counter() - t0)


def plain_select(url: str) -> tuple[float, int]:
    """The baseline: the day's rows as an unthinned map needs them, fetched (s, rows)."""
    since = datetime(DAY.year, DAY.month, DAY.day, tzinfo=UTC)
    t0 = time.perf_counter()
    with psycopg.connect(url) as conn, conn.cursor(binary=True) as cur:
        cur.execute(b'SELECT lat, lon, "row", spacing_m FROM seed_records '
                    b"WHERE utc >= %s AND utc < %s", (since, since + timedelta(days=1)))
        n = len(cur.fetchall())
    return time.perf_counter() - t0, n


async def first_draws(url: str, seeds: int, runs: int) -> dict[str, Any]:
    """Per page load, ms from navigation to the first frame of the day (the preview of a
    big day) and to the frame of the whole day."""
    firsts: list[float] = []
    fulls: list[float] = []
    out: dict[str, Any] = {}
    async with browser_page() as page:
        for _ in range(runs):
            await page.goto(f"{url}?day={DAY.isoformat()}")
            await page.wait_for_function(
                f"window.sowgate && sowgate.history.draws.some(d => d.seeds === {seeds} "
                "&& d.complete)", timeout=300_000)
            draws = await page.evaluate("sowgate.history.draws")
            firsts.append(float(draws[0]["t"]))
            full = next(d for d in draws if d["complete"])
            fulls.append(float(full["t"]))
            out.update(first_cells=int(draws[0]["cells"]), first_seeds=int(draws[0]["seeds"]),
                       cells=int(full["cells"]))
        out["payload"] = int(await page.evaluate(
            f"fetch('/api/history/field?day={DAY.isoformat()}')"
            ".then(r => r.arrayBuffer()).then(b => b.byteLength)"))
    out.update(firsts=firsts, fulls=fulls)
    return out


async def _measure(seeds: int, runs: int) -> dict[str, Any]:
    name = f"sowgate_bench_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"'.encode())
    url = f"postgresql://postgres@127.0.0.1:5432/{name}"
    fig: dict[str, Any] = {"seeds": seeds, "runs": runs}
    try:
        migrate(url)
        fig["copy_rows_s"] = load(url, seeds)
        selects = [plain_select(url) for _ in range(3)]
        fig["select_s"] = statistics.median(s for s, _ in selects)
        assert selects[0][1] == seeds, selects
        with tempfile.TemporaryDirectory(prefix="sowgate-bench-fleet-") as tmp:
            config = Path(tmp) / "sowgate.toml"
            config.write_text(f'[machine]\nid = "seeder-01"\n[positioning]\n'
                              f'target_spacing_m = {SPACING_M}\n[mqtt]\nport = 1\n'
                              f'[farm_server]\ndatabase_url = "{url}"\n')
            dash = DashboardProcess(config, Path(tmp) / "dashboard.log")
            await dash.start()
            try:
                t0 = time.perf_counter()
                d = await first_draws(dash.url, seeds, runs)
                fig["wall_s"] = time.perf_counter() - t0
            finally:
                await dash.stop()
        fig.update(first_ms=statistics.median(d["firsts"]), first_max_ms=max(d["firsts"]),
                   first_all_ms=d["firsts"], full_ms=statistics.median(d["fulls"]),
                   full_max_ms=max(d["fulls"]), full_all_ms=d["fulls"], cells=d["cells"],
                   first_cells=d["first_cells"], first_seeds=d["first_seeds"],
                   payload_mb=d["payload"] / 1e6)
    finally:
        with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'.encode())
    return fig


def run(seeds: int = SEEDS, runs: int = RUNS) -> dict[str, object]:
    f = asyncio.run(_measure(seeds, runs))
    loadavg = Path("/proc/loadavg")
    f["load_avg"] = loadavg.read_text().split()[0] if loadavg.exists() else "?"
    ratio = f["first_ms"] / 1000 / f["select_s"]
    met = "met" if f["first_max_ms"] <= TARGET_S * 1000 else "NOT met"
    fig: dict[str, object] = dict(f, ratio=ratio)
    fig["markdown"] = (
        f"### Fleet dashboard: a day of {seeds:,} seeds from the farm database, headless "
        "chromium\n\n"
        f"{seeds:,} seed records of {MACHINES} machines on one field ({ROWS} rows each) in a "
        f"fresh PostgreSQL with the farm server's schema (COPY: {f['copy_rows_s']:,.0f} "
        "rows/s with the point column); the real `sowgate dashboard` with `[farm_server] "
        "database_url`, Debian chromium headless (`--disable-gpu`): navigation → page → "
        "`/api/history/field?day=…` (the server counts the seeds on a "
        "grid of squares in SQL and returns one cell per occupied square) → first canvas "
        f"frame with the whole day. Median of {runs} page loads.\n\n"
        "| | median | slowest |\n|---|---|---|\n"
        f"| baseline: plain `SELECT lat, lon, row, spacing_m` of the day's rows into Python "
        f"(no JSON, no transfer, no drawing) | {f['select_s'] * 1000:.0f} ms | |\n"
        f"| first draw (a page sample of the day: {f['first_seeds']:,} seeds in "
        f"{f['first_cells']:,} cells) | {f['first_ms']:.0f} ms | {f['first_max_ms']:.0f} ms |\n"
        f"| the whole day drawn ({seeds:,} seeds in {f['cells']:,} cells) | "
        f"{f['full_ms']:.0f} ms | {f['full_max_ms']:.0f} ms |\n\n"
        f"The first draw takes {ratio:.2f} × the plain SELECT of the same rows, the whole "
        f"day {f['full_ms'] / 1000 / f['select_s']:.2f} ×; the whole day's map is "
        f"{f['payload_mb']:.1f} MB of JSON. Target ≤ {TARGET_S:g} s to the first draw "
        f"(slowest load): {met}. Load average of the machine at the end: {f['load_avg']} "
        "(other work shares its 2 cores). The first draw is a preview: on a day of more than "
        "80 000 rows the server first reads a `TABLESAMPLE SYSTEM` page sample of about "
        "40 000 rows and grids it (its cost does not grow with the day), then the whole "
        "day; the whole day's grid query reads every row of it, so its time grows with the "
        "seeds. Would "
        "break it: a slower database server, or a whole day wanted at once; the next step "
        "would be per-day cells kept by ingest (pre-aggregated tiles).\n"
    )
    return fig


if __name__ == "__main__":
    quick = "--quick" in sys.argv[1:]
    result = run(QUICK_SEEDS, 1) if quick else run()
    print(result["markdown"])
