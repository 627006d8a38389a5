"""The farm server's rows (issue 24 §4): the real daemon on the simulated planter, publishing
with ``[mqtt] farm_server_ack`` through a real mosquitto (with the shipped ACL) into
``sowgate ingest`` processes writing the real PostgreSQL; each row breaks one part.

Every row is a *lane* of its own (broker, database, ingest processes, cabs), and the lanes run
side by side, so the group takes about as long as its longest lane. A lane ends only when
every cab's pass is over and the retained ``<prefix>/<machine>/ingested`` watermark covers the
cab's last stored id; then the daemons are stopped and the database is compared id for id
with each cab's store: every record in PostgreSQL exactly once.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import shutil
import signal
import subprocess
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path

import aiomqtt
import psycopg

from gateway.farm_server.db import migrate
from gateway.recording.store import RecordStore
from simulator.machine import SimulatedMachine
from tests.helpers import eventually, sowgate_env, spawn_sowgate
from tests.mosquitto import Mosquitto, free_port
from tests.reliability.harness import DaemonProcess, RowResult, finish_row, steady_drive
from tests.reliability.rows import (
    FARM_ACK_TIMEOUT_S,
    FARM_DUPLICATE_COPIES,
    FARM_FLOOD_BATCHES,
    FARM_INGEST_KILLS,
    FARM_OFFLINE_S,
    FARM_PG_CABS,
    FARM_PG_DOWN_S,
    FARM_REPLAY_EVERY,
)

REPO = Path(__file__).resolve().parents[2]
ACL = REPO / "examples" / "mosquitto-farm.acl"
ADMIN_URL = "postgresql://postgres@127.0.0.1:5432/postgres"
PG_BIN = Path("/usr/lib/postgresql/15/bin")
INGEST_USER = "sowgate-ingest"  # the ACL's farm-side user (reads every machine's topics)
DASHBOARD_USER = "sowgate-dashboard"  # reads sowgate/#
CONFIRM_TIMEOUT_S = 120.0
# daemon start → its first records committed: the daemon, its simulated devices and a first
# GNSS fix on a 2-core host running the whole matrix (load 17-28 measured while writing this)
STARTUP_TIMEOUT_S = 240.0
PUBLISH_S = 30.0  # the flood's publishes: a PUBACK that never comes fails the row, not hangs it
# The cabs sow at 8 km/h until the row has done its fault, then every seed tube falls silent
# (the drive itself would end at a fixed time, whenever the daemons came up on a busy host)
PASS_S = 600.0  # pass over → the watermark covers the last id (a loaded host)


# ---- the parts ------------------------------------------------------------------------------


class IngestProcess:
    """``sowgate ingest --config …`` in its own process, its log appended across restarts."""

    def __init__(self, config: Path, log_path: Path) -> None:
        self.config = config
        self.log_path = log_path
        self.proc: asyncio.subprocess.Process | None = None
        self.exit_codes: list[int] = []
        self._log_at_start = 0

    async def start(self) -> None:
        self._log_at_start = len(self.log_text())
        with self.log_path.open("ab") as log:
            self.proc = await spawn_sowgate(
                "ingest", "--config", str(self.config), env=sowgate_env(clean=True),
                stdout=asyncio.subprocess.DEVNULL, stderr=log,
            )

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.returncode is None

    def subscribed(self) -> bool:
        """This run of it is connected and subscribed (its log says so)."""
        return "ingest connected" in self.log_text()[self._log_at_start:]

    async def kill(self) -> int:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        code = await self.proc.wait()
        self.exit_codes.append(code)
        return code

    async def close(self) -> None:
        if self.running:
            assert self.proc is not None
            self.proc.send_signal(signal.SIGTERM)
            try:
                code = await asyncio.wait_for(self.proc.wait(), 15.0)
            except TimeoutError:
                self.proc.send_signal(signal.SIGKILL)
                code = await self.proc.wait()
            self.exit_codes.append(code)

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""


class PrivatePostgres:
    """A PostgreSQL 15 cluster of its own (initdb in a temp dir, on a free port, trust auth),
    so a row can stop it without touching the machine's shared one on 5432. Run as the
    postgres user (runuser) when we are root; PostGIS comes from the system's PG 15 files."""

    def __init__(self, base: Path) -> None:
        self.dir = base / "pg"
        self.data = self.dir / "data"
        self.port = free_port()
        self.log = self.dir / "postgres.log"

    def _run(self, *argv: str) -> None:
        cmd = [str(PG_BIN / argv[0]), *argv[1:]]
        if os.geteuid() == 0:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)

    def init(self) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:
            shutil.chown(self.dir, "postgres", "postgres")
            # runuser keeps our cwd; the temp dirs above must be traversable by postgres
            for parent in self.dir.parents:
                if str(parent) in ("/", "/tmp"):
                    break
                os.chmod(parent, os.stat(parent).st_mode | 0o755)
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres",
                  "--no-sync", "-E", "UTF8")

    def start(self) -> None:
        opts = (f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 "
                "-c shared_buffers=32MB -c max_connections=40")
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60",
                  "-o", opts, "start")

    def stop(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.stop()

    def url(self, db: str = "postgres") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{db}"


@contextlib.contextmanager
def fresh_database(admin_url: str):  # type: ignore[no-untyped-def]
    """A database with the sowgate schema (migrated as the owner), dropped afterwards."""
    name = f"sowgate_faults_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(admin_url, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"'.encode())
    url = admin_url.rsplit("/", 1)[0] + f"/{name}"
    try:
        migrate(url)
        yield url
    finally:
        with contextlib.suppress(psycopg.Error), \
                psycopg.connect(admin_url, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'.encode())


class Proxy:
    """A TCP relay between a cab and the broker: ``cut()`` drops its connections and refuses
    new ones (the 4G link gone), ``restore()`` lets it through again."""

    def __init__(self) -> None:
        self.target_port = 0
        self.port = free_port()
        self.up = True
        self._writers: set[asyncio.StreamWriter] = set()
        self._server: asyncio.Server | None = None

    def to(self, target_port: int) -> int:
        """Relay to ``target_port``; the port to connect to instead."""
        self.target_port = target_port
        return self.port

    async def __aenter__(self) -> Proxy:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", self.port)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()
        self.cut()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self.up:
            writer.close()
            return
        try:
            up_r, up_w = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            writer.close()
            return
        self._writers.update((writer, up_w))

        async def pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            with contextlib.suppress(OSError, ConnectionError):
                while data := await src.read(65536):
                    if not self.up:
                        break
                    dst.write(data)
                    await dst.drain()
            dst.close()

        await asyncio.gather(pipe(reader, up_w), pipe(up_r, writer), return_exceptions=True)
        self._writers.difference_update((writer, up_w))

    def cut(self) -> None:
        self.up = False
        for w in list(self._writers):
            with contextlib.suppress(Exception):
                w.transport.abort()
        self._writers.clear()

    def restore(self) -> None:
        self.up = True


@dataclass
class Watermarks:
    """The latest ``ingested`` payload per machine, as a cab sees it (reconnects when the
    broker goes away)."""

    port: int
    seen: dict[str, int] = field(default_factory=dict)

    async def run(self) -> None:
        while True:
            with contextlib.suppress(aiomqtt.MqttError):
                async with aiomqtt.Client("127.0.0.1", self.port, username=DASHBOARD_USER,
                                          identifier=f"wm-{uuid.uuid4().hex[:8]}") as c:
                    await c.subscribe("sowgate/+/ingested", qos=1)
                    async for m in c.messages:
                        with contextlib.suppress(ValueError, KeyError, TypeError):
                            data = json.loads(m.payload)  # type: ignore[arg-type]
                            self.seen[m.topic.value.split("/")[1]] = int(
                                data["committed_through"])
            await asyncio.sleep(0.2)

    def through(self, machine: str) -> int:
        return self.seen.get(machine, 0)


async def retained_through(port: int, machine: str, timeout: float = 45.0) -> int | None:
    """What a cab connecting now is told: the retained watermark (None: there is none within
    ``timeout``, which covers ingest's full refresh, WATERMARK_FULL_REFRESH_S). A connection the
    loaded test loop loses is made again; a retained message arrives at once when it is there."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        with contextlib.suppress(TimeoutError, aiomqtt.MqttError):
            async with asyncio.timeout(left), aiomqtt.Client(
                    "127.0.0.1", port, username=DASHBOARD_USER,
                    identifier=f"wm-check-{uuid.uuid4().hex[:8]}") as c:
                await c.subscribe(f"sowgate/{machine}/ingested", qos=1)
                async for m in c.messages:
                    if m.retain:
                        return int(json.loads(m.payload)["committed_through"])  # type: ignore[arg-type]
                    # a live watermark (ingest's refresh): the retained one is now on the
                    # broker too; a new subscription is told it
                    break
        await asyncio.sleep(0.5)
    return None


def store_ids(db: Path, machine: str) -> list[int]:
    if not db.exists():
        return []
    with RecordStore.open_readonly(db, machine) as store:
        return [r.id for r in store.query_seeds()]


def database_ids(url: str, machine: str) -> list[int]:
    with psycopg.connect(url) as conn:
        return [int(i) for (i,) in conn.execute(
            "SELECT id FROM seed_records WHERE machine_id = %s ORDER BY id", (machine,))]


@dataclass
class Cab:
    machine_id: str
    sim: SimulatedMachine
    daemon: DaemonProcess
    store: Path


@dataclass
class Lane:
    """One row's parts, handed to its fault."""

    tmp: Path
    broker: Mosquitto
    url: str
    ingests: list[IngestProcess]
    cabs: list[Cab]
    marks: Watermarks
    res: RowResult
    extra: dict[str, object] = field(default_factory=dict)

    def min_through(self) -> int:
        return min(self.marks.through(c.machine_id) for c in self.cabs)

    def stored_max(self) -> dict[str, int]:
        return {c.machine_id: max(store_ids(c.store, c.machine_id), default=0)
                for c in self.cabs}

    async def confirmed(self, ceilings: dict[str, int], timeout: float, what: str) -> float:
        """Seconds until every cab's watermark reaches its ceiling."""
        return await eventually(
            lambda: all(self.marks.through(m) >= n for m, n in ceilings.items()), timeout,
            what, detail=lambda: (ceilings, dict(self.marks.seen)))


def ingest_config(path: Path, url: str, port: int) -> Path:
    path.write_text(
        f'[farm_server]\ndatabase_url = "{url}"\nflush_interval_s = 0.2\n\n'
        f'[mqtt]\nhost = "127.0.0.1"\nport = {port}\nusername = "{INGEST_USER}"\n'
        "keepalive = 5\n", encoding="utf-8")
    return path


@contextlib.asynccontextmanager
async def lane(
    tmp: Path, url: str, *, cabs: int = 1, ingests: int = 1,
    cab_port: Callable[[int], int] | None = None,
) -> AsyncIterator[Lane]:
    """Broker (ACL), ingest processes and cabs (daemon + simulated planter) running; on exit
    everything is stopped (the row's checks are in ``settle``)."""
    res = RowResult()
    with Mosquitto(listener_options=f"acl_file {ACL}\n") as broker:
        marks = Watermarks(broker.port)
        mark_task = asyncio.create_task(marks.run(), name="farm-watermarks")
        config = ingest_config(tmp / "ingest.toml", url, broker.port)
        procs = [IngestProcess(config, tmp / f"ingest-{k}.log") for k in range(ingests)]
        cab_list: list[Cab] = []
        async with contextlib.AsyncExitStack() as stack:
            try:
                for p in procs:
                    await p.start()
                await eventually(lambda: all(p.subscribed() for p in procs), STARTUP_TIMEOUT_S,
                                 "ingest subscribed",
                                 detail=lambda: [p.log_text()[-400:] for p in procs])
                port = cab_port(broker.port) if cab_port else broker.port
                for k in range(cabs):
                    mid = f"seeder-{k + 1:02d}"
                    sim = await stack.enter_async_context(SimulatedMachine(
                        drive=steady_drive(total_s=PASS_S), with_gnss=True, with_seed_tubes=True,
                        seed=k + 1))
                    cfg = sim.write_config(
                        tmp / f"{mid}.toml", machine={"id": mid},
                        control={"start_working": True},
                        mqtt={"enabled": True, "port": port, "keepalive": 5,
                              "reconnect_max_s": 1.0, "username": mid,
                              "farm_server_ack": True,
                              "farm_server_ack_timeout_s": FARM_ACK_TIMEOUT_S})
                    state = tmp / mid
                    daemon = DaemonProcess(cfg, state, tmp / f"{mid}.log")
                    cab_list.append(Cab(mid, sim, daemon, state / "records.sqlite3"))
                for c in cab_list:
                    await c.daemon.start()
                yield Lane(tmp, broker, url, procs, cab_list, marks, res)
            finally:
                for c in cab_list:
                    await c.daemon.close()
                for p in procs:
                    await p.close()
                mark_task.cancel()
                await asyncio.gather(mark_task, return_exceptions=True)


async def settle(ln: Lane) -> None:
    """The pass over, the watermarks cover every cab's last id; the daemons stopped; then the
    database id for id against each store, and the retained watermark a cab would be told."""
    res = ln.res
    await end_pass(ln)  # the last seeds fall and are committed by the daemon
    last = ln.stored_max()
    t0 = time.monotonic()
    try:
        await ln.confirmed(last, CONFIRM_TIMEOUT_S, "watermark covers every cab's last id")
        res.notes.append(f"last ids confirmed {time.monotonic() - t0:.1f} s after the pass")
    except AssertionError as exc:
        res.problems.append(str(exc)[:400])
    for c in ln.cabs:
        res.check(c.daemon.running, f"{c.machine_id}: the daemon exited on its own")
        code = await c.daemon.stop()
        # 1 is the daemon saying it could not zero the motor on exit: the simulated PWM module
        # of a starved test loop not answering in 0.2 s (the module's watchdog does it); the
        # farm server's rows judge the records, not the RS485 bus of a loaded host
        motor = "could not set motor and fan to 0 on exit" in c.daemon.log_text()[-3000:]
        res.check(code == 0 or (code == 1 and motor),
                  f"{c.machine_id}: graceful stop exited {code}")
        if code == 1 and motor:
            res.notes.append(f"{c.machine_id} exited 1: the simulated PWM module did not answer "
                             "the stop's motor 0 in time (a starved loop)")
    total = 0
    for c in ln.cabs:
        ids = store_ids(c.store, c.machine_id)
        in_db = database_ids(ln.url, c.machine_id)
        total += len(ids)
        res.check(len(ids) > 100, f"{c.machine_id}: only {len(ids)} records stored")
        res.check(ids == list(range(1, len(ids) + 1)),
                  f"{c.machine_id}: the store's ids are not 1..{len(ids)}")
        dup = len(in_db) - len(set(in_db))
        missing = sorted(set(ids) - set(in_db))
        extra = sorted(set(in_db) - set(ids))
        res.check(dup == 0, f"{c.machine_id}: {dup} records twice in the database")
        res.check(not missing, f"{c.machine_id}: {len(missing)} records not in the database "
                               f"(first {missing[:5]})")
        res.check(not extra, f"{c.machine_id}: {len(extra)} ids in the database the cab "
                             f"never stored ({extra[:5]})")
        retained = await retained_through(ln.broker.port, c.machine_id)
        res.check(retained == len(ids), f"{c.machine_id}: the retained watermark says "
                                        f"{retained}, the store's last id is {len(ids)}")
        finish_row(res, c.daemon)
    for p in ln.ingests:
        log = p.log_text()
        res.check("Traceback" not in log, f"a Traceback in {p.log_path.name}")
    res.lost = (f"0 of {total} records lost or doubled ({len(ln.cabs)} cab"
                f"{'s' if len(ln.cabs) > 1 else ''})" if not res.problems
                else f"{total} records stored; see problems")
    resends = sum(c.daemon.log_text().count("publishing them again") for c in ln.cabs)
    res.notes.append(f"cab resends (records not confirmed in {FARM_ACK_TIMEOUT_S:g} s "
                     f"published again): {resends}")
    ln.extra["resends"] = resends


async def end_pass(ln: Lane) -> None:
    """No more seeds: every row of every cab silent (the daemons keep running)."""
    for c in ln.cabs:
        assert c.sim.seed_tubes is not None
        c.sim.seed_tubes.silent_rows.update(range(256))
    await asyncio.sleep(1.5)  # the last seeds are positioned and committed by the daemon


async def seeding(ln: Lane, seconds: float = 3.0) -> None:
    """Every cab's records are being committed (a watermark above 0), then ``seconds`` more."""
    await eventually(lambda: ln.min_through() > 0, STARTUP_TIMEOUT_S, "first records committed",
                     detail=lambda: dict(ln.marks.seen))
    await asyncio.sleep(seconds)


# ---- the rows -------------------------------------------------------------------------------


async def row_pg_down(tmp: Path) -> RowResult:
    pg = PrivatePostgres(tmp)
    await asyncio.to_thread(pg.init)
    await asyncio.to_thread(pg.start)
    try:
        with fresh_database(pg.url()) as url:
            async with lane(tmp, url, cabs=FARM_PG_CABS) as ln:
                await seeding(ln)
                await asyncio.to_thread(pg.stop)
                await asyncio.sleep(FARM_PG_DOWN_S)
                ln.res.check(all(p.running for p in ln.ingests),
                             "ingest exited while PostgreSQL was down")
                ln.res.check(all(c.daemon.running for c in ln.cabs), "a daemon exited")
                await asyncio.to_thread(pg.start)
                ceilings = ln.stored_max()
                took = await ln.confirmed(ceilings, CONFIRM_TIMEOUT_S,
                                          "the outage's records committed")
                ln.res.recovery = (f"records of the outage committed {took:.1f} s after "
                                   "PostgreSQL came back")
                failures = sum(p.log_text().count("commit failed") for p in ln.ingests)
                ln.res.notes.append(f"ingest logged {failures} commit-failure warnings "
                                    "(rate-limited)")
                await settle(ln)
                return ln.res
    finally:
        await asyncio.to_thread(pg.close)


async def row_ingest_kills(tmp: Path) -> RowResult:
    rng = random.Random(24)
    with fresh_database(ADMIN_URL) as url:
        async with lane(tmp, url, ingests=2) as ln:
            await seeding(ln, 1.0)
            restarts = []
            for k in range(FARM_INGEST_KILLS):
                victim = ln.ingests[k % 2]
                other = ln.ingests[(k + 1) % 2]
                await eventually(other.subscribed, STARTUP_TIMEOUT_S, "the other ingest subscribed")
                before = ln.min_through()
                await eventually(lambda b=before: ln.min_through() > b, STARTUP_TIMEOUT_S,
                                 "records committed since the last kill")
                await asyncio.sleep(rng.uniform(0.2, 1.5))  # any phase of a flush
                code = await victim.kill()
                ln.res.check(code == -9, f"kill {k + 1}: ingest exit code {code}, not -9")
                await victim.start()
                restarts.append(await eventually(victim.subscribed, STARTUP_TIMEOUT_S,
                                                 f"ingest restarted after kill {k + 1}"))
            ln.res.recovery = (f"{FARM_INGEST_KILLS} kills, alternating between the two; a "
                               f"killed ingest subscribed again after max {max(restarts):.1f} s")
            ln.res.daemon = "cab running throughout"
            await settle(ln)
            ln.res.daemon = f"cab exited 0; ingest: {FARM_INGEST_KILLS} × −9, restarted"
            return ln.res


async def row_broker_restart(tmp: Path) -> RowResult:
    with fresh_database(ADMIN_URL) as url:
        async with lane(tmp, url) as ln:
            await seeding(ln)
            await asyncio.to_thread(ln.broker.stop)
            await asyncio.to_thread(ln.broker.start)
            ceilings = ln.stored_max()
            took = await ln.confirmed(ceilings, CONFIRM_TIMEOUT_S,
                                      "records of the restart committed")
            ln.res.recovery = (f"every record stored at the restart confirmed {took:.1f} s after "
                               f"(retained watermark, sessions and in-flight messages all lost)")
            await settle(ln)
            return ln.res


async def row_duplicate_flood(tmp: Path) -> RowResult:
    with fresh_database(ADMIN_URL) as url:
        async with lane(tmp, url) as ln:
            mid = ln.cabs[0].machine_id
            port = ln.broker.port
            topic = f"sowgate/{mid}/seeds"
            batches: list[bytes] = []
            flooded = 0
            stop = asyncio.Event()  # a stop flag: a 3.11 publish may swallow a cancel

            async def flood() -> None:
                nonlocal flooded
                async with aiomqtt.Client("127.0.0.1", port, username=DASHBOARD_USER,
                                          identifier="flood-read") as reader, \
                        aiomqtt.Client("127.0.0.1", port, username=mid,
                                       identifier="flood-write") as writer:
                    await reader.subscribe(topic, qos=1)
                    async for m in reader.messages:
                        if stop.is_set():
                            return
                        payload = m.payload
                        assert isinstance(payload, bytes)
                        if payload in batches:
                            continue  # our own copies come back too
                        batches.append(payload)
                        for _ in range(FARM_DUPLICATE_COPIES):
                            await writer.publish(topic, payload, qos=1, timeout=PUBLISH_S)
                            flooded += 1
                        if len(batches) % FARM_REPLAY_EVERY == 0:  # a replay of the last ones
                            for old in batches[-FARM_REPLAY_EVERY - 1:-1]:
                                await writer.publish(topic, old, qos=0, timeout=PUBLISH_S)
                                flooded += 1

            task = asyncio.create_task(flood(), name="duplicate-flood")
            try:
                await eventually(lambda: len(batches) >= FARM_FLOOD_BATCHES or task.done(),
                                 STARTUP_TIMEOUT_S, f"{FARM_FLOOD_BATCHES} batches flooded",
                                 detail=lambda: (len(batches), flooded))
                await end_pass(ln)
                await asyncio.sleep(1.0)  # the flood of the last batches
            finally:
                stop.set()
                task.cancel()
                # bounded without waiting for the cancel to land (a publish may swallow it)
                await asyncio.wait({task}, timeout=10.0)
            if task.done() and not task.cancelled() and task.exception() is not None \
                    and len(batches) < FARM_FLOOD_BATCHES:
                ln.res.problems.append(f"the flood failed: {task.exception()!r}")
            # one more replay of every batch after the pass, at QoS 1
            async with aiomqtt.Client("127.0.0.1", port, username=mid,
                                      identifier="flood-replay") as writer:
                for old in batches:
                    await writer.publish(topic, old, qos=1, timeout=PUBLISH_S)
                    flooded += 1
            ln.res.check(len(batches) >= FARM_FLOOD_BATCHES,
                         f"only {len(batches)} batches flooded")
            ln.res.recovery = (f"{flooded} duplicate messages ({FARM_DUPLICATE_COPIES} copies of "
                               f"each of {len(batches)} batches, the last {FARM_REPLAY_EVERY} "
                               f"replayed at every {FARM_REPLAY_EVERY}th, all once more after "
                               "the pass)")
            await settle(ln)
            return ln.res


async def row_cab_offline(tmp: Path) -> RowResult:
    with fresh_database(ADMIN_URL) as url:
        async with Proxy() as proxy, lane(tmp, url, cab_port=proxy.to) as ln:
            await seeding(ln)
            proxy.cut()
            t_cut = time.monotonic()
            before = ln.stored_max()
            await asyncio.sleep(FARM_OFFLINE_S)
            held = {m: n - before[m] for m, n in ln.stored_max().items()}
            proxy.restore()
            offline = time.monotonic() - t_cut
            ceilings = ln.stored_max()
            took = await ln.confirmed(ceilings, CONFIRM_TIMEOUT_S, "the held records confirmed")
            ln.res.recovery = (f"{sum(held.values())} records stored while offline "
                               f"({offline:.0f} s) confirmed {took:.1f} s after the link came "
                               "back")
            await settle(ln)
            return ln.res


ROW_FUNCS: dict[str, Callable[[Path], Awaitable[RowResult]]] = {
    "farm_postgres_down": row_pg_down,
    "farm_ingest_sigkill_x5": row_ingest_kills,
    "farm_broker_restart_no_persistence": row_broker_restart,
    "farm_duplicate_flood": row_duplicate_flood,
    "farm_cab_offline": row_cab_offline,
}


async def group_farm(tmp: Path) -> dict[str, RowResult]:
    """The farm server's rows, each in its own lane, side by side."""

    async def one(name: str) -> RowResult:
        started = time.monotonic()
        try:
            res = await ROW_FUNCS[name](tmp / name)
        except Exception as exc:
            import traceback

            res = RowResult(problems=[f"the row failed: {exc!r}"],
                            notes=["".join(traceback.format_exception(exc))[-1500:]])
        res.notes.append(f"lane {time.monotonic() - started:.0f} s")
        return res

    names = list(ROW_FUNCS)
    for name in names:
        (tmp / name).mkdir(parents=True, exist_ok=True)
    results = await asyncio.gather(*(one(n) for n in names))
    return dict(zip(names, results, strict=True))
