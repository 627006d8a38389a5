"""Seed records/s from sensor edge to PUBACK, control latency under that load, daemon RSS/CPU.

Issue 4 §8. Everything runs against one mosquitto started here on a free port.

(a) Throughput. GNSS epochs (10 Hz) and seed-tube edges of a 48-row planter at 16 km/h are
    made up in memory beforehand and fed to ``SeedRecorder.on_epoch``/``on_edge`` as fast as
    the event loop takes them: positioning, store append, commit, outbox read, publish QoS 1
    with several batches in flight and mark-delivered on PUBACK are all inside the figure
    (no ptys: the serial drivers are not what is measured). The reference, same run: raw
    aiomqtt publishing the same records in the same 500-record batches from memory, no store
    and no positioning. Both again through a relay adding a 4G-like round trip (``RTT_S``).
    A third local row starts at the store (already positioned drops): the outbox's own cost.
(b) Control latency under load. The real ``gateway.app.daemon.Daemon`` runs against
    ``simulator.machine.SimulatedMachine`` (RS485 and HMI on ptys, as in bench_latency), with
    its own record store and MQTT link; synthetic epochs and seed edges come in real time at
    the nominal 2 100 seeds/s. The seed edges are read by the real ``GpioSeedSensors`` from a
    synthetic kernel queue (``SyntheticLines``), with the driver's own read timing: ahead of
    each epoch, as the daemon wires it, and on its own tick grid when no epoch comes. The
    epochs (the GNSS reader is replaced by the feeder, on the daemon's event loop as it would
    be) each come on their own wake-up, ``GNSS_LATENCY_S`` after their time.
    ``daemon.latencies_s`` (reply → PWM write) gives the p99; the reference is the same daemon
    with no seeds.
(c) RSS and CPU. The daemon runs in a child process (``python -m benchmarks.bench_mqtt
    --daemon``); the simulator and the broker stay outside it. CPU is read from
    ``/proc/<pid>/stat`` (utime + stime) over ``DAEMON_MEASURE_S`` after a warm-up, RSS from
    ``/proc/<pid>/status`` (VmRSS at the end, VmHWM peak). The child's figure includes the
    feeder's making of the synthetic epochs and kernel edge events (a few µs per seed); that
    part is timed with ``time.thread_time``, shown apart and left out of the target check,
    since in the field the receiver's parser and the kernel do it. The GPIO driver's reading
    and the recorder stay counted. This is the wall-clock view, and it moves with the
    machine's load (other processes' cache and CPU-time pressure land in the child's utime);
    ``bench_cpu`` counts the per-seed part in instructions, which the load does not move.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, NamedTuple

import aiomqtt

from drivers.gnss_reader import GnssEpoch
from drivers.seed_sensors import GpioSeedSensors, SeedEdgeEvent
from gateway.config import Settings, load_config, parse_config
from gateway.core.alarms import AlarmBoard
from gateway.core.commands import Command
from gateway.core.records import SeedDrop, SeedRecord
from gateway.link.mqtt import MqttLink
from gateway.link.payloads import SeedBatch, StatePayload
from gateway.recording.recorder import SeedRecorder
from gateway.recording.store import RecordStore
from tests.mosquitto import Mosquitto

ROWS = 48
WIDTH_M = 36.0
SPEED_KMH = 16.0
NOMINAL_PER_S = 2_100.0  # a 48-row planter at 16 km/h
EPOCH_S = 0.1
FLAT_OUT_SEEDS = 60_000
FEED_CHUNK = 200  # events handed to the recorder between event-loop turns when flat out
STORE_APPEND = 100
BATCH = 500
INFLIGHT = 8
TARGET_PER_S = 5_000.0
TARGET_RATIO = 0.5
TARGET_RSS_MB = 100.0
TARGET_CPU_PCT = 5.0
TARGET_P99_MS = 5.0
RTT_S = 0.1
POLL_HZ = 10.0
REFRESH_S = 0.05  # < 1 / POLL_HZ
GNSS_LATENCY_S = 0.02  # from an epoch's UTC time to its arrival at the host
DAEMON_WARMUP_S = 4.0
DAEMON_MEASURE_S = 20.0
CPU_RUNS = 3
BASELINE_MEASURE_S = 8.0
PROXY_READ_BYTES = 65_536
MACHINE = "bench"
ORIGIN = (43.8, 125.3)
UTC0 = datetime(2026, 4, 20, 8, tzinfo=UTC)


def _planter(extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Config sections of a 48-row, 36 m planter (0.75 m rows; the daemon derives the row
    offsets from rows and width)."""
    data: dict[str, Any] = {
        "machine": {"id": MACHINE, "rows": ROWS, "working_width_m": WIDTH_M},
    }
    for section, values in (extra or {}).items():
        data.setdefault(section, {}).update(values)
    return data


@dataclass
class SyntheticField:
    """Synthetic GNSS epochs and seed edges: straight north at SPEED_KMH, rows in turn."""

    t0_mono: float
    seeds_per_s: float = NOMINAL_PER_S
    next_epoch: int = 0
    next_seed: int = 0

    def until(self, t_s: float) -> list[GnssEpoch | SeedEdgeEvent]:
        """Every event up to ``t_s`` after t0 not handed out yet, in time order."""
        out: list[GnssEpoch | SeedEdgeEvent] = []
        while True:
            te = self.next_epoch * EPOCH_S
            ts = self.next_seed / self.seeds_per_s
            if min(te, ts) > t_s:
                return out
            if te <= ts:
                out.append(self._epoch())
            else:
                out.append(self._edge())

    def epochs_until(self, t_s: float) -> list[GnssEpoch]:
        """The epochs up to ``t_s`` after t0 not handed out yet."""
        out: list[GnssEpoch] = []
        while self.next_epoch * EPOCH_S <= t_s:
            out.append(self._epoch())
        return out

    def take_seeds(self, t_s: float) -> range:
        """The numbers of the seeds up to ``t_s`` after t0 not handed out yet: seed k passes
        the sensor of row 1 + k % ROWS at t0 + k / seeds_per_s."""
        first = self.next_seed
        self.next_seed = max(first, math.floor(t_s * self.seeds_per_s) + 1)
        return range(first, self.next_seed)

    def _epoch(self) -> GnssEpoch:
        te = self.next_epoch * EPOCH_S
        self.next_epoch += 1
        return GnssEpoch(
            utc=UTC0 + timedelta(seconds=te), t_mono=self.t0_mono + te + GNSS_LATENCY_S,
            lat=ORIGIN[0] + SPEED_KMH / 3.6 * te / 111_120.0, lon=ORIGIN[1], alt_m=200.0,
            fix="rtk_fixed", speed_kmh=SPEED_KMH, course_deg=0.0, heading_deg=0.0,
            heading_valid=True, num_sv=24,
        )

    def _edge(self) -> SeedEdgeEvent:
        ts = self.next_seed / self.seeds_per_s
        self.next_seed += 1
        return SeedEdgeEvent(row=1 + (self.next_seed - 1) % ROWS, t_mono=self.t0_mono + ts)


class _FallingEdge:
    name = "FALLING_EDGE"


class _KernelEdge(NamedTuple):
    """What gpiod hands the driver for one edge (``gpiod.EdgeEvent``'s fields it reads)."""

    event_type: type[_FallingEdge]
    timestamp_ns: int
    line_offset: int
    global_seqno: int


class SyntheticLines:
    """A GPIO line request whose kernel queue is the synthetic field, for the real
    ``GpioSeedSensors`` in the daemon child. Its fd is a pipe kept readable, so the driver
    finds edges whenever it reads, on its own timer or from ``read_pending``: the reads, and
    the wake-ups they need, are the driver's own. Line offset k is row k + 1."""

    def __init__(self, field: SyntheticField, making: dict[str, float]) -> None:
        self.field = field
        self.making = making
        self.seqno = 0
        self._r, self._w = os.pipe()
        os.write(self._w, b"x")  # never drained: always "readable"

    @property
    def fd(self) -> int:
        return self._r

    def read_edge_events(self) -> list[_KernelEdge]:
        c0 = time.thread_time()
        field = self.field
        seeds = field.take_seeds(time.monotonic() - field.t0_mono)
        t0_ns, ns_per_seed = field.t0_mono * 1e9, 1e9 / field.seeds_per_s
        seqno = self.seqno + 1 - seeds.start
        out = [
            _KernelEdge(_FallingEdge, round(t0_ns + k * ns_per_seed), k % ROWS, seqno + k)
            for k in seeds
        ]
        self.seqno += len(out)
        self.making["cpu_s"] += time.thread_time() - c0
        self.making["seeds"] = field.next_seed
        return out

    def release(self) -> None:
        os.close(self._r)
        os.close(self._w)


def _feed(recorder: SeedRecorder, events: list[GnssEpoch | SeedEdgeEvent]) -> None:
    for ev in events:
        if isinstance(ev, SeedEdgeEvent):
            recorder.on_edge(ev)
        else:
            recorder.on_epoch(ev)


class DelayProxy:
    """TCP relay that delivers every chunk RTT/2 late in each direction, in its own thread.

    Its own thread and loop, so its work does not count against the link being measured.
    """

    def __init__(self, target_port: int, rtt_s: float) -> None:
        self.target_port = target_port
        self.delay_s = rtt_s / 2
        self.port = 0
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=lambda: asyncio.run(self._serve()),
                                        name="bench-delay-proxy")

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        self.port = server.sockets[0].getsockname()[1]
        self._ready.set()
        async with server:
            await self._stop.wait()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_r, up_w = await asyncio.open_connection("127.0.0.1", self.target_port)
        try:
            await asyncio.gather(self._pump(reader, up_w), self._pump(up_r, writer),
                                 return_exceptions=True)
        except asyncio.CancelledError:
            pass  # the proxy is shutting down at the end of the bench
        finally:
            writer.close()
            up_w.close()

    async def _pump(self, r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

        async def deliver() -> None:
            while True:
                due, data = await queue.get()
                if not data:
                    break
                await asyncio.sleep(max(0.0, due - loop.time()))
                w.write(data)
                await w.drain()
            w.close()

        task = asyncio.create_task(deliver(), name="bench-proxy-deliver")
        try:
            while data := await r.read(PROXY_READ_BYTES):
                queue.put_nowait((loop.time() + self.delay_s, data))
        except OSError:
            pass
        queue.put_nowait((0.0, b""))
        await asyncio.gather(task, return_exceptions=True)

    @contextmanager
    def running(self) -> Iterator[DelayProxy]:
        self._thread.start()
        self._ready.wait(10)
        try:
            yield self
        finally:
            if self._loop is not None and self._stop is not None:
                self._loop.call_soon_threadsafe(self._stop.set)
            self._thread.join(10)


class _Sink:
    def execute(self, command: Command, source: str) -> str:
        return "ok"


def _pct(values: list[float], q: float) -> float:
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))] if values else 0.0


@contextmanager
def _link(port: int, db: Path) -> Iterator[tuple[Settings, RecordStore, MqttLink]]:
    settings = parse_config(_planter({
        "mqtt": {"enabled": True, "port": port, "batch_max_records": BATCH,
                 "max_inflight_batches": INFLIGHT, "batch_max_ms": 500},
    }))
    store = RecordStore(db, MACHINE, commit_interval_s=0.2)
    link = MqttLink(settings, store, _Sink(),
                    lambda: StatePayload(machine_id=MACHINE, utc=datetime.now(UTC),
                                         work_state="working"),
                    AlarmBoard(MACHINE))
    try:
        yield settings, store, link
    finally:
        store.close()


async def _until_connected(link: MqttLink) -> None:
    while not link.connected:  # noqa: ASYNC110 (polling a plain flag)
        await asyncio.sleep(0.01)


async def _until_published(link: MqttLink, n: int) -> None:
    while link.stats.seeds_published < n:  # noqa: ASYNC110 (a plain counter)
        await asyncio.sleep(0.002)


async def _edge_to_puback(port: int, db: Path) -> tuple[float, list[SeedRecord]]:
    """Edges fed flat out through the recorder; records/s until the last PUBACK."""
    with _link(port, db) as (settings, store, link):
        recorder = SeedRecorder(settings, store)  # wired as the daemon wires it
        field = SyntheticField(t0_mono=time.monotonic() + 3600.0)  # never times out
        events = field.until(FLAT_OUT_SEEDS / field.seeds_per_s)
        # one more epoch so the last seeds find their bracketing epoch, as they would live
        tail = field.until(FLAT_OUT_SEEDS / field.seeds_per_s + 2 * EPOCH_S)
        tail = [e for e in tail if isinstance(e, GnssEpoch)]
        tasks = [asyncio.create_task(store.run(), name="bench-store"),
                 asyncio.create_task(link.run(), name="bench-link"),
                 asyncio.create_task(recorder.run(), name="bench-recorder")]
        try:
            await _until_connected(link)
            t0 = time.perf_counter()
            for i in range(0, len(events), FEED_CHUNK):
                _feed(recorder, events[i:i + FEED_CHUNK])
                await asyncio.sleep(0)
            _feed(recorder, tail)
            recorder.flush()
            await _until_published(link, recorder.records_stored)
            elapsed = time.perf_counter() - t0
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        records = list(store.query_seeds())  # for the raw reference, outside the timing
    return len(records) / elapsed, records


async def _store_to_puback(port: int, db: Path, drops: list[SeedDrop]) -> float:
    """Already positioned drops appended flat out: the outbox's own cost (no positioning)."""
    with _link(port, db) as (_settings, store, link):
        tasks = [asyncio.create_task(store.run(), name="bench-store"),
                 asyncio.create_task(link.run(), name="bench-link")]
        try:
            await _until_connected(link)
            t0 = time.perf_counter()
            for i in range(0, len(drops), STORE_APPEND):
                store.add_seeds(drops[i:i + STORE_APPEND])
                await asyncio.sleep(0)
            await _until_published(link, len(drops))
            elapsed = time.perf_counter() - t0
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
    return len(drops) / elapsed


async def _raw(port: int, records: list[SeedRecord]) -> float:
    """The same records in the same batches, serialised and published from memory."""
    slots = asyncio.Semaphore(INFLIGHT)
    batches = [records[i:i + BATCH] for i in range(0, len(records), BATCH)]

    async def one(client: aiomqtt.Client, batch: list[SeedRecord]) -> None:
        try:
            payload = SeedBatch.model_construct(machine_id=MACHINE, records=batch)
            await client.publish(f"sowgate/{MACHINE}/seeds", payload.model_dump_json().encode(),
                                 qos=1, timeout=60)
        finally:
            slots.release()

    async with aiomqtt.Client("127.0.0.1", port, identifier="bench-raw",
                              max_inflight_messages=INFLIGHT + 8) as client:
        t0 = time.perf_counter()
        async with asyncio.TaskGroup() as tg:
            for i, batch in enumerate(batches):
                await slots.acquire()
                tg.create_task(one(client, batch), name=f"bench-raw-{i}")
        return len(records) / (time.perf_counter() - t0)


# ------------------------------------------------------------------ the daemon child process


async def _daemon_child(config: Path, state_dir: Path, run_s: float,
                        seeds_per_s: float) -> dict[str, Any]:
    from gateway.app.daemon import Daemon, settle_gc

    settings = load_config(config)
    daemon = Daemon(settings, state_dir)
    recorder: SeedRecorder | None = None
    # CPU the feeder spends making up the synthetic epochs and kernel edge events (work the
    # receiver's parser and the kernel would do instead, so it is reported apart); the GPIO
    # driver reading the edges and handing them on, and the recorder, are counted.
    making = {"cpu_s": 0.0, "seeds": 0.0}
    if seeds_per_s > 0:
        assert daemon.parts.store is not None, "the bench config has MQTT on, so a store"
        recorder = SeedRecorder(settings, daemon.parts.store)
        field = SyntheticField(t0_mono=time.monotonic(), seeds_per_s=seeds_per_s)
        lines = SyntheticLines(field, making)
        sensors = GpioSeedSensors(
            "bench", list(range(ROWS)), settings.seed_sensors.debounce_ms, recorder.on_edge,
            request_factory=lambda chip, offsets, bias: lines,
        )

        async def feed_epochs() -> None:
            # as GnssReader does: each epoch as it arrives, GNSS_LATENCY_S after its UTC
            # time, to the listeners the daemon wires (gateway.app.wiring): the GPIO
            # lines are read first, then the recorder queues the epoch
            assert recorder is not None
            loop = asyncio.get_running_loop()
            while True:
                due = field.t0_mono + field.next_epoch * EPOCH_S + GNSS_LATENCY_S
                await asyncio.sleep(max(0.0, due - time.monotonic()))
                c0 = time.thread_time()
                epochs = field.epochs_until(loop.time() - field.t0_mono - GNSS_LATENCY_S)
                making["cpu_s"] += time.thread_time() - c0
                for epoch in epochs:
                    sensors.read_pending()
                    recorder.on_epoch(epoch)

        daemon.add_task("seed-sensors", sensors.run)
        daemon.add_task("bench-gnss-epochs", feed_epochs)
        daemon.add_task("seed-recorder", recorder.run)

    async def stop_later() -> None:
        await asyncio.sleep(run_s)
        daemon.request_stop()

    settle_gc()  # as ``sowgate run`` does once the daemon is built
    stopper = asyncio.create_task(stop_later(), name="bench-stop")
    await daemon.run()
    await stopper
    link = daemon.parts.mqtt
    return {
        "latencies_s": list(daemon.latencies_s),
        "stored": recorder.records_stored if recorder else 0,
        "published": link.stats.seeds_published if link else 0,
        "feeder_s_per_seed": making["cpu_s"] / making["seeds"] if making["seeds"] else 0.0,
    }


def _proc_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _proc_kb(pid: int, key: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return float(line.split()[1])
    return 0.0


async def _daemon_run(broker_port: int, tmp: Path, name: str, seeds_per_s: float,
                      measure_s: float, *, every_tick: bool = True) -> dict[str, float]:
    """Simulated machine here, daemon in a child: its CPU, RSS and control latency.

    ``every_tick``: poll at POLL_HZ and rewrite the duty every tick (the latency runs); else
    the daemon's default control settings (the CPU runs: what a box runs at).
    """
    control: dict[str, Any] = {"control": {"start_working": True}}
    if every_tick:
        # rewrite the duty every tick, so every tick yields a latency sample (at a steady
        # speed the duty barely changes and writes would be rare)
        control |= {"rs485": {"poll_hz": POLL_HZ}, "actuators": {"refresh_s": REFRESH_S}}
    from simulator.machine import SimulatedMachine
    from simulator.plant import Drive, Leg

    drive = Drive(legs=[Leg(0.5, 0.0), Leg(600.0, SPEED_KMH)], dt=0.02)
    state_dir = tmp / name
    state_dir.mkdir()
    out = tmp / f"{name}.json"
    async with SimulatedMachine(drive=drive, crop="wheat") as machine:
        config = machine.write_config(
            tmp / f"{name}.toml",
            **_planter({**control, "mqtt": {"enabled": True, "port": broker_port}}),
        )
        run_s = DAEMON_WARMUP_S + measure_s + 1.0
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "benchmarks.bench_mqtt", "--daemon", str(config),
            str(state_dir), str(run_s), str(seeds_per_s), str(out),
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )
        try:
            await asyncio.sleep(DAEMON_WARMUP_S)
            cpu0, t0 = _proc_cpu_s(proc.pid), time.perf_counter()
            await asyncio.sleep(measure_s)
            cpu1, t1 = _proc_cpu_s(proc.pid), time.perf_counter()
            rss_kb, hwm_kb = _proc_kb(proc.pid, "VmRSS"), _proc_kb(proc.pid, "VmHWM")
            _, err = await asyncio.wait_for(proc.communicate(), 30.0)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    if proc.returncode != 0:
        raise RuntimeError(f"daemon child failed: {err.decode(errors='replace')[-2000:]}")
    data = json.loads(out.read_text())
    lat = data["latencies_s"]
    return {
        "cpu_pct": (cpu1 - cpu0) / (t1 - t0) * 100, "rss_mb": rss_kb / 1024,
        "hwm_mb": hwm_kb / 1024, "p50_ms": _pct(lat, 0.5) * 1e3,
        "p99_ms": _pct(lat, 0.99) * 1e3, "max_ms": max(lat, default=0.0) * 1e3,
        "samples": float(len(lat)), "stored": float(data["stored"]),
        "published": float(data["published"]),
        "feeder_cpu_pct": data["feeder_s_per_seed"] * seeds_per_s * 100,
    }


async def _measure() -> dict[str, float]:
    fig: dict[str, float] = {}
    with Mosquitto() as broker, tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        fig["local_edge_per_s"], records = await _edge_to_puback(broker.port, tmp / "e.db")
        fig["local_raw_per_s"] = await _raw(broker.port, records)
        drops = [SeedDrop.model_construct(**{k: v for k, v in r.__dict__.items()
                                             if k not in ("id", "machine_id")})
                 for r in records]
        fig["local_store_per_s"] = await _store_to_puback(broker.port, tmp / "s.db", drops)
        with DelayProxy(broker.port, RTT_S).running() as proxy:
            fig["rtt_edge_per_s"], _ = await _edge_to_puback(proxy.port, tmp / "r.db")
            fig["rtt_raw_per_s"] = await _raw(proxy.port, records)
        for name, rate, seconds in (("idle", 0.0, BASELINE_MEASURE_S),
                                    ("nominal", NOMINAL_PER_S, DAEMON_MEASURE_S)):
            for key, value in (await _daemon_run(broker.port, tmp, name, rate,
                                                 seconds)).items():
                fig[f"{name}_{key}"] = value
        # CPU at the default control settings: the median of CPU_RUNS runs, because one
        # 20 s reading on a shared 2-core machine varies by about ±0.5 points of a core
        for name, rate, seconds in (("default_idle", 0.0, BASELINE_MEASURE_S),
                                    ("default", NOMINAL_PER_S, DAEMON_MEASURE_S)):
            runs = [
                await _daemon_run(broker.port, tmp, f"{name}{k}", rate, seconds,
                                  every_tick=False)
                for k in range(CPU_RUNS if rate else 1)
            ]
            cpu = sorted(r["cpu_pct"] - r["feeder_cpu_pct"] for r in runs)
            fig[f"{name}_cpu_pct"] = statistics.median(cpu)
            fig[f"{name}_cpu_min"], fig[f"{name}_cpu_max"] = cpu[0], cpu[-1]
            fig[f"{name}_hwm_mb"] = max(r["hwm_mb"] for r in runs)
            fig[f"{name}_feeder_cpu_pct"] = statistics.median(r["feeder_cpu_pct"] for r in runs)
    return fig


def run() -> dict[str, object]:
    f = asyncio.run(_measure())
    local = f["local_edge_per_s"] / f["local_raw_per_s"]
    store_ratio = f["local_store_per_s"] / f["local_raw_per_s"]
    rtt = f["rtt_edge_per_s"] / f["rtt_raw_per_s"]
    fig: dict[str, object] = dict(f, local_ratio=local, rtt_ratio=rtt, store_ratio=store_ratio)

    def ok(good: bool) -> str:
        return "met" if good else "NOT met"

    p99, p99_idle = f["nominal_p99_ms"], f["idle_p99_ms"]
    feeder = f["nominal_feeder_cpu_pct"]
    daemon_cpu = f["nominal_cpu_pct"] - feeder
    fig["markdown"] = (
        "### MQTT: seed records from sensor edge to PUBACK; the daemon under that load\n\n"
        f"{ROWS}-row planter at {SPEED_KMH:g} km/h, synthetic 10 Hz GNSS epochs and seed "
        f"edges fed in-process to `SeedRecorder` ({FLAT_OUT_SEEDS:,} seeds, as fast as the "
        f"loop takes them): positioning + store + commit + outbox + QoS 1 publish ({BATCH}-"
        f"record batches, {INFLIGHT} in flight) + mark delivered on PUBACK. Reference: raw "
        "aiomqtt publishing the same records in the same batches from memory (no store, no "
        "positioning), same run, same mosquitto. The RTT rows go through a relay adding "
        f"{RTT_S * 1e3:g} ms round trip (4G-like).\n\n"
        "| path | link | records/s | raw aiomqtt (records/s) | ratio |\n|---|---|---|---|---|\n"
        f"| edge → PUBACK | local | {f['local_edge_per_s']:,.0f} | {f['local_raw_per_s']:,.0f} "
        f"| {local:.2f} |\n"
        f"| edge → PUBACK | {RTT_S * 1e3:g} ms RTT | {f['rtt_edge_per_s']:,.0f} "
        f"| {f['rtt_raw_per_s']:,.0f} | {rtt:.2f} |\n"
        f"| store append → PUBACK (no positioning) | local | {f['local_store_per_s']:,.0f} "
        f"| {f['local_raw_per_s']:,.0f} | {store_ratio:.2f} |\n\n"
        f"Targets: ≥ {TARGET_PER_S:,.0f} records/s edge → PUBACK: "
        f"{ok(min(f['local_edge_per_s'], f['rtt_edge_per_s']) >= TARGET_PER_S)}; "
        f"≥ {TARGET_RATIO} × raw: {ok(rtt >= TARGET_RATIO)} over the RTT link, "
        f"{ok(local >= TARGET_RATIO)} on the local link (there raw publishing costs only "
        "the JSON encoding, while each outbox record is also positioned, written, committed, "
        "read back and marked: the local ratio is the CPU cost per record, the RTT ratio is "
        "what a 4G link sees).\n\n"
        "Real daemon (`gateway.app.daemon.Daemon`, own process) against the simulated machine "
        f"(RS485 + HMI on ptys, {POLL_HZ:g} Hz control loop, duty rewritten every tick), its "
        "record store and MQTT link "
        f"on the same broker; seeds fed in real time at {NOMINAL_PER_S:,.0f}/s into a "
        "`SeedRecorder` on its store: synthetic 10 Hz epochs stand in for the GNSS reader, "
        "and the edges come through the real GPIO seed-sensor driver from a synthetic kernel "
        "queue, read ahead of each epoch as the daemon wires it. CPU from /proc over "
        f"{DAEMON_MEASURE_S:g} s after {DAEMON_WARMUP_S:g} s warm-up; reference: the same "
        f"daemon with no seeds ({BASELINE_MEASURE_S:g} s).\n\n"
        "| daemon | control p99 reply→write (samples) | max | CPU (% of one core) "
        "| of which the synthetic feeder | RSS (peak) "
        "| seeds stored / PUBACKed |\n|---|---|---|---|---|---|---|\n"
        f"| no seeds | {p99_idle:.2f} ms ({f['idle_samples']:.0f}) | {f['idle_max_ms']:.2f} ms "
        f"| {f['idle_cpu_pct']:.1f} % | – "
        f"| {f['idle_rss_mb']:.0f} MB ({f['idle_hwm_mb']:.0f} MB) | – |\n"
        f"| {NOMINAL_PER_S:,.0f} seeds/s | {p99:.2f} ms ({f['nominal_samples']:.0f}) "
        f"| {f['nominal_max_ms']:.2f} ms "
        f"| {f['nominal_cpu_pct']:.1f} % | {feeder:.1f} % | {f['nominal_rss_mb']:.0f} MB "
        f"({f['nominal_hwm_mb']:.0f} MB) | {f['nominal_stored']:,.0f} / "
        f"{f['nominal_published']:,.0f} |\n\n"
        "CPU at the daemon's default control settings (RS485 polled at 3 Hz, duty rewritten "
        "when it changes or every 1 s, half the PWM watchdog timeout), same feed; "
        f"median of {CPU_RUNS} runs of "
        f"{DAEMON_MEASURE_S:g} s, the synthetic feeder's making of epochs and kernel edge "
        "events left out:\n\n"
        "| daemon, default settings | CPU (% of one core), median | min – max "
        "| feeder (left out) | RSS peak |\n|---|---|---|---|---|\n"
        f"| no seeds | {f['default_idle_cpu_pct']:.1f} % | – | – "
        f"| {f['default_idle_hwm_mb']:.0f} MB |\n"
        f"| {NOMINAL_PER_S:,.0f} seeds/s | {f['default_cpu_pct']:.1f} % "
        f"| {f['default_cpu_min']:.1f} – {f['default_cpu_max']:.1f} % "
        f"| {f['default_feeder_cpu_pct']:.1f} % | {f['default_hwm_mb']:.0f} MB |\n\n"
        f"Targets at nominal load: RSS ≤ {TARGET_RSS_MB:g} MB: "
        f"{ok(max(f['nominal_hwm_mb'], f['default_hwm_mb']) <= TARGET_RSS_MB)}; "
        f"CPU ≤ {TARGET_CPU_PCT:g} % of a core at the default settings: "
        f"{ok(f['default_cpu_pct'] <= TARGET_CPU_PCT)} ({f['default_cpu_pct']:.1f} %; "
        f"{daemon_cpu:.1f} % with 10 Hz polling and a duty write every tick). Not in these "
        "figures: the GNSS reader's parsing of the receiver's sentences (the synthetic epochs "
        "replace it, one wake-up per epoch; a receiver behind a USB adapter may need two or "
        "three) and the kernel's making of the edge events. Control p99 ≤ "
        f"{TARGET_P99_MS:g} ms: "
        f"{ok(p99 <= TARGET_P99_MS)} ({p99 / p99_idle if p99_idle else 0:.2f} × the "
        "no-seed p99).\n"
    )
    return fig


def _main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--daemon", nargs=5,
                        metavar=("CONFIG", "STATE_DIR", "RUN_S", "SEEDS_PER_S", "OUT"))
    args = parser.parse_args(argv)
    if args.daemon:
        config, state_dir, run_s, per_s, out = args.daemon
        result = asyncio.run(_daemon_child(Path(config), Path(state_dir), float(run_s),
                                           float(per_s)))
        Path(out).write_text(json.dumps(result))
    else:
        print(run()["markdown"])


if __name__ == "__main__":
    _main(sys.argv[1:])
