"""`sowgate ingest`: every record from the broker in PostgreSQL exactly once, the watermark
says so, hostile input is counted and never stored (real mosquitto, real PostgreSQL)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta

import aiomqtt
import pytest

from gateway.config import FarmServerSection, MqttSection
from gateway.core.records import SeedRecord
from gateway.farm_server.ingest import Ingest, gap_text
from gateway.link.payloads import SeedBatch, StatePayload
from tests.gateway.farm_server.conftest import rows
from tests.helpers import eventually
from tests.mosquitto import Mosquitto

T0 = datetime(2026, 4, 20, 23, 59, 58, tzinfo=UTC)  # the records cross midnight: two days


def records(machine: str, first: int, last: int) -> list[SeedRecord]:
    return [
        SeedRecord(id=i, machine_id=machine, row=1 + i % 6,
                   utc=T0 + timedelta(milliseconds=5 * i), lat=48.0 + i * 1e-7,
                   lon=15.0, fix="rtk_fixed", speed_kmh=8.0, spacing_m=0.12)
        for i in range(first, last + 1)
    ]


def batch(machine: str, first: int, last: int, pending_from: int | None = None) -> bytes:
    return SeedBatch(machine_id=machine, records=records(machine, first, last),
                     pending_from=pending_from).model_dump_json().encode()


@contextlib.asynccontextmanager
async def running_ingest(url: str, broker: Mosquitto, **farm: object) -> AsyncIterator[Ingest]:
    ingest = Ingest(
        FarmServerSection(database_url=url, flush_interval_s=0.1, state_sample_s=0,
                          **farm),  # type: ignore[arg-type]
        MqttSection(host=broker.host, port=broker.port, username="sowgate-ingest"),
    )
    task = asyncio.create_task(ingest.run(), name="test-ingest")
    try:
        await eventually(ingest.connected.is_set, 20, "ingest subscribed", unless=task)
        yield ingest
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        if ingest._db is not None:
            ingest._db.close()


@contextlib.asynccontextmanager
async def cab(broker: Mosquitto, machine: str) -> AsyncIterator[aiomqtt.Client]:
    """A simulated cab publisher, logged in as its machine id (the ACL's %u)."""
    async with aiomqtt.Client(broker.host, broker.port, identifier=f"cab-{machine}",
                              username=machine) as client:
        yield client


@contextlib.asynccontextmanager
async def watermarks(broker: Mosquitto) -> AsyncIterator[dict[str, dict[str, object]]]:
    """The latest `ingested` payload per machine, as a cab would see it."""
    seen: dict[str, dict[str, object]] = {}

    async def run() -> None:
        async with aiomqtt.Client(broker.host, broker.port, username="sowgate-ingest") as c:
            await c.subscribe("sowgate/+/ingested", qos=1)
            async for m in c.messages:
                assert isinstance(m.payload, bytes)
                if not m.payload:  # a retained watermark deleted
                    seen.pop(m.topic.value.split("/")[1], None)
                    continue
                seen[m.topic.value.split("/")[1]] = json.loads(m.payload)

    task = asyncio.create_task(run())
    try:
        yield seen
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


def through(seen: dict[str, dict[str, object]], machine: str) -> object:
    return seen.get(machine, {}).get("committed_through")


async def test_records_from_a_cab_end_in_postgresql_exactly_once(
    database: str, broker: Mosquitto
) -> None:
    async with running_ingest(database, broker) as ingest, watermarks(broker) as seen, \
            cab(broker, "seeder-01") as client:
        for first in range(1, 1001, 100):
            await client.publish("sowgate/seeder-01/seeds", batch("seeder-01", first, first + 99),
                                 qos=1)
        # at-least-once: the cab sends a batch again after a lost PUBACK
        await client.publish("sowgate/seeder-01/seeds", batch("seeder-01", 301, 400), qos=1)
        await eventually(lambda: through(seen, "seeder-01") == 1000, 30, "watermark 1000",
                         detail=lambda: (seen, ingest.stats))
    count, distinct, days, srid, first_lat = rows(
        database, "SELECT count(*), count(DISTINCT id), count(DISTINCT utc::date), "
        "min(ST_SRID(geom)), min(ST_Y(geom)) FROM seed_records WHERE machine_id = 'seeder-01'"
    )[0]
    assert (count, distinct, days, srid) == (1000, 1000, 2, 4326)
    assert first_lat == pytest.approx(48.0 + 1e-7)
    # each day in its own partition, created on demand
    parts = rows(database, "SELECT count(*) FROM pg_inherits WHERE inhparent = "
                 "'seed_records'::regclass")[0][0]
    assert parts == 2
    assert ingest.stats.seeds_duplicate == 100


async def test_a_duplicate_flood_makes_no_duplicate_row(database: str, broker: Mosquitto) -> None:
    async with running_ingest(database, broker, batch_rows=500) as ingest, \
            watermarks(broker) as seen, cab(broker, "seeder-02") as client:
        payloads = [batch("seeder-02", f, f + 49) for f in range(1, 501, 50)]
        for _ in range(20):  # a replay of the whole outbox, twenty times over
            for p in payloads:
                await client.publish("sowgate/seeder-02/seeds", p, qos=1)
        await client.publish("sowgate/seeder-02/seeds", batch("seeder-02", 250, 520), qos=1)
        await eventually(lambda: through(seen, "seeder-02") == 520, 60, "watermark 520",
                         detail=lambda: ingest.stats)
        await eventually(lambda: ingest.stats.seeds_committed + ingest.stats.seeds_duplicate
                         == 20 * 500 + 271, 60, "every copy judged")
    assert rows(database, "SELECT count(*), count(DISTINCT id) FROM seed_records")[0] == (520, 520)
    assert ingest.stats.seeds_committed == 520


async def test_gaps_are_known_per_machine_and_named(database: str, broker: Mosquitto) -> None:
    async with running_ingest(database, broker) as ingest, watermarks(broker) as seen, \
            cab(broker, "seeder-03") as client:
        await client.publish("sowgate/seeder-03/seeds", batch("seeder-03", 1, 199), qos=1)
        await client.publish("sowgate/seeder-03/seeds", batch("seeder-03", 341, 400), qos=1)
        await eventually(lambda: ingest.gaps().get("seeder-03") == [(200, 340)], 30, "the gap")
        assert "seeder-03: records 200–340 not received yet" in ingest.summary()
        # the watermark stops at the gap, and lists what is committed above it
        await eventually(lambda: seen.get("seeder-03", {}).get("committed") ==
                         [[1, 199], [341, 400]], 30, "watermark with the gap")
        assert through(seen, "seeder-03") == 199
        await client.publish("sowgate/seeder-03/seeds", batch("seeder-03", 200, 340), qos=1)
        await eventually(lambda: through(seen, "seeder-03") == 400, 30, "gap filled")
        assert ingest.gaps() == {}
    assert gap_text("seeder-03", [(18200, 18340)]) == \
        "seeder-03: records 18 200–18 340 not received yet"


async def test_ids_the_machine_will_never_send_do_not_hold_the_watermark(
    database: str, broker: Mosquitto
) -> None:
    """A cab whose ids do not start at 1 (delivered before this farm server knew it) or jump
    by a reservation block (an unclean stop) says so in ``pending_from``: those ids count as
    done for ``committed_through`` and are not named as missing; a ``pending_from`` above the
    batch's own first id is capped at it."""
    async with running_ingest(database, broker) as ingest, watermarks(broker) as seen, \
            cab(broker, "seeder-10") as client:
        topic = "sowgate/seeder-10/seeds"
        await client.publish(topic, batch("seeder-10", 5001, 5100, pending_from=5001), qos=1)
        await eventually(lambda: through(seen, "seeder-10") == 5100, 30, "through 5100",
                         detail=lambda: (seen, ingest.stats))
        # a block skipped after a kill: 5101..25100 never used
        await client.publish(topic, batch("seeder-10", 25101, 25150, pending_from=25101), qos=1)
        await eventually(lambda: through(seen, "seeder-10") == 25150, 30, "through 25150")
        # a batch without pending_from (an older cab) above a gap: the gap stays a gap
        await client.publish(topic, batch("seeder-10", 25200, 25210), qos=1)
        await eventually(lambda: ingest.gaps().get("seeder-10") == [(25151, 25199)], 30,
                         "a real gap named")
        assert through(seen, "seeder-10") == 25150
        # pending_from beyond the batch: only the ids below the batch are given up
        await client.publish(topic, batch("seeder-10", 25300, 25310, pending_from=99_999),
                             qos=1)
        await eventually(lambda: through(seen, "seeder-10") == 25310, 30, "through 25310")
        await client.publish(topic, batch("seeder-10", 25320, 25330), qos=1)
        await eventually(lambda: ingest.gaps().get("seeder-10") == [(25311, 25319)], 30,
                         "the gap above the capped pending_from")
        assert through(seen, "seeder-10") == 25310
    assert rows(database, "SELECT count(*), count(DISTINCT id) FROM seed_records")[0] == \
        (100 + 50 + 11 + 11 + 11, 100 + 50 + 11 + 11 + 11)
    assert rows(database, "SELECT lo, hi FROM seed_void ORDER BY lo") == \
        [(1, 5000), (5101, 25100), (25151, 25199), (25211, 25299)]
    assert rows(database, "SELECT lo, hi FROM seed_coverage ORDER BY lo") == \
        [(5001, 5100), (25101, 25150), (25200, 25210), (25300, 25310), (25320, 25330)]


async def test_the_point_has_a_gist_index(database: str) -> None:
    (index,) = rows(database, "SELECT indexdef FROM pg_indexes WHERE tablename = "
                    "'seed_records' AND indexname = 'seed_records_geom_gist'")
    assert "USING gist (geom)" in str(index[0])


async def test_alarms_state_and_status_are_kept_state_thinned(
    database: str, broker: Mosquitto
) -> None:
    state = StatePayload(machine_id="seeder-04", utc=T0, work_state="seeding", speed_kmh=8.0)
    alarm = {"id": 7, "machine_id": "seeder-04", "code": "radar.lost", "active": True,
             "severity": "warning", "message": "radar silent", "utc": T0.isoformat()}
    async with running_ingest(database, broker) as ingest, cab(broker, "seeder-04") as client:
        ingest.farm.state_sample_s = 3600.0
        for k in range(5):
            s = state.model_copy(update={"utc": T0 + timedelta(seconds=k)})
            await client.publish("sowgate/seeder-04/state", s.model_dump_json().encode(), qos=1)
        for _ in range(3):
            await client.publish("sowgate/seeder-04/alarms", json.dumps(alarm).encode(), qos=1)
        await client.publish("sowgate/seeder-04/status", b"online", qos=1)
        await eventually(lambda: ingest.stats.alarms_committed == 1
                         and ingest.stats.states_thinned == 4, 30, "alarm and state committed")
        await eventually(lambda: rows(database, "SELECT status FROM machine_status") ==
                         [("online",)], 30, "status")
    assert rows(database, "SELECT count(*) FROM state_samples")[0][0] == 1
    assert rows(database, "SELECT code, active FROM alarm_events") == [("radar.lost", True)]


HOSTILE = [
    ("sowgate/seeder-05/seeds", b"not json"),
    ("sowgate/seeder-05/seeds", b"[" * 100_000 + b"]" * 100_000),  # deep nesting
    ("sowgate/seeder-05/seeds", b'{"machine_id": "seeder-05", "records": [{"id": -1}]}'),
    ("sowgate/seeder-05/seeds", batch("seeder-09", 1, 3)),  # another machine's records
    ("sowgate/seeder-05/alarms", b'{"id": 1}'),
    ("sowgate/seeder-05/state", b"\xff\xfe"),
    ("sowgate/seeder-05/status", b"maybe"),
    ("sowgate/seeder-05/seeds", b"{" + b'"a":' * 1 + b"1" * 70_000 + b"}"),
]


async def test_hostile_payloads_are_counted_never_stored_never_fatal(
    database: str, broker: Mosquitto, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.farm_server.ingest")
    async with running_ingest(database, broker, max_payload_bytes=1_000_000) as ingest, \
            watermarks(broker) as seen, cab(broker, "seeder-05") as client:
        for topic, payload in HOSTILE:
            await client.publish(topic, payload, qos=1)
        await client.publish("sowgate/seeder-05/seeds", b"x" * 1_000_001, qos=1)  # too large
        await eventually(lambda: sum(ingest.stats.rejected.values()) == len(HOSTILE) + 1, 30,
                         "every hostile message rejected", detail=lambda: ingest.stats)
        # and it still works
        await client.publish("sowgate/seeder-05/seeds", batch("seeder-05", 1, 10), qos=1)
        await eventually(lambda: through(seen, "seeder-05") == 10, 30, "a good batch after")
    assert ingest.stats.rejected["impersonation"] == 1
    assert ingest.stats.rejected["too_large"] == 1
    # logged, at most once per reason per 10 s (a flood cannot fill the journal)
    logged = [r for r in caplog.records if "ingest rejected a message" in r.getMessage()]
    assert {r.getMessage().split("(")[1].split(",")[0] for r in logged} == \
        set(ingest.stats.rejected)
    assert len(logged) <= 2 * len(ingest.stats.rejected)
    assert rows(database, "SELECT count(*) FROM seed_records")[0][0] == 10
    assert rows(database, "SELECT count(*) FROM alarm_events")[0][0] == 0
    assert rows(database, "SELECT count(*) FROM machine_status")[0][0] == 0


async def test_the_acl_lets_a_machine_publish_only_as_itself(
    database: str, broker: Mosquitto
) -> None:
    async with running_ingest(database, broker) as ingest, watermarks(broker) as seen, \
            cab(broker, "seeder-06") as client:
        # seeder-06 tries to write seeder-07's records: the broker drops it
        await client.publish("sowgate/seeder-07/seeds", batch("seeder-07", 1, 5), qos=1)
        await client.publish("sowgate/seeder-06/seeds", batch("seeder-06", 1, 5), qos=1)
        await eventually(lambda: through(seen, "seeder-06") == 5, 30, "its own records")
        assert ingest.stats.messages == 1
    assert rows(database, "SELECT DISTINCT machine_id FROM seed_records") == [("seeder-06",)]


async def test_a_flood_while_the_database_is_away_stays_bounded_and_loses_nothing(
    database: str, broker: Mosquitto
) -> None:
    """Back-pressure: with the database away, ingest queues at most ``max_queued_rows`` (and
    one batch over), then reads nothing more and acknowledges nothing more; the broker keeps
    what it does not send, and past UNREAD_MAXIMUM messages received and not read ingest does
    not read its socket (mosquitto 2.0.11 lets more through than the Receive Maximum). Once the
    database is back (and the cab has published again what no watermark covers, were anything
    lost) every record is committed exactly once."""
    from gateway.farm_server.ingest import RECEIVE_MAXIMUM, UNREAD_MAXIMUM
    from tests.gateway.farm_server.conftest import database_away

    batches, per, cap = 160, 500, 1000  # 80 000 records, 5 x RECEIVE_MAXIMUM messages

    async def publish_uncovered(client: aiomqtt.Client, seen: dict[str, dict[str, object]]
                                ) -> None:
        done = through(seen, "seeder-09") or 0
        assert isinstance(done, int)
        for k in range(batches):
            if (k + 1) * per > done:
                await client.publish("sowgate/seeder-09/seeds",
                                     batch("seeder-09", 1 + k * per, (k + 1) * per), qos=1)

    async with running_ingest(database, broker, max_queued_rows=cap) as ingest, \
            watermarks(broker) as seen, cab(broker, "seeder-09") as client:
        database_away(database, True)
        try:
            await publish_uncovered(client, seen)
            # ingest stopped reading; the broker filled at least the window it allows
            await eventually(lambda: ingest.stats.paused > 0
                             and ingest.unread_messages() >= RECEIVE_MAXIMUM - 1, 60,
                             "ingest paused with its receive window full",
                             detail=lambda: (ingest.stats, ingest.unread_messages()))
            assert ingest.stats.peak_queued_rows < cap + per
            # (plus the few packets one read of the socket may bring past it)
            assert ingest.stats.peak_unread_messages <= UNREAD_MAXIMUM + 16
            assert ingest.stats.messages <= cap // per + 1  # read: the cap's worth, no more
            assert ingest.stats.seeds_committed == 0
        finally:
            database_away(database, False)
        await eventually(lambda: ingest.unread_messages() == 0 and ingest._rows == 0, 60,
                         "what ingest held committed", detail=lambda: ingest.stats)
        await publish_uncovered(client, seen)  # the cab's resend of what is not covered
        await eventually(lambda: through(seen, "seeder-09") == batches * per, 60,
                         "every record committed",
                         detail=lambda: (ingest.stats, broker.log.read_text()[-2000:]))
        assert ingest.stats.peak_queued_rows < cap + per
        assert ingest.stats.peak_unread_messages <= UNREAD_MAXIMUM + 16
    assert rows(database, "SELECT count(*), count(DISTINCT id), max(id) FROM seed_records") \
        == [(batches * per, batches * per, batches * per)]


async def retained_watermark(broker: Mosquitto, machine: str, wait_s: float = 0.5) -> object:
    """What a cab connecting now is told: the retained watermark's committed_through, or None
    when the broker holds none (nothing retained arrives within ``wait_s``)."""
    async with aiomqtt.Client(broker.host, broker.port, username="sowgate-ingest") as c:
        await c.subscribe(f"sowgate/{machine}/ingested", qos=1)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(wait_s):
                async for m in c.messages:
                    if m.retain and isinstance(m.payload, bytes) and m.payload:
                        return json.loads(m.payload).get("committed_through")
    return None


async def test_a_retained_watermark_the_broker_lost_comes_back_with_no_cab_sending(
    database: str, broker: Mosquitto, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A broker restarted within ingest's keepalive (or a retained store cleared) loses the
    watermark while ingest stays connected and every cab's records are committed: nobody
    sends, so the active machines' refresh never runs; the full refresh puts it back."""
    from gateway.farm_server import ingest as ingest_module

    monkeypatch.setattr(ingest_module, "WATERMARK_FULL_REFRESH_S", 1.0)
    async with running_ingest(database, broker) as ingest, watermarks(broker) as seen:
        async with cab(broker, "seeder-05") as client:
            await client.publish("sowgate/seeder-05/seeds", batch("seeder-05", 1, 100), qos=1)
            await eventually(lambda: through(seen, "seeder-05") == 100, 30, "watermark 100")
        assert await retained_watermark(broker, "seeder-05") == 100
        # the cab's activity has been refreshed for: from now on nobody sends
        await eventually(lambda: "seeder-05" not in ingest._active, 10, "activity refreshed")
        # the broker's retained copy gone (an empty retained payload deletes it)
        async with aiomqtt.Client(broker.host, broker.port, username="sowgate-ingest") as c:
            await c.publish("sowgate/seeder-05/ingested", b"", qos=1, retain=True)
        # ingest's next full refresh retains it again (a cab connecting is told 100)
        told = None
        async with asyncio.timeout(15):
            while told is None:
                told = await retained_watermark(broker, "seeder-05")
        assert told == 100
