"""The server's pure parts: what a page joining mid-field gets, and which requests it takes."""

from __future__ import annotations

import json
import logging

import pytest

from gateway.dashboard.guard import (
    LoginThrottle,
    LogLimiter,
    TrustedHosts,
    foreign_origin,
    hostname_of,
)
from gateway.dashboard.model import Fleet
from gateway.dashboard.server import Hub
from tests.gateway.dashboard.test_model import batch, record


def seeds_in(texts: list[str]) -> int:
    n = 0
    for text in texts:
        msg = json.loads(text)
        if msg["type"] == "snapshot":
            n += sum(len(m["seeds"]) // 4 for m in msg["machines"].values())
        elif msg["type"] == "machine":
            n += len(msg.get("seeds", [])) // 4
    return n


def drained(queue: object) -> list[str]:
    out = []
    while not queue.empty():  # type: ignore[attr-defined]
        out.append(queue.get_nowait())  # type: ignore[attr-defined]
    return out


async def test_a_page_joining_while_seeds_flow_gets_each_seed_exactly_once() -> None:
    fleet = Fleet()
    hub = Hub(fleet)
    first, first_snapshot = hub.join()
    fleet.handle("sowgate/m/seeds", batch([record(i, machine="m") for i in range(1, 11)], "m"))
    # seeds arrived, not pushed yet: a second page joins now
    second, snapshot = hub.join()
    fleet.handle("sowgate/m/seeds", batch([record(i, machine="m") for i in range(11, 16)], "m"))
    hub.push()
    assert seeds_in([snapshot, *drained(second)]) == 15
    assert seeds_in([first_snapshot, *drained(first)]) == 15


async def test_a_page_that_lags_is_resynchronised_with_a_snapshot_not_an_endless_queue() -> None:
    fleet = Fleet()
    hub = Hub(fleet)
    queue, _ = hub.join()
    for i in range(1, 200):  # the page reads nothing meanwhile
        fleet.handle("sowgate/m/seeds", batch([record(i, machine="m")], "m"))
        hub.push()
    texts = drained(queue)
    assert len(texts) < 80
    assert json.loads(texts[-1])["type"] in ("snapshot", "machine", "origin")
    assert any(json.loads(t)["type"] == "snapshot" for t in texts)


def test_commands_and_the_websocket_are_taken_only_from_the_page_itself() -> None:
    hosts = TrustedHosts({"localhost", "127.0.0.1", "::1"}, any_ip=False)
    assert foreign_origin({"host": "127.0.0.1:8080"}, hosts) is None  # curl: no Origin
    assert foreign_origin({"host": "127.0.0.1:8080", "origin": "http://127.0.0.1:8080"},
                          hosts) is None
    assert foreign_origin({"host": "127.0.0.1:8080", "origin": "https://evil.example"}, hosts)
    assert foreign_origin({"host": "127.0.0.1:8080", "origin": "http://127.0.0.1:9999"}, hosts)
    assert foreign_origin({"host": "127.0.0.1:8080", "origin": "null"}, hosts)
    # DNS rebinding: Host and Origin agree, but the name is not this machine's
    why = foreign_origin({"host": "evil.example:8080", "origin": "http://evil.example:8080"},
                         hosts)
    assert why is not None and "not an allowed host" in why


def test_the_host_list_takes_its_names_wildcards_and_beyond_loopback_any_ip() -> None:
    local = TrustedHosts({"localhost", "127.0.0.1", "::1", "*.farm.lan"}, any_ip=False)
    assert local.allows(hostname_of("127.0.0.1:8080"))
    assert local.allows(hostname_of("[::1]:8080"))
    assert local.allows(hostname_of("LOCALHOST"))
    assert local.allows(hostname_of("cab.farm.lan:80"))
    assert not local.allows(hostname_of("farm.lan.evil.example"))
    assert not local.allows(hostname_of("evil.example:8080"))
    assert not local.allows(hostname_of("192.168.1.20:8080"))
    assert not local.allows(hostname_of("127.0.0.1:notaport"))
    assert not local.allows(hostname_of(""))
    assert TrustedHosts({"localhost"}, any_ip=True).allows(hostname_of("192.168.1.20:8080"))


def test_wrong_passwords_wait_longer_each_time_and_all_addresses_share_a_cap() -> None:
    now = [0.0]
    throttle = LoginThrottle(clock=lambda: now[0])
    assert throttle.wait_s("10.0.0.5") == 0
    delays = [throttle.failed("10.0.0.5")[1] for _ in range(8)]
    assert delays == [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0]
    assert throttle.wait_s("10.0.0.5") == 10.0
    assert throttle.wait_s("10.0.0.6") == 0  # another address: its own count
    throttle.succeeded("10.0.0.5")
    assert throttle.wait_s("10.0.0.5") == 0
    # many addresses, one failure each: once the burst is spent everyone waits
    for i in range(40):
        throttle.failed(f"10.1.0.{i}")
    assert throttle.wait_s("10.9.9.9") > 0
    now[0] += 3600
    assert throttle.wait_s("10.9.9.9") == 0


def test_log_lines_are_rate_limited_and_the_next_one_counts_what_was_left_out(
    caplog: pytest.LogCaptureFixture,
) -> None:
    now = [0.0]
    limiter = LogLimiter(per_minute=3, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING):
        for i in range(10):
            limiter.warning("failure %d", i)
        now[0] += 61
        limiter.warning("failure %d", 10)
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["failure 0", "failure 1", "failure 2",
                     "failure 10 (7 similar lines left out)"]
