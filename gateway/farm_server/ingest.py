"""``sowgate ingest``'s MQTT side: one member of a shared subscription that validates every
machine's ``seeds``, ``alarms``, ``state`` and ``status``, commits them in batches through
``gateway.farm_server.db`` and publishes each machine's watermark.

Why correctness does not rest on the broker. mosquitto keeps handing a shared subscription's
share to a disconnected persistent member (queued for it, eclipse-mosquitto #1747), and a
clean member's in-flight messages die with it (#2662); paho acknowledges a QoS 1 message on
receipt, before it is committed. So a message can be lost between broker and database. What
makes that harmless is end to end: after each commit ingest publishes, retained, per machine,
``<prefix>/<machine_id>/ingested`` = ``{"committed_through": N, ...}`` computed from the
database's coverage of that machine's ids, and a cab with ``[mqtt] farm_server_ack`` keeps
and re-publishes every record above it (docs/mqtt.md). Members connect clean (MQTT 5
clean start), so the broker never queues a share for a member that is gone.

Hostile input. Every payload is size-capped and validated with the same pydantic models the
cab publishes with (docs/schemas/); the machine id in the payload must be the topic's. A
rejected message is counted per reason, logged at most once per reason per
``REJECT_LOG_INTERVAL_S`` and never stored; nothing in a payload can end the process
(deep nesting, a RecursionError, included).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import re
import socket
import time
from dataclasses import dataclass, field

import aiomqtt
import orjson
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from pydantic import ValidationError

from gateway.config import FarmServerSection, MqttSection
from gateway.core.records import AlarmEvent
from gateway.farm_server.db import Committed, IngestDatabase
from gateway.farm_server.rows import RowEncoder, SeedRows, parse_seed_batch, rows_of_records
from gateway.link.mqtt import mqtt_client
from gateway.link.payloads import SeedBatch, StatePayload

log = logging.getLogger("sowgate.ingest")

KINDS = ("seeds", "alarms", "state", "status")
MACHINE_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
REJECT_LOG_INTERVAL_S = 10.0
GAP_LOG_INTERVAL_S = 30.0
WATERMARK_RANGES = 64  # the newest committed id ranges a watermark lists
RECONNECT_S = 2.0
SUMMARY_INTERVAL_S = 60.0  # an INFO line with the counters and the gaps
# Watermarks are published again from the database: every machine's at each (re)connect (a
# broker restarted without persistence lost them, and a cab whose records are all committed
# sends nothing that would bring a new one), and every this many seconds those of the machines
# that sent seeds meanwhile (two ingest processes publish in any order: the retained one may be
# the older of two, until this puts the database's newest coverage on top again)
WATERMARK_REFRESH_S = 5.0
# ... and every machine's every this many seconds: a retained watermark the broker lost while
# ingest stayed connected (a broker restarted in less than the keepalive, a retained store
# cleared by hand) is put back although no cab sends anything (a few bytes a machine)
WATERMARK_FULL_REFRESH_S = 30.0
# Back-pressure (docs/farm-server.md). Ingest acknowledges a QoS 1 message once its records
# are queued (not on receipt, paho's default), and reads nothing while ``max_queued_rows``
# wait for the database (or are being committed). MQTT 5 Receive Maximum: the broker sends
# at most this many messages ingest has not acknowledged, and keeps the rest. But mosquitto
# 2.0.11 (Debian 12) lets more than the Receive Maximum through once acknowledgements have
# come (measured: 4 PUBACKs let 15 more in past a maximum of 5), so ingest also stops reading
# its socket when UNREAD_MAXIMUM messages are received and not read yet (TCP's flow control
# then holds the broker), and reads it again below UNREAD_RESUME. Nothing is dropped; memory
# is max_queued_rows rows (≈ 0.3 kB each) plus UNREAD_MAXIMUM payloads (and the few more one
# read of the socket may bring: paho reads a packet more for each of its own in flight).
# A socket not read for longer than the keepalive ends the connection: with the database away
# that long, ingest reconnects, and what was in flight is published again by the cabs, as
# after any lost connection.
RECEIVE_MAXIMUM = 32
UNREAD_MAXIMUM = 64
UNREAD_RESUME = 16
PAUSE_LOG_INTERVAL_S = 10.0


class Rejected(Exception):
    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass
class IngestStats:
    messages: int = 0
    seeds_committed: int = 0
    seeds_duplicate: int = 0
    alarms_committed: int = 0
    states_committed: int = 0
    states_thinned: int = 0
    rejected: collections.Counter[str] = field(default_factory=collections.Counter)
    watermarks_published: int = 0
    commit_failures: int = 0
    # back-pressure: times reading stopped at max_queued_rows, seconds stopped in all, and
    # the most rows queued and messages received but not yet read at any moment
    paused: int = 0
    paused_s: float = 0.0
    peak_queued_rows: int = 0
    peak_unread_messages: int = 0
    socket_pauses: int = 0  # times the socket was not read at UNREAD_MAXIMUM messages


def gap_text(machine_id: str, gaps: list[tuple[int, int]]) -> str:
    """``seeder-03: records 18 200–18 340 not received yet`` (ids with thin-space groups)."""
    def n(i: int) -> str:
        return f"{i:,}".replace(",", " ")
    runs = ", ".join(n(lo) if lo == hi else f"{n(lo)}–{n(hi)}" for lo, hi in gaps[:10])
    more = f" and {len(gaps) - 10} more runs" if len(gaps) > 10 else ""
    return f"{machine_id}: records {runs}{more} not received yet"


@dataclass
class _Work:
    """What one flush commits; what is left in it after a failure was not committed."""

    seeds: dict[str, SeedRows]
    alarms: list[AlarmEvent]
    states: list[StatePayload]
    status: dict[str, str]
    done: list[Committed] = field(default_factory=list)


class Ingest:
    def __init__(self, farm: FarmServerSection, mqtt: MqttSection) -> None:
        if farm.database_url is None:
            raise ValueError("farm_server.database_url is required")
        self.farm = farm
        self.mqtt = mqtt
        self.prefix = farm.topic_prefix.rstrip("/")
        self.client_id = farm.client_id or f"sowgate-ingest-{socket.gethostname()}-{os.getpid()}"
        self.stats = IngestStats()
        self.connected = asyncio.Event()
        self.committed: dict[str, Committed] = {}  # the latest coverage seen, per machine
        self._seeds: dict[str, SeedRows] = {}
        self._encoders: dict[str, RowEncoder] = {}
        self._alarms: list[AlarmEvent] = []
        self._states: list[StatePayload] = []
        self._status: dict[str, str] = {}
        self._last_state: dict[str, float] = {}
        self._rows = 0
        self._flush_now = asyncio.Event()
        self._room = asyncio.Event()  # set at the end of every flush
        self._committing = 0  # rows of the flush under way
        self._client: aiomqtt.Client | None = None
        self._pause_logged = -1e9
        self._reject_logged: dict[str, float] = {}
        self._gap_logged: dict[str, float] = {}
        self._failure_logged = -1e9
        self._db: IngestDatabase | None = None
        self._db_lock = asyncio.Lock()
        self._active: set[str] = set()  # machines that sent seeds since the last refresh
        # per machine, the highest ``pending_from`` it sent (no id below it will come again)
        self._pending_from: dict[str, int] = {}

    # -- parsing: pure, every failure is a Rejected -------------------------------------------

    def accept(self, topic: str, payload: bytes) -> None:
        """Validate one message and queue what it carries; rejects are counted and logged."""
        self.stats.messages += 1
        try:
            self._accept(topic, payload)
        except Rejected as exc:
            self._reject(exc.reason, f"{topic[:200]!r}: {exc}")
        except (RecursionError, MemoryError, ValueError, TypeError) as exc:
            self._reject("malformed", f"{topic[:200]!r}: {type(exc).__name__}")

    def _accept(self, topic: str, payload: bytes) -> None:
        parts = topic.split("/")
        base = self.prefix.split("/")
        if parts[: len(base)] != base or len(parts) != len(base) + 2:
            raise Rejected("topic", "not <prefix>/<machine_id>/<kind>")
        machine_id, kind = parts[len(base)], parts[len(base) + 1]
        if kind not in KINDS:
            raise Rejected("topic", f"unknown kind {kind[:40]!r}")
        if not MACHINE_ID.match(machine_id):
            raise Rejected("machine_id", "machine id not [A-Za-z0-9_.-]{1,64}")
        if len(payload) > self.farm.max_payload_bytes:
            raise Rejected("too_large", f"{len(payload)} bytes")
        known = machine_id in self._seeds or machine_id in self.committed
        if not known and len(set(self._seeds) | set(self.committed)) >= self.farm.max_machines:
            raise Rejected("too_many_machines", f"over farm_server.max_machines for {machine_id}")
        if kind == "status":
            text = payload.decode("utf-8", "replace")
            if text not in ("online", "offline"):
                raise Rejected("malformed", "status is neither online nor offline")
            self._status[machine_id] = text
            return
        try:
            if kind == "seeds":
                encoder = self._encoders.get(machine_id)
                if encoder is None:
                    encoder = self._encoders[machine_id] = RowEncoder(machine_id)
                # the cab's own shape, checked and encoded in one pass; anything else is
                # judged by the pydantic models, as every other payload is
                parsed = parse_seed_batch(payload, machine_id, encoder)
                if parsed is not None:
                    rows, min_id, pending_from = parsed.rows, parsed.min_id, parsed.pending_from
                else:
                    batch = SeedBatch.model_validate_json(payload)
                    ids = [r.machine_id for r in batch.records]
                    if batch.machine_id != machine_id or any(i != machine_id for i in ids):
                        raise Rejected("impersonation", "machine_id differs from the topic's")
                    try:
                        rows = rows_of_records(machine_id, batch.records, encoder)
                    except ValueError as exc:
                        raise Rejected("invalid", f"seeds: {exc}") from None
                    min_id = min((r.id for r in batch.records), default=0)
                    pending_from = batch.pending_from
                self._active.add(machine_id)
                if rows:
                    queued = self._seeds.get(machine_id)
                    if queued is None:
                        self._seeds[machine_id] = rows
                    else:
                        queued.extend(rows)
                    if pending_from is not None:  # never above what it sends itself
                        floor = min(pending_from, min_id)
                        if floor > self._pending_from.get(machine_id, 0):
                            self._pending_from[machine_id] = floor
                    self._rows += len(rows)
            elif kind == "alarms":
                event = AlarmEvent.model_validate_json(payload)
                if event.machine_id != machine_id:
                    raise Rejected("impersonation", "machine_id differs from the topic's")
                self._alarms.append(event)
                self._rows += 1
            else:
                state = StatePayload.model_validate_json(payload)
                if state.machine_id != machine_id:
                    raise Rejected("impersonation", "machine_id differs from the topic's")
                now = time.monotonic()
                last = self._last_state.get(machine_id)
                if last is not None and now - last < self.farm.state_sample_s:
                    self.stats.states_thinned += 1
                    return
                self._last_state[machine_id] = now
                self._states.append(state)
                self._rows += 1
        except ValidationError as exc:
            errors = exc.errors(include_url=False)
            where = ".".join(str(p) for p in errors[0]["loc"])[:80] if errors else ""
            what = errors[0]["msg"] if errors else "invalid"
            raise Rejected("invalid", f"{kind}: {where}: {what}"[:300]) from None
        if self._rows >= self.farm.batch_rows:
            self._flush_now.set()
        if self._rows + self._committing > self.stats.peak_queued_rows:
            self.stats.peak_queued_rows = self._rows + self._committing

    def _reject(self, reason: str, detail: str) -> None:
        self.stats.rejected[reason] += 1
        now = time.monotonic()
        if now - self._reject_logged.get(reason, -1e9) >= REJECT_LOG_INTERVAL_S:
            self._reject_logged[reason] = now
            log.warning("ingest rejected a message (%s, %d so far): %s", reason,
                        self.stats.rejected[reason], detail)

    # -- committing ----------------------------------------------------------------------------

    def _commit(self, work: _Work) -> list[Committed]:
        """The blocking part of a flush (runs in a thread): commits ``work``, emptying it as
        it goes, so that what is left after an exception is exactly what was not committed."""
        if self._db is None:
            assert self.farm.database_url is not None
            self._db = IngestDatabase(self.farm.database_url)
        db = self._db
        done = []
        try:
            if work.seeds:
                # every machine of the flush in one transaction: one commit, all or nothing
                done = db.write_seed_rows(work.seeds, self._pending_from)
                work.seeds = {}
                for result in done:
                    self.stats.seeds_committed += result.new_seeds
                    self.stats.seeds_duplicate += result.duplicate_seeds
            self.stats.alarms_committed += db.write_alarms(work.alarms)
            work.alarms = []
            db.write_states(work.states)
            self.stats.states_committed += len(work.states)
            work.states = []
            for machine_id in list(work.status):
                db.write_status(machine_id, work.status.pop(machine_id))
        except BaseException:
            with contextlib.suppress(Exception):
                db.close()
            self._db = None
            work.done = done
            raise
        return done

    async def flush(self, client: aiomqtt.Client | None) -> None:
        """Commit what is queued, then publish the touched machines' watermarks. On a
        database failure what was not committed is queued again for the next flush."""
        async with self._db_lock:
            if not (self._seeds or self._alarms or self._states or self._status):
                return
            work = _Work(self._seeds, self._alarms, self._states, self._status)
            self._seeds, self._alarms, self._states, self._status = {}, [], [], {}
            self._committing, self._rows = self._rows, 0
            try:
                done = await asyncio.to_thread(self._commit, work)
            except BaseException:
                for machine_id, rows in work.seeds.items():
                    self._seeds.setdefault(machine_id, SeedRows()).prepend(rows)
                self._alarms[:0] = work.alarms
                self._states[:0] = work.states
                for machine_id, text in work.status.items():
                    self._status.setdefault(machine_id, text)
                self._rows = (sum(map(len, self._seeds.values())) + len(self._alarms)
                              + len(self._states))
                done = work.done
                for result in done:
                    self.committed[result.machine_id] = result
                raise
            finally:
                self._committing = 0
                self._room.set()
        for result in done:
            self.committed[result.machine_id] = result
            self._log_gaps(result)
        if client is not None and done:
            # every machine's watermark at once, not waiting for PUBACKs (_publish_watermark)
            await asyncio.gather(*(self._publish_watermark(client, r) for r in done))

    def _log_gaps(self, result: Committed) -> None:
        gaps = result.gaps()
        if not gaps:
            return
        now = time.monotonic()
        if now - self._gap_logged.get(result.machine_id, -1e9) >= GAP_LOG_INTERVAL_S:
            self._gap_logged[result.machine_id] = now
            log.warning("%s", gap_text(result.machine_id, gaps))

    def gaps(self) -> dict[str, list[tuple[int, int]]]:
        """Per machine, the runs of ids below its newest committed one not committed yet."""
        return {m: c.gaps() for m, c in self.committed.items() if c.gaps()}

    def watermark_payload(self, result: Committed) -> bytes:
        return orjson.dumps({
            "committed_through": result.through,
            "committed": [list(r) for r in result.coverage[-WATERMARK_RANGES:]],
        })

    def _read_coverage(self, machines: set[str] | None) -> list[Committed]:
        if self._db is None:
            assert self.farm.database_url is not None
            self._db = IngestDatabase(self.farm.database_url)
        try:
            return self._db.coverage_of(machines)
        except BaseException:
            with contextlib.suppress(Exception):
                self._db.close()
            self._db = None
            raise

    async def refresh_watermarks(self, client: aiomqtt.Client | None,
                                 machines: set[str] | None = None) -> None:
        """Publish these machines' watermarks (None: every machine's) from the database's
        coverage; a database away is logged and left for the next time."""
        if machines is not None and not machines:
            return
        async with self._db_lock:
            try:
                known = await asyncio.to_thread(self._read_coverage, machines)
            except Exception as exc:
                log.info("ingest: watermarks not refreshed (%s: %s)", type(exc).__name__,
                         str(exc).strip()[:200])
                return
        for result in known:
            self.committed[result.machine_id] = result
            if client is not None:
                await self._publish_watermark(client, result)

    async def _publish_watermark(self, client: aiomqtt.Client, result: Committed) -> None:
        """QoS 1 and retained, handed to paho without waiting for the PUBACK: ingest may have
        stopped reading its socket (back-pressure), and a flush must not wait on that. The
        broker takes one connection's publishes in order, so a machine's watermarks never
        overtake; a lost one is published again (every WATERMARK_REFRESH_S for the machines that
        sent seeds, every WATERMARK_FULL_REFRESH_S for all, and at connect)."""
        info = client._client.publish(
            f"{self.prefix}/{result.machine_id}/ingested", self.watermark_payload(result),
            qos=1, retain=True)
        if info.rc != 0:
            raise aiomqtt.MqttCodeError(info.rc, "could not publish the watermark")
        self.stats.watermarks_published += 1

    # -- the MQTT session ----------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, subscribe, commit; reconnect for ever. Only CancelledError escapes."""
        while True:
            try:
                await self._session()
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                log.warning("ingest: %s: %s; retrying in %.0f s", type(exc).__name__, exc,
                            RECONNECT_S)
            self.connected.clear()
            await asyncio.sleep(RECONNECT_S)

    async def _wait_for_room(self) -> None:
        """Back-pressure: ``max_queued_rows`` wait for the database. Read nothing more (so
        acknowledge nothing more: the broker keeps the rest, at most ``RECEIVE_MAXIMUM``
        messages in flight to us) until a flush makes room."""
        cap = self.farm.max_queued_rows
        self.stats.paused += 1
        now = time.monotonic()
        if now - self._pause_logged >= PAUSE_LOG_INTERVAL_S:
            self._pause_logged = now
            log.warning("ingest: %d rows wait for the database (farm_server.max_queued_rows "
                        "%d): reading from the broker paused until they are committed (%d "
                        "pauses so far)", self._rows, cap, self.stats.paused)
        self._flush_now.set()
        try:
            while self._rows + self._committing >= cap:
                self._room.clear()
                await self._room.wait()
        finally:
            self.stats.paused_s += time.monotonic() - now

    async def _session(self) -> None:
        properties = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]
        properties.ReceiveMaximum = RECEIVE_MAXIMUM
        ingest = self
        loop = asyncio.get_running_loop()
        paused_fd: list[int] = []  # the socket ingest stopped reading, if it did

        def read_socket() -> None:
            """aiomqtt's own socket reader (``Client._on_socket_open``), registered again
            when ingest reads its socket again."""
            try:
                while True:
                    paho.loop_read()
                    pending = getattr(paho.socket(), "pending", None)
                    if pending is not None and pending() > 0:  # TLS
                        continue
                    break
            except Exception as exc:
                if not client._disconnected.done():
                    client._disconnected.set_exception(exc)

        def pause_socket() -> None:
            sock = paho.socket()
            if paused_fd or sock is None:
                return
            paused_fd.append(sock.fileno())
            loop.remove_reader(paused_fd[0])
            ingest.stats.socket_pauses += 1

        def resume_socket() -> None:
            if paused_fd:
                fd = paused_fd.pop()
                sock = paho.socket()
                if sock is not None and sock.fileno() == fd:
                    loop.add_reader(fd, read_socket)

        class Received(asyncio.Queue[aiomqtt.Message]):
            """aiomqtt's queue of messages received and not read yet: at UNREAD_MAXIMUM the
            socket is not read any more (see UNREAD_MAXIMUM)."""

            def put_nowait(self, item: aiomqtt.Message) -> None:
                super().put_nowait(item)
                stats = ingest.stats
                stats.peak_unread_messages = max(stats.peak_unread_messages, self.qsize())
                if self.qsize() >= UNREAD_MAXIMUM:
                    pause_socket()

        client = mqtt_client(self.mqtt, self.client_id, protocol=aiomqtt.ProtocolVersion.V5,
                             properties=properties, queue_type=Received)
        self._client = client
        # acknowledge a message once its records are queued, not on receipt (paho's default)
        paho = client._client
        paho.manual_ack_set(True)
        async with client:
            for kind in KINDS:
                await client.subscribe(
                    f"$share/{self.farm.share_group}/{self.prefix}/+/{kind}", qos=1)
            await self.refresh_watermarks(client)
            self.connected.set()
            log.info("ingest connected to %s:%s as %s (share group %s)", self.mqtt.host,
                     self.mqtt.port, self.client_id, self.farm.share_group)
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._flush_loop(client), name="ingest-flush")
                async for message in client.messages:
                    if self._rows + self._committing >= self.farm.max_queued_rows:
                        await self._wait_for_room()
                    raw = message.payload
                    payload = raw if isinstance(raw, bytes) else str(raw or "").encode()
                    self.accept(message.topic.value, payload)
                    if message.qos:
                        paho.ack(message.mid, message.qos)
                    if paused_fd and len(client.messages) < UNREAD_RESUME:
                        resume_socket()

    def unread_messages(self) -> int:
        """Messages received from the broker and not read (so not acknowledged) yet."""
        return len(self._client.messages) if self._client is not None else 0

    def summary(self) -> str:
        """One line for the journal: what came, what was committed, rejected, missing."""
        st = self.stats
        rejected = ", ".join(f"{k} {v}" for k, v in sorted(st.rejected.items())) or "none"
        gaps = self.gaps()
        missing = "; ".join(gap_text(m, g) for m, g in sorted(gaps.items())) or "no gaps"
        return (f"ingest: {st.messages} messages, {st.seeds_committed} seeds committed "
                f"({st.seeds_duplicate} repeats dropped), {st.alarms_committed} alarms, "
                f"{st.states_committed} states; rejected: {rejected}; reading paused "
                f"{st.paused} times ({st.paused_s:.0f} s) at max_queued_rows; {missing}")

    async def _flush_loop(self, client: aiomqtt.Client) -> None:
        next_summary = time.monotonic() + SUMMARY_INTERVAL_S
        next_refresh = time.monotonic() + WATERMARK_REFRESH_S
        next_full_refresh = time.monotonic() + WATERMARK_FULL_REFRESH_S
        while True:
            if time.monotonic() >= next_full_refresh:
                next_full_refresh = time.monotonic() + WATERMARK_FULL_REFRESH_S
                next_refresh = time.monotonic() + WATERMARK_REFRESH_S
                self._active = set()
                await self.refresh_watermarks(client)
            if time.monotonic() >= next_refresh:
                next_refresh = time.monotonic() + WATERMARK_REFRESH_S
                active, self._active = self._active, set()
                await self.refresh_watermarks(client, active)
            if time.monotonic() >= next_summary:
                next_summary = time.monotonic() + SUMMARY_INTERVAL_S
                log.info("%s", self.summary())
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.farm.flush_interval_s):
                    await self._flush_now.wait()
            self._flush_now.clear()
            try:
                await self.flush(client)
            except Exception as exc:  # the database is away: keep what is queued, retry
                self.stats.commit_failures += 1
                now = time.monotonic()
                if now - self._failure_logged >= REJECT_LOG_INTERVAL_S:
                    self._failure_logged = now
                    log.warning("ingest: commit failed (%d so far), kept for the next try: "
                                "%s: %s", self.stats.commit_failures, type(exc).__name__,
                                str(exc).strip()[:300])
                await asyncio.sleep(RECONNECT_S)
