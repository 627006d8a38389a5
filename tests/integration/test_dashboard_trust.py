"""The dashboard trusts no stranger: the real ``sowgate dashboard`` process (uvicorn on a free
port) and a real mosquitto, asked the way a hostile web page, a password guesser and a broker
full of stray machine ids would ask (issue 20, item 8)."""

from __future__ import annotations

import asyncio
import base64
import http.client
import json
import os
import re
import socket
import time
from pathlib import Path
from typing import Any

import aiomqtt

from tests.browser import DashboardProcess, dashboard_process
from tests.gateway.dashboard.test_model import batch, record
from tests.helpers import eventually
from tests.mosquitto import Mosquitto

WAIT_S = 60.0
COMMAND = json.dumps({"command": "start", "machine_id": "m1", "payload": {}}).encode()


def request(port: int, method: str, path: str, headers: dict[str, str],
            body: bytes | None = None,
            conn: http.client.HTTPConnection | None = None) -> tuple[int, dict[str, str], str]:
    """One request with exactly these headers (``Host`` included): (status, headers, body)."""
    own = conn is None
    conn = conn or http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request(method, path, body=body, headers=headers)
        resp = conn.getresponse()
        return resp.status, dict(resp.getheaders()), resp.read().decode(errors="replace")
    finally:
        if own:
            conn.close()


def upgrade(port: int, host: str, origin: str | None,
            authorization: str | None = None) -> tuple[int, socket.socket]:
    """A WebSocket upgrade of ``/ws`` as a browser sends it: (HTTP status, the open socket)."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    lines = [
        "GET /ws HTTP/1.1", f"Host: {host}", "Upgrade: websocket", "Connection: Upgrade",
        "Sec-WebSocket-Key: " + base64.b64encode(os.urandom(16)).decode(),
        "Sec-WebSocket-Version: 13",
    ]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    if authorization is not None:
        lines.append(f"Authorization: {authorization}")
    sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
    head = b""
    while b"\r\n" not in head:
        chunk = sock.recv(4096)
        if not chunk:
            break
        head += chunk
    match = re.match(rb"HTTP/1\.1 (\d{3})", head)
    assert match, head
    return int(match.group(1)), sock


def health(port: int) -> dict[str, Any]:
    try:
        status, _, body = request(port, "GET", "/api/health", {"Host": f"127.0.0.1:{port}"})
    except OSError:
        return {}
    return json.loads(body) if status == 200 else {}


def basic(password: str) -> str:
    return "Basic " + base64.b64encode(f"farmer:{password}".encode()).decode()


async def test_a_rebound_name_cannot_command_the_machine_or_open_the_live_feed(
    tmp_path: Path,
) -> None:
    """DNS rebinding: a page at evil.example points its name at 127.0.0.1 and posts to the
    dashboard with Host and Origin both evil.example:PORT. Refused (400) before anything is
    sent; the page itself, and a script without Origin, still command the machine."""
    with Mosquitto() as broker:
        async with aiomqtt.Client("127.0.0.1", broker.port) as spy:
            await spy.publish("sowgate/m1/status", b"online", qos=1, retain=True)
            await spy.subscribe("sowgate/m1/cmd/#", qos=1)
            config = tmp_path / "sowgate.toml"
            config.write_text(f'[mqtt]\nport = {broker.port}\n[commands]\nenabled = ["start"]\n'
                              '[dashboard]\nmax_clients = 2\n')
            async with dashboard_process(config, tmp_path / "dashboard.log") as dash:
                port = dash.port
                await eventually(lambda: "m1" in health(port).get("machines", {}), WAIT_S,
                                 "the dashboard sees m1")
                evil = f"evil.example:{port}"
                post = {"Content-Type": "application/json"}
                status, _, body = await asyncio.to_thread(
                    request, port, "POST", "/api/command",
                    {**post, "Host": evil, "Origin": f"http://{evil}"}, COMMAND)
                assert status == 400 and "allowed_hosts" in body, body
                assert (await asyncio.to_thread(upgrade, port, evil, f"http://{evil}"))[0] == 400
                # the right Host, but posted from another site's page
                own = f"127.0.0.1:{port}"
                status, _, body = await asyncio.to_thread(
                    request, port, "POST", "/api/command",
                    {**post, "Host": own, "Origin": "http://evil.example"}, COMMAND)
                assert status == 403 and "cross-origin" in body, body
                assert (await asyncio.to_thread(upgrade, port, own, "http://evil.example"))[0] \
                    == 403
                # a GET of the page under the rebound name: refused as well
                status, _, _ = await asyncio.to_thread(request, port, "GET", "/", {"Host": evil})
                assert status == 400
                # nothing reached the broker; now the page itself, then a script (no Origin)
                for headers in ({**post, "Host": own, "Origin": f"http://{own}"},
                                {**post, "Host": f"localhost:{port}"}):
                    status, _, body = await asyncio.to_thread(
                        request, port, "POST", "/api/command", headers, COMMAND)
                    assert status == 200 and json.loads(body)["ok"] is True, body
                sent = []
                async with asyncio.timeout(WAIT_S):
                    async for message in spy.messages:
                        sent.append(json.loads(bytes(message.payload)))  # type: ignore[arg-type]
                        if len(sent) == 2:
                            break
                assert all(set(m) == {"request_id"} for m in sent)
                # the live feed: the page's own upgrade works, up to max_clients pages
                first = await asyncio.to_thread(upgrade, port, own, f"http://{own}")
                second = await asyncio.to_thread(upgrade, port, f"localhost:{port}", None)
                try:
                    assert first[0] == second[0] == 101
                    await eventually(lambda: health(port).get("pages") == 2, WAIT_S, "2 pages")
                    assert (await asyncio.to_thread(upgrade, port, own, f"http://{own}"))[0] \
                        == 403
                    assert health(port)["pages_refused"] == 1
                finally:
                    first[1].close()
                    second[1].close()
                assert health(port)["requests_refused"] == 5
            log = (tmp_path / "dashboard.log").read_text()
            assert "refused POST /api/command from 127.0.0.1: host 'evil.example" in log, log


async def test_wrong_passwords_are_slowed_refused_in_parallel_and_logged(tmp_path: Path) -> None:
    """2 577 guesses a second became: each wrong password waits longer (0.25 s, doubling), and
    guesses sent meanwhile are refused unchecked (429); every failure is one log line."""
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n")
    config = tmp_path / "sowgate.toml"
    config.write_text(f'[mqtt]\nport = 9\n[dashboard]\npassword_file = "{secret}"\n')
    async with dashboard_process(config, tmp_path / "dashboard.log") as dash:
        port = dash.port
        host = {"Host": f"127.0.0.1:{port}"}
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)  # one connection
        try:
            t0 = time.monotonic()
            for guess in ("a", "b", "c"):
                status, _, _ = await asyncio.to_thread(
                    request, port, "GET", "/api/health", {**host, "Authorization": basic(guess)},
                    None, conn)
                assert status == 401
            assert time.monotonic() - t0 >= 0.25 + 0.5 + 1.0  # a lower bound: never flaky
        finally:
            conn.close()
        # five guesses at once: one is checked (and waits 2 s), the others are not checked
        results = await asyncio.gather(*(asyncio.to_thread(
            request, port, "GET", "/api/health", {**host, "Authorization": basic(f"p{i}")})
            for i in range(5)))
        statuses = sorted(status for status, _, _ in results)
        assert statuses == [401, 429, 429, 429, 429], statuses
        retry = max(int(h["retry-after"]) for s, h, _ in results if s == 429)
        assert 1 <= retry <= 10
        # the farmer, once the wait is over, gets in; the browser's first ask is not a failure
        await eventually(lambda: request(port, "GET", "/api/health",
                                         {**host, "Authorization": basic("s3cret")})[0] == 200,
                         WAIT_S, "the right password taken after the wait")
        assert request(port, "GET", "/", host)[0] == 401
    log = (tmp_path / "dashboard.log").read_text()
    failures = re.findall(r"wrong password from 127\.0\.0\.1 \((\d+) in a row", log)
    assert failures == ["1", "2", "3", "4"], log


def vm_rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


async def test_twenty_thousand_machine_ids_on_the_broker_do_not_grow_the_dashboard(
    tmp_path: Path,
) -> None:
    """A broker carrying 20 000 machine ids (a misconfigured fleet, or a hostile client) grew
    the dashboard by 60 MB. It shows the first 64 ([dashboard] max_machines) and counts, logs
    and drops the rest."""
    ids = 20_000
    with Mosquitto() as broker:
        config = tmp_path / "sowgate.toml"
        config.write_text(f'[mqtt]\nport = {broker.port}\n')
        dash = DashboardProcess(config, tmp_path / "dashboard.log")
        await dash.start()
        try:
            port = dash.port
            await eventually(lambda: health(port).get("broker_connected"), WAIT_S, "connected")
            assert dash.proc is not None
            async with aiomqtt.Client("127.0.0.1", broker.port) as pub:
                # the first machines, then the baseline: what 64 machines hold
                for i in range(64):
                    await pub.publish(f"sowgate/m{i}/seeds", batch([record(1, machine=f"m{i}")],
                                                                   f"m{i}"), qos=1)
                await eventually(lambda: len(health(port).get("machines", {})) == 64, WAIT_S,
                                 "64 machines shown")
                before = vm_rss_kb(dash.proc.pid)
                for start in range(64, ids, 500):
                    await asyncio.gather(*(
                        pub.publish(f"sowgate/m{i}/seeds",
                                    batch([record(1, machine=f"m{i}")], f"m{i}"), qos=1)
                        for i in range(start, min(start + 500, ids))))
            await eventually(lambda: health(port).get("machines_refused") == ids - 64, WAIT_S,
                             "every further machine id counted",
                             detail=lambda: health(port))
            grown_mb = (vm_rss_kb(dash.proc.pid) - before) / 1024
            assert len(health(port)["machines"]) == 64
            assert grown_mb < 15, f"the dashboard grew {grown_mb:.1f} MB"
        finally:
            await dash.stop()
    log = (tmp_path / "dashboard.log").read_text()
    assert "max_machines" in log and "dropped" in log, log
    assert log.count("max_machines") <= 10  # rate-limited, not 19 936 lines
