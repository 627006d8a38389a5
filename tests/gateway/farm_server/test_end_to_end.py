"""End to end with the cab's own link (``[mqtt] farm_server_ack``): a record is delivered only
once the farm server has committed it, whatever the broker or an ingest process loses."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import aiomqtt
import pytest

from gateway.config import Settings, parse_config
from gateway.link.mqtt import MqttLink
from tests.gateway.farm_server.conftest import REPO, rows
from tests.gateway.farm_server.test_ingest import running_ingest
from tests.gateway.link.test_mqtt import MACHINE, drops, running_link
from tests.helpers import eventually
from tests.mosquitto import Mosquitto


def cab_settings(broker: Mosquitto, timeout_s: float) -> Settings:
    return parse_config({
        "machine": {"id": MACHINE},
        "mqtt": {
            "enabled": True, "host": broker.host, "port": broker.port, "keepalive": 5,
            "username": MACHINE,  # the ACL's %u: the cab publishes only as itself
            "reconnect_max_s": 0.5, "batch_max_records": 100, "batch_max_ms": 50,
            "max_inflight_batches": 4, "farm_server_ack": True,
            "farm_server_ack_timeout_s": timeout_s,
        },
    })


@contextlib.asynccontextmanager
async def seed_ids_seen(broker: Mosquitto) -> AsyncIterator[list[int]]:
    """Every seed id published on the cab's `seeds`, repeats included (a farm dashboard)."""
    seen: list[int] = []
    ready = asyncio.Event()

    async def run() -> None:
        async with aiomqtt.Client(broker.host, broker.port, username="sowgate-dashboard") as c:
            await c.subscribe(f"sowgate/{MACHINE}/seeds", qos=1)
            ready.set()
            async for m in c.messages:
                assert isinstance(m.payload, bytes)
                seen.extend(r["id"] for r in json.loads(m.payload)["records"])

    task = asyncio.create_task(run())
    try:
        await eventually(ready.is_set, 20, "dashboard subscribed", unless=task)
        yield seen
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_the_cab_publishes_again_what_the_watermark_does_not_cover(
    database: str, broker: Mosquitto, tmp_path: Path
) -> None:
    async with seed_ids_seen(broker) as seen, \
            running_link(cab_settings(broker, 1.0), tmp_path / "cab.sqlite3") as cab:
        cab.store.append_seeds(drops(300))
        cab.store.flush()
        await eventually(lambda: len(seen) >= 300, 30, "first publication")
        # no farm server: the broker's PUBACK alone does not make them delivered ...
        assert cab.store.backlog() == 300
        # ... and after the timeout they go out again
        await eventually(lambda: seen.count(1) >= 2 and cab.link.stats.farm_server_resends, 30,
                         "published again")
        # with no farm server answering, each resend waits twice as long as the one before
        await eventually(lambda: cab.link.stats.farm_server_resends >= 2, 30, "second resend")
        assert cab.link.resend_after_s >= 4.0
        async with running_ingest(database, broker):
            await eventually(lambda: cab.store.backlog() == 0, 60, "watermark covers all",
                             detail=lambda: (cab.store.backlog(), cab.link.stats))
        assert cab.link.stats.farm_server_through == 300
        assert cab.link.resend_after_s == 1.0  # a watermark that covered more: back to 1 s
    assert rows(database, "SELECT count(*), count(DISTINCT id) FROM seed_records")[0] == (300, 300)


async def test_a_watermark_marks_only_what_it_covers(broker: Mosquitto, tmp_path: Path) -> None:
    async with running_link(cab_settings(broker, 3600.0), tmp_path / "cab.sqlite3") as cab:
        cab.store.append_seeds(drops(100))
        cab.store.flush()
        link: MqttLink = cab.link
        link.on_watermark(b'{"committed_through": 40, "committed": [[1, 40], [61, 70]]}')
        assert cab.store.backlog() == 100 - 40 - 10
        assert cab.store.oldest_pending_seed_id() == 41
        for bad in (b"", b"[" * 50_000, b'{"committed_through": "all"}', b'{"x": 1}',
                    b'{"committed_through": 5, "committed": [[1]]}'):
            link.on_watermark(bad)  # ignored, logged
        # ids the store never handed out are not marked (an older box's database)
        link.on_watermark(b'{"committed_through": 10000}')
        assert cab.store.backlog() == 0
        cab.store.append_seeds(drops(5))
        cab.store.flush()
        assert cab.store.backlog() == 5


def ingest_config(path: Path, url: str, broker: Mosquitto) -> Path:
    path.write_text(
        f'[farm_server]\ndatabase_url = "{url}"\nflush_interval_s = 0.1\n\n'
        f'[mqtt]\nhost = "{broker.host}"\nport = {broker.port}\nusername = "sowgate-ingest"\n'
        "keepalive = 5\n", encoding="utf-8")
    return path


def start_ingest(config: Path, log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "gateway.app.cli", "ingest", "--config", str(config)],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=log.open("wb"),
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


async def test_two_ingest_processes_one_sigkilled_every_record_exactly_once(
    database: str, broker: Mosquitto, tmp_path: Path
) -> None:
    config = ingest_config(tmp_path / "ingest.toml", database, broker)
    logs = [tmp_path / "ingest-a.log", tmp_path / "ingest-b.log"]
    procs = [start_ingest(config, log) for log in logs]
    try:
        await eventually(lambda: all(b"share group" in p.read_bytes() for p in logs), 60,
                         "both ingest processes up",
                         detail=lambda: [p.read_text(errors="replace")[-500:] for p in logs])
        await eventually(lambda: all(b"connected" in p.read_bytes() for p in logs), 60,
                         "both subscribed")
        async with running_link(cab_settings(broker, 2.0), tmp_path / "cab.sqlite3") as cab:
            for k in range(40):  # 4 000 records while one ingest dies
                cab.store.append_seeds(drops(100))
                cab.store.flush()
                if k == 15:
                    procs[0].send_signal(signal.SIGKILL)
                    procs[0].wait(timeout=10)
                await asyncio.sleep(0.05)
            await eventually(lambda: cab.store.backlog() == 0, 120, "every record confirmed",
                             detail=lambda: (cab.store.backlog(), cab.link.stats))
            assert cab.link.stats.farm_server_through == 4000
        assert procs[1].poll() is None, "the surviving ingest process kept running"
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(timeout=10)
    count, distinct, lo, hi = rows(
        database, "SELECT count(*), count(DISTINCT id), min(id), max(id) FROM seed_records")[0]
    assert (count, distinct, lo, hi) == (4000, 4000, 1, 4000)
    assert procs[0].returncode == -signal.SIGKILL


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "gateway.app.cli", "ingest", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=60)


def test_config_without_a_database_url_exits_78_naming_the_key(tmp_path: Path) -> None:
    config = tmp_path / "c.toml"
    config.write_text("[farm_server]\nshare_group = \"farm\"\n", encoding="utf-8")
    result = run_cli("--config", str(config))
    assert result.returncode == 78
    assert "farm_server.database_url" in result.stderr
    config.write_text("[farm_server]\ndatabase_url = \"x\"\nshare_group = \"a/b\"\n",
                      encoding="utf-8")
    result = run_cli("--config", str(config))
    assert result.returncode == 78
    assert "farm_server.share_group" in result.stderr


def test_an_older_ingest_refuses_a_newer_schema(database: str, tmp_path: Path) -> None:
    import psycopg

    with psycopg.connect(database, autocommit=True) as conn:
        conn.execute("INSERT INTO sowgate_schema (version) VALUES (99)")
    config = tmp_path / "c.toml"
    config.write_text(f'[farm_server]\ndatabase_url = "{database}"\n', encoding="utf-8")
    for extra in ((), ("--migrate",)):
        result = run_cli("--config", str(config), *extra)
        assert result.returncode == 65, result.stderr
        assert "schema version 99" in result.stderr and "upgrade sowgate" in result.stderr


def documented_grants() -> list[str]:
    """The GRANT statements docs/farm-server.md tells an administrator to run."""
    text = (REPO / "docs" / "farm-server.md").read_text(encoding="utf-8")
    statements, current = [], ""
    for line in text.splitlines():
        line = line.strip().split("--")[0].strip()
        if line.startswith("GRANT") or current:
            current += " " + line
            if current.endswith(";"):
                statements.append(current.strip())
                current = ""
    return statements


async def test_the_ingest_user_works_with_only_the_documented_grants(
    database: str, broker: Mosquitto
) -> None:
    import psycopg

    grants = documented_grants()
    assert len(grants) >= 4
    with psycopg.connect(database, autocommit=True) as owner:
        if owner.execute("SELECT 1 FROM pg_roles WHERE rolname = 'sowgate_ingest'").fetchone() \
                is None:
            with contextlib.suppress(psycopg.errors.DuplicateObject):
                owner.execute("CREATE ROLE sowgate_ingest LOGIN")
        for grant in grants:
            owner.execute(grant.encode())
    url = database.replace("postgres@", "sowgate_ingest@")
    try:
        async with running_ingest(url, broker) as ingest, \
                contextlib.AsyncExitStack() as stack:
            from tests.gateway.farm_server.test_ingest import batch, cab, through, watermarks

            seen = await stack.enter_async_context(watermarks(broker))
            client = await stack.enter_async_context(cab(broker, "seeder-08"))
            await client.publish("sowgate/seeder-08/seeds", batch("seeder-08", 1, 50), qos=1)
            await client.publish("sowgate/seeder-08/status", b"online", qos=1)
            await client.publish("sowgate/seeder-08/status", b"offline", qos=1)
            await eventually(lambda: through(seen, "seeder-08") == 50, 30, "committed",
                             detail=lambda: ingest.stats)
            await eventually(lambda: rows(database, "SELECT status FROM machine_status")
                             == [("offline",)], 30, "status updated")
        with psycopg.connect(url) as conn, pytest.raises(psycopg.errors.InsufficientPrivilege):
            conn.execute("DELETE FROM seed_records")  # it cannot take a record back
    finally:
        with psycopg.connect(database, autocommit=True) as owner:
            owner.execute("REVOKE ALL ON ALL TABLES IN SCHEMA public FROM sowgate_ingest")
            owner.execute("REVOKE ALL ON SCHEMA public FROM sowgate_ingest")
            owner.execute("REVOKE ALL ON FUNCTION sowgate_ensure_day(date) FROM sowgate_ingest")


async def test_the_database_away_loses_nothing_even_past_the_queue_cap(
    database: str, broker: Mosquitto, tmp_path: Path
) -> None:
    from tests.gateway.farm_server.conftest import database_away

    async with running_ingest(database, broker, max_queued_rows=1000) as ingest, \
            running_link(cab_settings(broker, 2.0), tmp_path / "cab.sqlite3") as cab:
        cab.store.append_seeds(drops(500))
        cab.store.flush()
        await eventually(lambda: cab.store.backlog() == 0, 60, "first 500 confirmed")
        database_away(database, True)
        try:
            cab.store.append_seeds(drops(3000))
            cab.store.flush()
            # past the cap ingest stops reading: the broker holds the rest
            await eventually(lambda: ingest.stats.paused > 0, 60,
                             "the queue cap reached", detail=lambda: ingest.stats)
            assert ingest.stats.peak_queued_rows < 1000 + 500  # the cap and one batch
            assert cab.store.backlog() == 3000  # nothing confirmed while the database is away
            await eventually(lambda: ingest.stats.commit_failures > 0, 60, "commit failed")
        finally:
            database_away(database, False)
        await eventually(lambda: cab.store.backlog() == 0, 120, "every record confirmed",
                         detail=lambda: (cab.store.backlog(), ingest.stats, cab.link.stats))
    assert rows(database, "SELECT count(*), count(DISTINCT id), max(id) FROM seed_records")[0] \
        == (3500, 3500, 3500)


@pytest.mark.slow
async def test_the_real_daemon_on_the_simulator_ends_every_record_in_postgresql(
    database: str, broker: Mosquitto, tmp_path: Path
) -> None:
    """`sowgate demo` (the daemon on the simulated planter) with farm_server_ack, through the
    ACL'd broker, into ingest: after it stops, every record its store holds is in PostgreSQL
    exactly once and the watermark it saw covers all of them."""
    import sqlite3

    from tests.gateway.farm_server.test_ingest import through, watermarks
    from tests.helpers import sowgate_env, sowgate_process

    env = sowgate_env(env={
        "SOWGATE_MQTT__HOST": broker.host, "SOWGATE_MQTT__PORT": str(broker.port),
        "SOWGATE_MQTT__USERNAME": "seeder-01", "SOWGATE_MQTT__FARM_SERVER_ACK": "true",
    }, clean=True)
    async with running_ingest(database, broker), watermarks(broker) as seen:
        async with sowgate_process("demo", "--no-tui", "--duration", "8", "--state-dir",
                                   str(tmp_path), env=env) as proc:
            _, err = await asyncio.wait_for(proc.communicate(), 120.0)
        assert proc.returncode == 0, err.decode()[-2000:]
        with contextlib.closing(sqlite3.connect(tmp_path / "records.sqlite3")) as store:
            count, last = store.execute("SELECT count(*), max(id) FROM seeds").fetchone()
        assert count > 20 and count == last  # ids 1..last, none pruned (a loaded host sows less)
        await eventually(lambda: through(seen, "seeder-01") == last, 60, "watermark = last id",
                         detail=lambda: seen)
    assert rows(database, "SELECT count(*), count(DISTINCT id), min(id), max(id) "
                "FROM seed_records WHERE machine_id = 'seeder-01'")[0] == (last, last, 1, last)


def test_ingest_migrates_a_fresh_database_itself_when_it_may(tmp_path: Path) -> None:
    """As the owner it creates the schema at start; as a user that owns nothing it says what
    to run instead (and never half-creates anything)."""
    import uuid

    import psycopg

    from gateway.farm_server.db import SCHEMA_VERSION, SchemaError, ensure_schema, schema_version
    from tests.gateway.farm_server.conftest import ADMIN_URL

    name = f"sowgate_test_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"'.encode())
        if admin.execute("SELECT 1 FROM pg_roles WHERE rolname = 'sowgate_ingest'") \
                .fetchone() is None:
            with contextlib.suppress(psycopg.errors.DuplicateObject):
                admin.execute("CREATE ROLE sowgate_ingest LOGIN")
    url = f"postgresql://postgres@127.0.0.1:5432/{name}"
    try:
        with pytest.raises(SchemaError, match="--migrate"):
            ensure_schema(url.replace("postgres@", "sowgate_ingest@"))
        assert schema_version(url) == 0
        assert ensure_schema(url) == 0
        assert schema_version(url) == SCHEMA_VERSION
        assert ensure_schema(url) == SCHEMA_VERSION  # and again: nothing to do
    finally:
        with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'.encode())


async def test_a_cab_whose_ids_do_not_start_at_1_or_jump_is_confirmed_to_its_last_id(
    database: str, broker: Mosquitto, tmp_path: Path
) -> None:
    """Ids 1..300 delivered on PUBACK before the cab had a farm server, then an unclean stop
    that left the id reservation 20 000 ahead (what a SIGKILL leaves): the farm server never
    gets ids 1..20 300, and the cab's ``pending_from`` says so; the watermark reaches the cab's
    last id and nothing is named missing."""
    from gateway.recording.store import RecordStore
    from gateway.recording.store.ids import reservation_path
    from tests.gateway.farm_server.test_ingest import watermarks

    path = tmp_path / "cab.sqlite3"
    store = RecordStore(path, MACHINE)
    ids = store.append_seeds(drops(300))
    store.flush()
    store.mark_seeds_delivered(list(ids))
    store.close()
    reservation_path(path).write_text('{"seeds": 20300, "alarms": 0}', encoding="utf-8")
    async with running_ingest(database, broker) as ingest, watermarks(broker) as seen, \
            running_link(cab_settings(broker, 2.0), path) as cab:
        cab.store.append_seeds(drops(100))
        cab.store.flush()
        await eventually(lambda: cab.store.backlog() == 0, 60, "every record confirmed",
                         detail=lambda: (cab.store.backlog(), ingest.stats, seen))
        await eventually(lambda: seen.get(MACHINE, {}).get("committed_through") == 20400, 30,
                         "watermark at the last id", detail=lambda: seen)
        assert ingest.gaps() == {}
    assert rows(database, "SELECT count(*), min(id), max(id) FROM seed_records")[0] == \
        (100, 20301, 20400)
    assert rows(database, "SELECT lo, hi FROM seed_void") == [(1, 20300)]


def test_a_version_1_schema_is_migrated_to_2(tmp_path: Path) -> None:
    """The GiST index on the point and seed_void are added to a database ingest 1 made."""
    import uuid

    import psycopg

    from gateway.farm_server.db import MIGRATIONS, SCHEMA_VERSION, ensure_schema, schema_version
    from tests.gateway.farm_server.conftest import ADMIN_URL

    name = f"sowgate_test_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"'.encode())
    url = f"postgresql://postgres@127.0.0.1:5432/{name}"
    try:
        with psycopg.connect(url) as conn:
            conn.execute("CREATE TABLE sowgate_schema (version integer NOT NULL, "
                         "migrated_at timestamptz NOT NULL DEFAULT now())")
            for statement in MIGRATIONS[1]:
                conn.execute(statement.encode())
            conn.execute("INSERT INTO sowgate_schema (version) VALUES (1)")
            conn.execute("SELECT sowgate_ensure_day('2026-04-20')")
        assert ensure_schema(url) == 1
        assert schema_version(url) == SCHEMA_VERSION == 2
        assert rows(url, "SELECT count(*) FROM seed_void")[0][0] == 0
        # the index on the partitioned table reaches the partition made before it
        assert rows(url, "SELECT count(*) FROM pg_indexes WHERE tablename = "
                    "'seed_records_20260420' AND indexdef LIKE '%USING gist (geom)%'")[0][0] == 1
    finally:
        with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'.encode())
