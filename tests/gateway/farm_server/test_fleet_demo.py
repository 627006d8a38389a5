"""Issue 24's "done when": a demo drive with `sowgate ingest` running ends with every record in
PostgreSQL, and `sowgate dashboard` shows that field from the database once the demo has
stopped (the commands of docs/farm-server.md, "Try it": real mosquitto with the farm ACL,
the real `sowgate ingest` and `sowgate demo` processes, PostgreSQL, chromium)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import sqlite3
import urllib.request
from pathlib import Path

import pytest

from tests.browser import DashboardProcess, browser_page
from tests.gateway.farm_server.conftest import rows
from tests.gateway.farm_server.test_ingest import through, watermarks
from tests.helpers import eventually, sowgate_env, sowgate_process
from tests.mosquitto import Mosquitto


def get(url: str) -> dict[str, object]:
    with urllib.request.urlopen(url, timeout=60) as resp:
        body: dict[str, object] = json.loads(resp.read())
        return body


@pytest.mark.slow
async def test_a_demo_drive_ends_in_postgresql_and_the_dashboard_shows_it_after_the_demo(
    database: str, broker: Mosquitto, tmp_path: Path
) -> None:
    farm = tmp_path / "farm.toml"  # the farm server's one config: ingest and the dashboard
    farm.write_text(
        f'[mqtt]\nhost = "{broker.host}"\nport = {broker.port}\nusername = "sowgate-ingest"\n'
        f'[farm_server]\ndatabase_url = "{database}"\nflush_interval_s = 0.2\n')
    cab = tmp_path / "cab"
    env = sowgate_env(env={
        "SOWGATE_MQTT__HOST": broker.host, "SOWGATE_MQTT__PORT": str(broker.port),
        "SOWGATE_MQTT__USERNAME": "seeder-01", "SOWGATE_MQTT__FARM_SERVER_ACK": "true",
    }, clean=True)
    async with sowgate_process("ingest", "--config", str(farm),
                               env=sowgate_env(clean=True)) as ingest, \
            watermarks(broker) as seen:
        async with sowgate_process("demo", "--no-tui", "--duration", "10", "--state-dir",
                                   str(cab), env=env) as demo:
            _, err = await asyncio.wait_for(demo.communicate(), 180.0)
        assert demo.returncode == 0, err.decode()[-2000:]
        with contextlib.closing(sqlite3.connect(cab / "records.sqlite3")) as store:
            count, last = store.execute("SELECT count(*), max(id) FROM seeds").fetchone()
            alarms = store.execute("SELECT count(*) FROM alarms").fetchone()[0]
        assert count > 20 and count == last
        await eventually(lambda: through(seen, "seeder-01") == last, 60, "watermark = last id",
                         detail=lambda: seen)
        assert ingest.returncode is None
        ingest.terminate()
        await asyncio.wait_for(ingest.wait(), 30)
    # every record, exactly once; the alarms too
    assert rows(database, "SELECT count(*), count(DISTINCT id), min(id), max(id) "
                "FROM seed_records WHERE machine_id = 'seeder-01'")[0] == (last, last, 1, last)
    assert rows(database, "SELECT count(*) FROM alarm_events")[0][0] == alarms
    day = str(rows(database, "SELECT min(utc AT TIME ZONE 'UTC')::date FROM seed_records")[0][0])
    # the demo and ingest are gone: the dashboard reads the field from the database
    dash = DashboardProcess(farm, tmp_path / "dashboard.log")
    await dash.start()
    try:
        assert day in get(dash.url + "api/history/days")["days"]  # type: ignore[operator]
        field = get(dash.url + f"api/history/field?day={day}")
        if rows(database, "SELECT count(DISTINCT utc::date) FROM seed_records")[0][0] == 1:
            assert field["seeds"] == last  # (a drive across midnight is two days)
        (machine,) = field["machines"]  # type: ignore[misc]
        assert machine["machine_id"] == "seeder-01" and machine["gap_runs"] == 0
        assert machine["gaps_text"] == "seeder-01: every record up to the newest received"
        assert len(field["cells"]) > 0  # type: ignore[arg-type]
        async with browser_page() as page:
            await page.goto(dash.url + f"?day={day}")
            await page.wait_for_function(
                "sowgate.history.draws.some(d => d.complete && d.cells > 0)", timeout=60_000)
            lit = await page.evaluate("""() => {
                const c = document.getElementById('h-map');
                const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                let n = 0;
                for (let i = 0; i < d.length; i += 4)
                    if (!(d[i] === 0x3b && d[i + 1] === 0x33 && d[i + 2] === 0x26)) n++;
                return n; }""")
            assert lit > 10  # seeds drawn on the field's background
            text = await page.locator("#h-machines tr[data-machine='seeder-01']").inner_text()
            assert "every record up to the newest received" in text
    finally:
        await dash.stop()
