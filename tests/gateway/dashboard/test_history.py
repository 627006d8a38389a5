"""The fleet view: ``sowgate dashboard`` with a farm database shows any day of every machine
(map thinned on the server, machines with their gaps, per-row quality, alarms), behind the
dashboard's guard, with every parameter checked (real dashboard process, real PostgreSQL,
real chromium)."""

from __future__ import annotations

import base64
import json
import random
import urllib.error
import urllib.request
from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from gateway.core.records import AlarmEvent, SeedRecord
from gateway.dashboard.history import GRID_CELLS
from gateway.farm_server.db import IngestDatabase
from gateway.recording.database_source import DatabaseSource
from gateway.recording.export import quality_by_row_chunks
from tests.browser import DashboardProcess, browser_page

T0 = datetime(2026, 4, 20, 7, 0, tzinfo=UTC)
DAY = "2026-04-20"


def seeds(machine: str, n: int, east_m: float, skip: range = range(0)) -> list[SeedRecord]:
    rnd = random.Random(machine)
    out = []
    for i in range(1, n + 1):
        if i in skip:
            continue
        j = i // 6
        out.append(SeedRecord(
            id=i, machine_id=machine, row=1 + i % 6, utc=T0 + timedelta(milliseconds=20 * i),
            lat=52.0 + j * 0.2 / 111_195, lon=13.0 + (east_m + (i % 6) * 0.75) / 68_450,
            fix="rtk_fixed", speed_kmh=8.0,
            spacing_m=None if i <= 6 else max(0.01, rnd.choice([0.07] + [0.2] * 18 + [0.45])
                                               * rnd.gauss(1, 0.05))))
    return out


def fill(url: str) -> None:
    db = IngestDatabase(url)
    try:
        db.write_seeds("seeder-01", seeds("seeder-01", 3000, 0.0))
        # seeder-02 lost 1 001..1 200 on the way: ingest's coverage has the gap
        db.write_seeds("seeder-02", seeds("seeder-02", 2400, 30.0, range(1001, 1201)))
        db.write_alarms([
            AlarmEvent(id=1, machine_id="seeder-02", code="radar.lost", active=True,
                       severity="critical", message="radar <b>lost</b>",
                       utc=T0 + timedelta(seconds=10)),
            AlarmEvent(id=2, machine_id="seeder-02", code="radar.lost", active=False,
                       severity="critical", message="radar back",
                       utc=T0 + timedelta(seconds=20)),
            AlarmEvent(id=1, machine_id="seeder-01", code="row.3.blocked", active=True,
                       severity="warning", message="row 3 blocked",
                       utc=T0 + timedelta(seconds=30)),
        ])
    finally:
        db.close()


def get(url: str, headers: dict[str, str] | None = None) -> tuple[int, Any]:
    req = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=30) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        body = exc.read()
        try:
            return exc.code, json.loads(body)
        except ValueError:
            return exc.code, body.decode()


@pytest.fixture
async def dashboard(tmp_path: Path, database: str) -> AsyncIterator[DashboardProcess]:
    fill(database)
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(f'[machine]\nid = "seeder-01"\n[positioning]\ntarget_spacing_m = 0.2\n'
                   f'[mqtt]\nport = 1\n[farm_server]\ndatabase_url = "{database}"\n')
    dash = DashboardProcess(cfg, tmp_path / "dashboard.log")
    await dash.start()
    try:
        yield dash
    finally:
        await dash.stop()


async def test_a_day_of_the_fleet_comes_back_thinned_with_gaps_quality_and_alarms(
        dashboard: DashboardProcess, database: str) -> None:
    base = dashboard.url + "api/history/"
    assert get(base + "days") == (200, {"days": [DAY]})
    status, field = get(base + f"field?day={DAY}")
    assert status == 200
    assert field["seeds"] == 3000 + 2200 and field["complete"] is True
    # a day this small is whole even when a preview is asked for
    assert get(base + f"field?day={DAY}&preview=1")[1] == field
    one, two = field["machines"]
    assert (one["machine_id"], one["seeds"], one["gap_runs"]) == ("seeder-01", 3000, 0)
    assert (two["machine_id"], two["seeds"], two["gaps"]) == ("seeder-02", 2200, [[1001, 1200]])
    assert two["gaps_text"] == "seeder-02: records 1 001–1 200 not received yet"
    assert one["x_ref_m"] == 0.2 and one["target_configured"]  # the config's own machine
    assert 0.15 < two["x_ref_m"] < 0.25 and not two["target_configured"]  # its median
    cells = field["cells"]
    n = len(cells) // 4
    assert 100 < n <= 5200  # a cell per occupied square (the benchmark: 1 M seeds, fewer)
    assert {cells[i + 2] for i in range(0, len(cells), 4)} == {0, 1}  # both machines
    assert {cells[i + 3] for i in range(0, len(cells), 4)} <= {0, 1, 2, 3}
    assert max(field["extent_cells"]) <= GRID_CELLS
    # one machine only
    status, only = get(base + f"field?day={DAY}&machine=seeder-02")
    assert status == 200 and [m["machine_id"] for m in only["machines"]] == ["seeder-02"]
    # per-row quality: export's numbers for the same records and reference
    status, q = get(base + f"quality?day={DAY}&machine=seeder-01")
    assert status == 200
    with DatabaseSource(database, "seeder-01") as src:
        expected = quality_by_row_chunks(src.query_seed_rows(), 0.2)
    assert q["rows"] == {str(r): v.as_dict() for r, v in expected.items()}
    status, alarms = get(base + f"alarms?day={DAY}")
    assert status == 200 and alarms["total"] == 3
    assert [(e["machine_id"], e["code"], e["active"]) for e in alarms["events"]] == [
        ("seeder-02", "radar.lost", True), ("seeder-02", "radar.lost", False),
        ("seeder-01", "row.3.blocked", True)]
    # another day: empty, not an error
    assert get(base + "field?day=2026-04-21")[1]["machines"] == []


@pytest.mark.parametrize(("query", "message"), [
    ("field", "day: required"),
    ("field?day=2026-13-01", "day: not a calendar date"),
    ("field?day=yesterday", "day: not a date as YYYY-MM-DD"),
    ("field?day=2026-04-20'%3B%20DROP%20TABLE%20seed_records--", "day: not a date"),
    ("field?day=2026-04-20&machine=a%20b", "machine: not a machine id"),
    ("field?day=2026-04-20&machine=x'%20OR%201=1", "machine: not a machine id"),
    ("field?day=2026-04-20&day=2026-04-21", "each parameter once"),
    ("field?day=2026-04-20&zoom=3", "zoom: not a parameter of this request"),
    ("quality?day=2026-04-20", "machine: required"),
    ("field?day=2026-04-20&preview=yes", "preview: 0 or 1"),
    ("days?x=1", "x: not a parameter"),
])
async def test_bad_parameters_are_a_400_that_says_which_and_why(
        dashboard: DashboardProcess, database: str, query: str, message: str) -> None:
    status, body = get(dashboard.url + "api/history/" + query)
    assert status == 400, body
    assert message in body["error"], body
    # and the table is still there
    assert get(dashboard.url + f"api/history/field?day={DAY}")[1]["seeds"] == 5200


async def test_the_guard_covers_the_fleet_view(dashboard: DashboardProcess) -> None:
    url = dashboard.url + f"api/history/field?day={DAY}"
    status, body = get(url, {"Host": "evil.example"})
    assert status == 400 and "not one this dashboard answers to" in body
    status, body = get(url, {"Origin": "http://evil.example"})
    assert status == 403 and "cross-origin request refused" in body
    status, body = get(url, {"Origin": dashboard.url.rstrip("/")})
    assert status == 200
    assert get(dashboard.url + "api/history/tiles")[0] == 404


async def test_with_a_password_the_fleet_view_needs_it(tmp_path: Path, database: str) -> None:
    fill(database)
    secret = tmp_path / "password"
    secret.write_text("s3cret-enough\n")
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text(f'[mqtt]\nport = 1\n[dashboard]\npassword_file = "{secret}"\n'
                   f'[farm_server]\ndatabase_url = "{database}"\n')
    dash = DashboardProcess(cfg, tmp_path / "dashboard.log")
    await dash.start()
    try:
        url = dash.url + f"api/history/field?day={DAY}"
        assert get(url)[0] == 401
        auth = "Basic " + base64.b64encode(b"farmer:s3cret-enough").decode()
        status, body = get(url, {"Authorization": auth})
        assert status == 200 and body["seeds"] == 5200
    finally:
        await dash.stop()


async def test_without_a_database_the_fleet_view_is_a_404_saying_how(tmp_path: Path) -> None:
    cfg = tmp_path / "sowgate.toml"
    cfg.write_text("[mqtt]\nport = 1\n")
    dash = DashboardProcess(cfg, tmp_path / "dashboard.log")
    await dash.start()
    try:
        status, body = get(dash.url + "api/history/days")
        assert status == 404 and "[farm_server] database_url" in body["error"]
    finally:
        await dash.stop()


async def test_the_page_draws_the_day_with_machines_quality_and_timeline(
        dashboard: DashboardProcess) -> None:
    async with browser_page() as page:
        await page.goto(dashboard.url + f"?day={DAY}")
        await page.wait_for_function(
            "sowgate.history.draws.some(d => d.cells > 100 && d.seeds === 5200)", timeout=30_000)
        # pixels of the field are drawn in the class colours, not only background
        lit = await page.evaluate("""() => {
            const c = document.getElementById('h-map');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let n = 0;
            for (let i = 0; i < d.length; i += 4) if (d[i] === 102 && d[i + 1] === 187) n++;
            return n; }""")
        assert lit > 100
        gaps = page.locator("#h-machines tr[data-machine='seeder-02'] td.gaps")
        assert await gaps.inner_text() == "seeder-02: records 1 001–1 200 not received yet"
        await page.wait_for_function(
            "document.querySelectorAll('#h-quality tr[data-row]').length === 12",
            timeout=30_000)
        await page.wait_for_selector("#h-alarms .lane[data-machine='seeder-02'] i.critical")
        # the alarm message is text, never markup
        assert await page.locator("#h-alarms b").count() == 0
        assert await page.locator("#h-day").input_value() == DAY
