"""The dashboard in a real browser: headless Debian chromium (Playwright) on the page of the real
``sowgate dashboard`` process, subscribed to a real mosquitto, where the real daemon on the
simulated planter publishes. What the page shows must be what the daemon published."""

from __future__ import annotations

import contextlib
import json
import os
import re
import urllib.request
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from tests.browser import DashboardProcess, browser_page, dashboard_process
from tests.helpers import eventually
from tests.integration.conftest import Rig, running
from tests.integration.test_recording_end_to_end import all_delivered, stored_ids
from tests.mosquitto import Mosquitto, Subscriber, subscriber

BASE = "sowgate/seeder-01"
REPO = Path(__file__).resolve().parents[2]
# every run writes build/dashboard.png; SOWGATE_UPDATE_SCREENSHOT=1 also the README's picture
SCREENSHOT = REPO / "build" / "dashboard.png"
README_SCREENSHOT = REPO / "docs" / "img" / "dashboard.png"
WAIT_S = 20.0
# the tractor stands this long first (the dashboard has subscribed before the daemon starts)
STANDING_S = 8.0


@dataclass
class Scene:
    broker: Mosquitto
    sub: Subscriber
    rig: Rig
    dash: DashboardProcess
    page: Any

    async def text(self, element_id: str) -> str:
        return str(await self.page.locator(f"#{element_id}").inner_text())

    async def until_text(self, element_id: str, wanted: str, timeout: float = WAIT_S) -> None:
        """Wait until the element's text contains ``wanted`` (Playwright's own retrying)."""
        from playwright.async_api import expect

        await expect(self.page.locator(f"#{element_id}")).to_contain_text(
            wanted, timeout=timeout * 1000
        )

    async def until_exact(self, element_id: str, wanted: str, timeout: float = WAIT_S) -> None:
        from playwright.async_api import expect

        await expect(self.page.locator(f"#{element_id}")).to_have_text(
            wanted, timeout=timeout * 1000
        )

    def published_ids(self) -> set[int]:
        return set(self.sub.seed_ids())

    def last_state(self) -> dict[str, Any]:
        return dict(json.loads(self.sub.on("state")[-1]))


def sowing(seconds: float, kmh: float = 8.0) -> Drive:
    """Stand, sow for ``seconds``, stand (seeds stop, so every count can settle)."""
    return Drive(legs=[Leg(STANDING_S, 0.0), Leg(seconds, kmh), Leg(600.0, 0.0)], dt=0.02)


@contextlib.asynccontextmanager
async def scene(
    tmp_path: Path, drive: Drive, commands: list[str] | None = None, crop: str = "rapeseed",
    standing_s: float = STANDING_S,
) -> AsyncIterator[Scene]:
    """Broker, a subscriber that records what the daemon published, the daemon on the
    simulated planter, the dashboard process (same config file) and a browser on its page."""
    import tomli_w

    with Mosquitto(persistent=True) as broker:
        async with subscriber(broker.port, BASE, client_id="test-recorder") as sub:
            overrides: dict[str, Any] = {
                "mqtt": {"enabled": True, "port": broker.port, "keepalive": 5,
                         "reconnect_max_s": 1.0},
                "control": {"start_working": True},
                "commands": {"enabled": commands or []},
            }
            # the dashboard subscribes before the daemon starts: seeds are not retained, and
            # on a loaded machine a dashboard started next to the daemon came too late for the
            # first ones. It reads [mqtt] and [commands], the tables the daemon's file has too.
            config = tmp_path / "dashboard.toml"
            config.write_text(tomli_w.dumps(overrides))
            async with (
                dashboard_process(config, tmp_path / "dashboard.log") as dash,
                browser_page(dash.url) as page,
            ):
                await eventually(lambda: _health(dash.url).get("broker_connected") is True,
                                 WAIT_S, "the dashboard subscribed")
                machine = SimulatedMachine(drive=drive, with_gnss=True, with_seed_tubes=True,
                                           crop=crop)
                async with running(tmp_path, machine, **overrides) as rig:
                    yield Scene(broker, sub, rig, dash, page)


async def test_the_page_shows_what_the_daemon_published_and_sends_commands(
    tmp_path: Path,
) -> None:
    sow_s = 12.0
    commands = ["start", "stop", "rate", "ack_alarm"]
    async with scene(tmp_path, sowing(sow_s), commands=commands, crop="wheat") as s:
        await s.until_text("status", "online")
        # the tractor sows, then stands: once every stored seed has been published, the page
        # counts exactly the distinct records the daemon published (duplicates dropped)
        db = tmp_path / "state" / "records.sqlite3"
        machine = s.rig.machine
        await eventually(lambda: machine.pose().t > STANDING_S + sow_s + 0.5, 60.0, "sowing done")
        await eventually(lambda: all_delivered(db, s.sub), WAIT_S, "every seed published")
        published = len(s.published_ids())
        assert published == len(stored_ids(db)) > 200
        await s.until_exact("seed-count", str(published))
        # live values are those of the latest retained state
        state = s.last_state()
        assert await s.text("crop") == state["crop"]
        assert (await s.text("work-state")) == state["work_state"]
        assert (await s.text("target-rate")).startswith(f"{state['target_rate_kg_ha']:.1f}")
        assert "radar" in await s.text("devices")
        # the applied rate (seed mass over area, both published to the gram and the m²) is
        # shown once some seed has gone out: over its last stretch, near the mean over the
        # whole pass (this pass drives faster than the meter can follow: below the target)
        applied = await s.text("applied-rate")
        assert applied.endswith("kg/ha"), applied
        mean = state["seed_mass_kg"] / state["area_ha"]
        assert float(applied.split()[0]) == pytest.approx(mean, rel=0.2), (applied, mean)
        # the rate form offers the config's crops (no free text), the machine's one chosen
        crop = s.page.locator("#rate-crop")
        options = await crop.locator("option").all_text_contents()
        assert options == sorted(s.rig.daemon.settings.control.crops), options
        assert await crop.input_value() == state["crop"]
        rows = await s.page.locator("#rows tbody tr[data-row]").count()
        assert rows == s.rig.daemon.settings.machine.rows

        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        # the README's picture: the last metres of the pass, close up
        await s.page.evaluate("sowgate.view.scale = 30; sowgate.dirty = true")
        await s.page.screenshot(path=str(SCREENSHOT), full_page=True)
        if os.environ.get("SOWGATE_UPDATE_SCREENSHOT") == "1":
            README_SCREENSHOT.write_bytes(SCREENSHOT.read_bytes())

        # a command from the page reaches the daemon, and its ack is shown
        await s.page.locator("#cmd-stop").click()
        await s.until_text("cmd-log", "stop: done")
        await s.rig.until(lambda: s.rig.state() is not None and s.rig.state().value == "stopped",
                          what="the daemon stopped")
        await s.until_text("work-state", "stopped")
        await s.page.locator("#rate-crop").select_option("wheat")
        await s.page.locator("#rate-value").fill("999")
        await s.page.locator("#cmd-rate").click()
        await s.until_text("cmd-log", "rate: refused")



async def test_a_critical_alarm_appears_clears_and_stays_until_acknowledged_from_the_page(
    tmp_path: Path,
) -> None:
    async with scene(tmp_path, sowing(120.0), commands=["ack_alarm"]) as s:
        await s.until_text("status", "online")
        # no operation controls offered (only ack_alarm is enabled)
        assert not await s.page.locator("#cmd-stop").is_visible()
        rs485 = s.rig.machine.rs485
        assert rs485 is not None
        rs485.set_silent(rs485.device_ids["pwm"], True)  # the PWM module stops answering
        row = s.page.locator('#alarms tr[data-code="pwm.unavailable"]')
        await _expect(row, "to_contain_text", "active")
        await _expect(row, "to_contain_text", "critical")
        await _expect(s.page.locator("#devices"), "to_contain_text", "pwm (not answering)")
        rs485.set_silent(rs485.device_ids["pwm"], False)
        await s.rig.until(lambda: not s.rig.daemon.alarms.is_active("pwm.unavailable"),
                          timeout=WAIT_S, what="the alarm cleared on the box")
        # cleared, with its time, and still waiting for the operator
        await _expect(row, "to_have_class", re.compile(r"\bcleared\b.*\bunacked\b"))
        assert "active" not in await row.locator("td").nth(3).inner_text()
        assert [a.code for a in s.rig.daemon.alarms.unacknowledged] == ["pwm.unavailable"]
        await row.locator("button.ack-alarm").click()
        await s.until_text("cmd-log", "ack_alarm: done: acknowledged: pwm.unavailable")
        assert s.rig.daemon.alarms.unacknowledged == []
        await _expect(row, "not_to_have_class", re.compile(r"\bunacked\b"))
        await _expect(row.locator("button.ack-alarm"), "to_have_count", 0)


async def test_a_blocked_row_is_marked_in_the_rows_table_and_listed_as_an_alarm(
    tmp_path: Path,
) -> None:
    """Issue 20 item 2: row 4's tube sends nothing while the others sow; the page marks it
    blocked beside its singulation bars and lists ``row.4.blocked`` (critical)."""
    # it reads the retained state, not the seeds: it may subscribe late on a busy machine
    drive = Drive(legs=[Leg(2.0, 0.0), Leg(60.0, 8.0), Leg(600.0, 0.0)], dt=0.02)
    async with scene(tmp_path, drive, standing_s=60.0) as s:
        s.rig.machine.seed_tubes.silent_rows.add(4)
        from playwright.async_api import expect

        row4 = s.page.locator('#rows tbody tr[data-row="4"]')
        await expect(row4).to_have_class(re.compile(r"\brow-blocked\b"), timeout=40_000)
        assert (await row4.locator(".row-state").inner_text()).lower() == "blocked"
        assert await s.page.locator("#rows tbody tr.row-blocked").count() == 1
        await s.until_text("alarms", "row.4.blocked", timeout=WAIT_S)
        assert "row 4 blocked" in await s.text("alarms")


async def test_the_page_says_the_broker_is_lost_and_refills_the_map_after_it_returns(
    tmp_path: Path,
) -> None:
    sow_s = 25.0
    db = tmp_path / "state" / "records.sqlite3"
    async with scene(tmp_path, sowing(sow_s)) as s:
        await s.until_text("status", "online")
        await _expect(s.page.locator("#broker"), "to_be_hidden")
        await eventually(lambda: len(s.published_ids()) > 100, WAIT_S, "seeds published")
        s.broker.stop()
        await _expect(s.page.locator("#broker"), "to_contain_text",
                      "MQTT broker connection lost")
        shown = int(await s.text("seed-count"))
        # the daemon keeps recording into its store while the broker is away
        await eventually(lambda: len(stored_ids(db)) > shown + 200, WAIT_S, "seeds recorded")
        assert int(await s.text("seed-count")) == shown  # nothing arrives meanwhile
        s.broker.start()
        await _expect(s.page.locator("#broker"), "to_be_hidden")
        machine = s.rig.machine
        await eventually(lambda: machine.pose().t > STANDING_S + sow_s + 0.5, 60.0, "sowing done")
        await eventually(lambda: all_delivered(db, s.sub), WAIT_S, "every seed published")
        # every stored seed on the map, once: the redelivered ones were deduplicated
        await s.until_exact("seed-count", str(len(stored_ids(db))))
        health = await s.page.evaluate("fetch('/api/health').then(r => r.json())")
        assert health["broker_connected"] is True


async def test_with_a_password_the_page_and_its_live_updates_need_it(tmp_path: Path) -> None:
    """Basic auth covers the WebSocket too: the browser, once logged in, gets live data
    (here: that the broker is away); without the password it gets nothing."""
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n")
    config = tmp_path / "sowgate.toml"
    config.write_text(f'[mqtt]\nport = 9\n[commands]\nenabled = ["stop"]\n'
                      f'[dashboard]\npassword_file = "{secret}"\n')
    async with dashboard_process(config, tmp_path / "dashboard.log") as dash:
        async with browser_page(dash.url, http_credentials={"username": "farmer",
                                                            "password": "s3cret"}) as page:
            await _expect(page.locator("#link"), "to_have_text", "live")
            await _expect(page.locator("#nodata-detail"), "to_contain_text",
                          "Not connected to the MQTT broker")
        async with browser_page() as page:
            assert (await page.request.get(dash.url)).status == 401
            assert (await page.request.get(dash.url + "static/dashboard.js")).status == 401


def _health(url: str) -> dict[str, Any]:
    """The dashboard's /api/health (broker_connected is set once its subscriptions are made)."""
    try:
        with urllib.request.urlopen(url + "api/health", timeout=2) as resp:
            doc: dict[str, Any] = json.load(resp)
    except OSError:
        return {}
    return doc


async def _expect(locator: Any, check: str, *args: Any) -> None:
    """Playwright's retrying assertion ``check`` on ``locator`` (a condition, not a sleep)."""
    from playwright.async_api import expect

    await getattr(expect(locator), check)(*args, timeout=WAIT_S * 1000)


async def test_several_seeders_on_one_broker_each_have_their_page_and_tiles_load(
    tmp_path: Path,
) -> None:
    """Two boxes publishing on one broker (here: their payloads, as docs/mqtt.md gives them):
    one tab each, each with its own values and seeds; a configured tile server is asked for
    the tiles under the field."""
    from tests.gateway.dashboard.test_model import batch, record, state

    tiles = TileServer()
    with Mosquitto() as broker, tiles:
        config = tmp_path / "sowgate.toml"
        config.write_text(f'[mqtt]\nport = {broker.port}\n[dashboard]\n'
                          f'tile_url = "http://127.0.0.1:{tiles.port}/{{z}}/{{x}}/{{y}}.png"\n')
        async with dashboard_process(config, tmp_path / "dashboard.log") as dash:
            # seeds are not retained: publish them once the dashboard has subscribed (its
            # health says so), as a box's seeds reach a dashboard that is already running
            await eventually(lambda: _health(dash.url).get("broker_connected") is True, WAIT_S,
                             "the dashboard subscribed")
            async with aiomqtt.Client("127.0.0.1", broker.port) as client:
                for mid, crop, n in (("north-01", "wheat", 30), ("south-02", "rapeseed", 12)):
                    await client.publish(f"sowgate/{mid}/status", b"online", qos=1, retain=True)
                    await client.publish(f"sowgate/{mid}/state", state(machine_id=mid, crop=crop),
                                         qos=1, retain=True)
                    await client.publish(f"sowgate/{mid}/seeds", batch(
                        [record(i, row=1 + i % 4, north_m=i * 0.2, machine=mid)
                         for i in range(1, n + 1)], mid), qos=1)
            async with browser_page(dash.url) as page:
                tabs = page.locator("#machines button")
                await _expect(tabs, "to_have_count", 2)
                await _expect(tabs, "to_have_text", ["north-01", "south-02"])
                await _expect(page.locator("#crop"), "to_have_text", "wheat")
                await _expect(page.locator("#seed-count"), "to_have_text", "30")
                await tabs.nth(1).click()
                await _expect(page.locator("#crop"), "to_have_text", "rapeseed")
                await _expect(page.locator("#seed-count"), "to_have_text", "12")
                await eventually(lambda: tiles.requests > 0, WAIT_S, "a tile requested")
                assert all(re.fullmatch(r"/\d+/\d+/\d+\.png", p) for p in tiles.paths)
                # and drawn under the seeds: the map's corner is the tiles' grey
                await page.wait_for_function(
                    "(() => { const c = document.getElementById('map');"
                    " const p = c.getContext('2d').getImageData(3, 3, 1, 1).data;"
                    " return p[0] === 128 && p[1] === 128 && p[2] === 128; })()",
                    timeout=WAIT_S * 1000,
                )


class TileServer:
    """An XYZ tile server on a free port answering every tile with one grey PNG."""

    PNG = bytes.fromhex(
        "89504e470d0a1a0a0000000d49484452000000010000000108000000003a7e9b"
        "550000000a49444154789c636800000082008177cd72b60000000049454e44ae"
        "426082"
    )

    def __init__(self) -> None:
        import http.server
        import threading

        outer = self
        self.paths: list[str] = []

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                outer.paths.append(self.path)
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Access-Control-Allow-Origin", "*")
                self.end_headers()
                self.wfile.write(TileServer.PNG)

            def log_message(self, *args: object) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, name="tiles")

    @property
    def requests(self) -> int:
        return len(self.paths)

    def __enter__(self) -> TileServer:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join()
