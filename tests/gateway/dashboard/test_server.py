"""The server's pure parts: what a page joining mid-field gets, and which requests it takes."""

from __future__ import annotations

import json

from gateway.dashboard.model import Fleet
from gateway.dashboard.server import Hub, same_origin
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
    assert same_origin({"host": "127.0.0.1:8080"})  # curl, a script: no Origin header
    assert same_origin({"host": "127.0.0.1:8080", "origin": "http://127.0.0.1:8080"})
    assert not same_origin({"host": "127.0.0.1:8080", "origin": "https://evil.example"})
    assert not same_origin({"host": "127.0.0.1:8080", "origin": "http://127.0.0.1:9999"})
