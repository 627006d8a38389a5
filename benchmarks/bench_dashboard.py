"""The dashboard's seed map: 100 000 seeds replayed, time to the first full draw in chromium.

Seed batches as the daemon publishes them (500 records, QoS 1) go through a real mosquitto to
the real ``sowgate dashboard`` process; then a headless Debian chromium (Playwright, software
rendering) opens the page and the time from navigation to the first canvas frame holding every
seed is read from the page (``performance.now()``, whose origin is the navigation start). The
baseline is the same page, same run, with 10 000 seeds of another machine; a redraw (panning,
following the machine) is timed too, since that is what "smooth" means to the driver.

The field is synthetic (straight passes of a 12-row planter at 0.75 m, 15 cm spacing with a
few percent multiples and misses): the page's cost depends on the number of seeds, not on
where they lie.
"""

from __future__ import annotations

import asyncio
import math
import random
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import aiomqtt
import orjson

from tests.browser import DashboardProcess, browser_page
from tests.mosquitto import Mosquitto

BIG = 100_000
BASELINE = 10_000
BATCH = 500
ROWS = 12
ROW_WIDTH_M = 0.75
SPACING_M = 0.15
PASS_M = 400.0
TARGET_S = 2.0
REDRAWS = 30
RUNS = 5  # page loads per size: the median is reported
LAT0, LON0 = 52.1, 13.2
K = math.pi / 180 * 6_371_008.8


def records(machine_id: str, count: int, seed: int) -> list[dict[str, Any]]:
    rnd = random.Random(seed)
    out: list[dict[str, Any]] = []
    per_row = count // ROWS + 1
    per_pass = int(PASS_M / SPACING_M)
    cos = math.cos(math.radians(LAT0))
    for i in range(per_row):
        p, j = divmod(i, per_pass)
        north = j * SPACING_M if p % 2 == 0 else PASS_M - j * SPACING_M
        for row in range(1, ROWS + 1):
            if len(out) == count:
                return out
            east = p * ROWS * ROW_WIDTH_M + (row - 1) * ROW_WIDTH_M
            spacing = rnd.choice([0.05] + [SPACING_M] * 30 + [0.3]) + rnd.gauss(0, 0.01)
            out.append({
                "id": len(out) + 1, "machine_id": machine_id, "row": row,
                "utc": f"2026-04-20T08:{(i // 600) % 60:02d}:{(i // 10) % 60:02d}."
                       f"{(i % 10) * 100000:06d}Z",
                "lat": LAT0 + north / K, "lon": LON0 + east / (K * cos), "fix": "rtk_fixed",
                "speed_kmh": 8.0, "heading_deg": 0.0 if p % 2 == 0 else 180.0,
                "heading_source": "dual_antenna", "extrapolated": False,
                "method": "interpolated", "spacing_m": round(max(0.0, spacing), 4),
            })
    return out


async def publish(port: int, machine_id: str, count: int, seed: int) -> None:
    recs = records(machine_id, count, seed)
    async with aiomqtt.Client("127.0.0.1", port, identifier=f"bench-{machine_id}") as client:
        await client.publish(f"sowgate/{machine_id}/status", b"online", qos=1, retain=True)
        for i in range(0, len(recs), BATCH):
            payload = orjson.dumps({"machine_id": machine_id, "records": recs[i:i + BATCH]})
            await client.publish(f"sowgate/{machine_id}/seeds", payload, qos=1)


async def health(page: Any) -> dict[str, Any]:
    return dict(await page.evaluate("fetch('/api/health').then(r => r.json())"))


async def first_full_draw(page: Any, url: str, count: int) -> tuple[float, list[float]]:
    """(ms from navigation to the first frame with ``count`` seeds, redraw times in ms)."""
    await page.goto(url)
    await page.wait_for_function(
        f"window.sowgate && sowgate.draws.some(d => d.seeds === {count})", timeout=60_000
    )
    first = float(await page.evaluate(
        f"sowgate.draws.find(d => d.seeds === {count}).t"
    ))
    redraws: list[float] = []
    for _ in range(REDRAWS):
        ms = await page.evaluate("""() => new Promise(done => {
            const n = sowgate.draws.length;
            sowgate.dirty = true;
            const wait = () => sowgate.draws.length > n
                ? done(sowgate.draws[sowgate.draws.length - 1].ms) : requestAnimationFrame(wait);
            requestAnimationFrame(wait);
        })""")
        redraws.append(float(ms))
    return first, redraws


async def _measure() -> dict[str, Any]:
    fig: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="sowgate-bench-dash-") as tmp, Mosquitto() as broker:
        config = Path(tmp) / "sowgate.toml"
        config.write_text(f"[mqtt]\nport = {broker.port}\n[dashboard]\nmax_seeds = 200000\n")
        dash = DashboardProcess(config, Path(tmp) / "dashboard.log")
        await dash.start()
        try:
            async with browser_page() as page:
                await page.goto(dash.url)
                ingest = 0.0
                # the baseline first, alone on the dashboard; then the big field joins it (the
                # page's snapshot then holds both: 110 000 seeds)
                for name, count, wanted in (("base", BASELINE, {"base": BASELINE}),
                                            ("big", BIG, {"base": BASELINE, "big": BIG})):
                    t0 = time.perf_counter()
                    await publish(broker.port, name, count, len(wanted))
                    deadline = time.monotonic() + 120
                    while (await health(page))["machines"] != wanted:
                        if time.monotonic() > deadline:
                            raise RuntimeError(f"dashboard has {await health(page)}")
                        await asyncio.sleep(0.1)
                    ingest += time.perf_counter() - t0
                    firsts, redraws = [], []
                    for _ in range(RUNS):
                        first, frames = await first_full_draw(
                            page, f"{dash.url}?machine={name}&view=field", count)
                        firsts.append(first)
                        redraws += frames
                    fig[f"{name}_first_ms"] = statistics.median(firsts)
                    fig[f"{name}_first_max_ms"] = max(firsts)
                    fig[f"{name}_redraw_p50_ms"] = statistics.median(redraws)
                    fig[f"{name}_redraw_p95_ms"] = sorted(redraws)[int(0.95 * len(redraws))]
                fig["ingest_s"] = ingest
                snap = await page.evaluate(
                    "new Promise(done => { const ws = new WebSocket(`ws://${location.host}/ws`);"
                    " let n = 0; ws.onmessage = e => { n += e.data.length;"
                    " if (JSON.parse(e.data).type === 'snapshot') { ws.close(); done(n); } }; })"
                )
                fig["snapshot_mb"] = float(snap) / 1e6
        finally:
            await dash.stop()
    return fig


def run() -> dict[str, object]:
    f = asyncio.run(_measure())
    ratio = f["big_first_ms"] / f["base_first_ms"]
    met = "met" if f["big_first_max_ms"] <= TARGET_S * 1000 else "NOT met"
    fig: dict[str, object] = dict(f, ratio=ratio)
    fig["markdown"] = (
        "### Dashboard: 100 000 seeds on the map, headless chromium\n\n"
        f"{BIG:,} and {BASELINE:,} synthetic seeds ({ROWS} rows, {BATCH}-record batches, "
        "QoS 1) published through mosquitto to the real `sowgate dashboard` process "
        f"(ingested, deduplicated and classed in {f['ingest_s']:.1f} s for both); then Debian "
        "chromium (headless, `--disable-gpu`: software rendering) loads the page: "
        "navigation → WebSocket snapshot → first canvas frame holding every seed, the whole "
        f"field in view (every seed on screen). Median of {RUNS} page loads; a redraw is one "
        f"more frame of that view ({REDRAWS} per load).\n\n"
        "| seeds | first full draw (median) | slowest load | redraw p50 | redraw p95 |\n"
        "|---|---|---|---|---|\n"
        f"| {BASELINE:,} (baseline) | {f['base_first_ms']:.0f} ms | "
        f"{f['base_first_max_ms']:.0f} ms | {f['base_redraw_p50_ms']:.1f} ms | "
        f"{f['base_redraw_p95_ms']:.1f} ms |\n"
        f"| {BIG:,} | {f['big_first_ms']:.0f} ms | {f['big_first_max_ms']:.0f} ms | "
        f"{f['big_redraw_p50_ms']:.1f} ms | {f['big_redraw_p95_ms']:.1f} ms |\n\n"
        f"{BIG:,} seeds take {ratio:.2f} × the baseline's time to first full draw (the "
        f"baseline alone on the dashboard, the {BIG:,} next to it: a snapshot of "
        f"{BIG + BASELINE:,} seeds; the baseline's time is mostly the page load itself, what the "
        "big field adds is the snapshot's transfer and parse). Target "
        f"≤ {TARGET_S:g} s to the first full draw (slowest load): {met}. The page's snapshot "
        f"(both machines, all seeds, JSON) is {f['snapshot_mb']:.1f} MB: its transfer and "
        "parse grow with the seeds kept (`[dashboard] max_seeds`, 300 000 by default), the "
        "draw itself (one ImageData pass) stays a few milliseconds. Would break it: a "
        "slower cab tablet than this 2-core sandbox, or `max_seeds` raised far above the "
        "default (a million seeds is about 10 × this snapshot).\n"
    )
    return fig


if __name__ == "__main__":
    print(run()["markdown"])
