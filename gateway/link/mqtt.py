"""The MQTT link to the farm: durable outbox publishing, retained state, remote commands.

Design rules, in order of importance:

* Nothing is lost. Seed records and alarms are published from the record store's outbox and
  marked delivered only when the broker's PUBACK arrives; after a reconnect or a restart the
  outbox is read again from the oldest undelivered record (at-least-once; consumers dedupe by
  ``id``). Several seed batches are in flight at once, so a 4G round trip does not cap the rate.
* The control loop never waits on MQTT. The only entry points the daemon's control loop
  touches are synchronous callbacks that enqueue (alarm listener, ``notify_state_changed``);
  everything that can block on the network runs in this module's own tasks.
* Remote commands go through the same ``CommandSink`` as the HMI. Each gets an ack (carrying
  the result text the cab screen shows, or the reason it was refused); a refused
  command changes nothing. Commands are off unless listed in ``[commands] enabled``. The
  payload is parsed, strictly, by ``gateway.link.command_payloads`` (pure, fuzzed); no payload
  and no failure while executing a command can end the session.
* ``run()`` reconnects forever with capped, jittered backoff and never raises (except
  ``CancelledError``): a broker outage is a normal day on a tractor.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import ssl
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiomqtt
import orjson
from paho.mqtt.properties import Properties

from drivers.backoff import Backoff
from drivers.tasks import raise_if_cancelled
from gateway.config import MqttSection, Settings, TlsSection
from gateway.config.startup import file_problem
from gateway.core.alarms import AlarmBoard
from gateway.core.commands import CommandSink
from gateway.core.errors import CommandError
from gateway.core.records import AlarmEvent
from gateway.link.command_payloads import (
    KNOWN_COMMANDS,
    CommandPayloadError,
    parse_command,
)
from gateway.link.payloads import CommandAck, StatePayload
from gateway.recording.alarm_recorder import AlarmRecorder
from gateway.recording.store import OutboxBatch, RecordStore

log = logging.getLogger(__name__)

DISCONNECT_TIMEOUT_S = 3.0
# State messages are at least this far apart (max 10 msg/s) however often it changes.
STATE_MIN_GAP_S = 0.1
ALARMS_PER_READ = 100
# Alarm events the store could not keep (disk full) wait here to be published live; a bound
# so an alarm flapping on a full disk cannot grow it without end (the oldest go first).
MAX_LIVE_ALARMS = 256
OFFLINE_PUBLISH_TIMEOUT_S = 2.0  # clean shutdown must not hang on a dead link
# On a stop, how long ``drain`` waits for the broker to acknowledge what the last commit added
# (a 0.5 s flush of a 48-row planter is a few batches; a 4G round trip is ~0.1 s). With the
# offline publish and the disconnect it stays well inside systemd's TimeoutStopSec (15 s).
STOP_DRAIN_TIMEOUT_S = 2.0
ERROR_TEXT_MAX_CHARS = 500
# [mqtt] farm_server_ack: the resend wait grows to at most this many times the timeout
MAX_RESEND_BACKOFF = 16
ACK_TEXT_MAX_CHARS = 500  # an OK ack's result message
BACKLOG_ALARM = "mqtt.backlog"
# A session must last this long to reset the reconnect backoff. Otherwise a connection the
# broker drops right after CONNACK (typically: two boxes cloned from one image, same client
# id, taking each other's session over) would retry at the initial delay forever.
STABLE_SESSION_S = 10.0


@dataclass
class LinkStats:
    connects: int = 0
    disconnects: int = 0
    batches_published: int = 0
    seeds_published: int = 0
    alarms_published: int = 0
    states_published: int = 0
    commands_ok: int = 0
    commands_rejected: int = 0
    last_error: str = ""
    farm_server_through: int = 0  # the highest committed_through the farm server published
    farm_server_resends: int = 0  # times records were published again (not confirmed in time)


@dataclass(frozen=True)
class Topics:
    base: str

    @property
    def status(self) -> str:
        return f"{self.base}/status"

    @property
    def state(self) -> str:
        return f"{self.base}/state"

    @property
    def seeds(self) -> str:
        return f"{self.base}/seeds"

    @property
    def alarms(self) -> str:
        return f"{self.base}/alarms"

    @property
    def ingested(self) -> str:
        """The farm server's retained watermark for this machine (``sowgate ingest``)."""
        return f"{self.base}/ingested"

    @property
    def commands(self) -> str:
        return f"{self.base}/cmd/+"

    def ack(self, name: str) -> str:
        return f"{self.base}/cmd/{name}/ack"


class MqttLink:
    def __init__(
        self,
        settings: Settings,
        store: RecordStore,
        commands: CommandSink,
        state: Callable[[], StatePayload | Mapping[str, Any]],
        alarms: AlarmBoard,
        *,
        backoff: Backoff | None = None,
        recorded: AlarmRecorder | None = None,
    ) -> None:
        self.cfg = settings.mqtt
        self.enabled_commands = frozenset(settings.commands.enabled)
        self.max_payload_bytes = settings.commands.max_payload_bytes
        self.machine_id = settings.machine.id
        self.client_id = self.cfg.client_id or f"sowgate-{self.machine_id}"
        self.topics = Topics(f"{self.cfg.topic_prefix.rstrip('/')}/{self.machine_id}")
        self.store = store
        self.commands = commands
        self.state = state
        self.alarms = alarms
        self.backoff = backoff or Backoff(initial_s=0.5, cap_s=self.cfg.reconnect_max_s)
        self.connected = False
        self._connected_at: float | None = None  # when the current session's CONNACK came
        self.stats = LinkStats()
        self.publish_timeout_s = 2.0 * self.cfg.keepalive + 30.0
        self._seeds_wake = asyncio.Event()
        self._draining = False  # a stop is publishing the rest: partial batches go at once
        self._progress = asyncio.Event()  # a PUBACK was taken, or the session ended (drain)
        self._alarms_wake = asyncio.Event()
        self._state_wake = asyncio.Event()
        # alarm events published straight from the AlarmBoard, not from the store's outbox
        self._live_alarms: collections.deque[AlarmEvent] = collections.deque(
            maxlen=MAX_LIVE_ALARMS
        )
        # [mqtt] farm_server_ack: (when PUBACKed, last id) of batches published and not yet
        # covered by the farm server's watermark, oldest first
        self._unconfirmed: collections.deque[tuple[float, int]] = collections.deque()
        # the wait before publishing uncovered records again: doubles after each resend that
        # brought no watermark (a farm server away must not get the whole backlog each
        # minute over 4G), back to farm_server_ack_timeout_s when a watermark covers more
        self.resend_after_s = self.cfg.farm_server_ack_timeout_s
        # The daemon stores its alarms whether MQTT is on or not (its AlarmRecorder); a link
        # built on its own (tests, benchmarks) stores them through one of its own.
        (recorded or AlarmRecorder(alarms, store)).subscribe(self._on_alarm)
        store.add_commit_listener(self._on_commit)
        if store.on_backlog is None:
            store.on_backlog = self._on_backlog

    # -- callbacks: called from the control loop, so they only enqueue ---------------------

    def _on_alarm(self, stored: AlarmEvent) -> None:
        """An alarm event the recorder stored; if the store could not commit it now (id 0),
        publish it live as well.

        The alarm that says the disk is full is exactly the one the store cannot keep: it
        goes out at once with id 0 ("not stored yet"), and again with its id once the store
        has written it (consumers dedupe by id; a live event is a notice, not a record).
        """
        if stored.id == 0:
            self._live_alarms.append(stored)
        self._alarms_wake.set()
        self._state_wake.set()  # the state lists the active alarms

    def _on_commit(self) -> None:
        self._seeds_wake.set()
        if self.store.pending_alarm_count():  # most commits hold seeds only
            self._alarms_wake.set()

    def _on_backlog(self, count: int, over: bool) -> None:
        self.alarms.set(
            BACKLOG_ALARM,
            over,
            f"{count} records waiting for the MQTT broker (alarm above "
            f"{self.store.backlog_alarm_records}); they are kept, nothing is dropped",
        )

    def notify_state_changed(self) -> None:
        """The state may have changed: compare it now, publish it at once if the change is
        one a dashboard must see at once (``StatePayload.same_as``), else at ``state_hz``.

        The daemon calls this after every control tick, which is when the work state changes;
        the link itself adds alarms. Comparing on these notices instead of on a timer of its
        own costs the box no extra wake-ups.
        """
        self._state_wake.set()

    async def drain(self, timeout_s: float = STOP_DRAIN_TIMEOUT_S) -> None:
        """On a stop, after the store's last commit: wait until the broker has acknowledged
        every committed record, at most ``timeout_s`` and only while connected.

        Without it the seeds the recorder stored in its final flush (those still waiting for
        their epoch when the stop came) were committed and then left in the outbox, because
        this link was cancelled right after that commit; the dashboard got them only after
        the next start. What is still unacknowledged when the wait ends stays in the outbox
        and is published after the next start (nothing is lost either way); it is logged.
        """
        if not self.cfg.enabled:
            return
        self._draining = True
        self._seeds_wake.set()
        self._alarms_wake.set()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                while self.connected and self.store.backlog():
                    self._progress.clear()
                    await self._progress.wait()
        left = self.store.backlog()
        if left:
            why = f"timed out after {timeout_s:.1f} s" if self.connected else "not connected"
            log.warning(
                "mqtt: %d records not acknowledged by the broker at stop (%s); they stay in "
                "the store and are published after the next start", left, why,
            )

    # -- connection loop -------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, publish, reconnect; forever. Only ``CancelledError`` escapes."""
        if not self.cfg.enabled:
            log.info("mqtt disabled in config")
            return
        while True:
            self._connected_at = None
            try:
                await self._session()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # every failure means: reconnect later
                self.stats.last_error = _flatten(exc)[:ERROR_TEXT_MAX_CHARS]
                log.warning("mqtt %s:%s: %s", self.cfg.host, self.cfg.port, self.stats.last_error)
            if self._connected_at is not None:
                self.stats.disconnects += 1
                lasted = time.monotonic() - self._connected_at
                if lasted >= STABLE_SESSION_S:
                    self.backoff.reset()
                else:
                    log.warning(
                        "mqtt session dropped %.1f s after connecting; backing off (is another "
                        "client using client id %r?)", lasted, self.client_id,
                    )
            self.connected = False
            await asyncio.sleep(self.backoff.next_delay())

    def _client(self) -> aiomqtt.Client:
        return mqtt_client(
            self.cfg,
            self.client_id,
            will=aiomqtt.Will(self.topics.status, b"offline", qos=1, retain=True),
            max_inflight_messages=self.cfg.max_inflight_batches + 8,
        )

    async def _connect(self, client: aiomqtt.Client) -> None:
        """Enter the client; on cancel or failure make sure no half-open socket survives."""
        enter = asyncio.create_task(client.__aenter__(), name="mqtt-connect")
        try:
            await asyncio.shield(enter)
        except asyncio.CancelledError:
            # The connect runs in an executor thread that cannot be interrupted: let it finish,
            # then close what it opened, then honour the cancel.
            with contextlib.suppress(Exception):
                await asyncio.wait_for(enter, timeout=client.timeout + 1.0)
                # bounded as in _session: a DISCONNECT the broker never answers (a loaded
                # machine, a broker going away) must not hold the cancel up indefinitely
                async with asyncio.timeout(DISCONNECT_TIMEOUT_S):
                    await client.__aexit__(None, None, None)
            _force_close(client)
            raise
        except Exception:
            _force_close(client)
            raise

    async def _session(self) -> None:
        client = self._client()
        await self._connect(client)
        try:
            self.connected = True
            self._connected_at = time.monotonic()
            self.stats.connects += 1
            log.info("mqtt connected to %s:%s as %s", self.cfg.host, self.cfg.port, self.client_id)
            # A stop from here on must leave 'offline': the clean disconnect below discards the
            # will, and the birth may already be retained on the broker before its PUBACK.
            try:
                await client.subscribe(self.topics.commands, qos=1)
                if self.cfg.farm_server_ack:
                    await client.subscribe(self.topics.ingested, qos=1)
                await client.publish(self.topics.status, b"online", qos=1, retain=True)
                async with asyncio.TaskGroup() as tg:
                    tg.create_task(self._commands_loop(client), name="mqtt-commands")
                    tg.create_task(self._seeds_loop(client), name="mqtt-seeds")
                    tg.create_task(self._alarms_loop(client), name="mqtt-alarms")
                    tg.create_task(self._state_loop(client), name="mqtt-state")
            except asyncio.CancelledError:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(
                        client.publish(self.topics.status, b"offline", qos=1, retain=True),
                        OFFLINE_PUBLISH_TIMEOUT_S,
                    )
                raise
        finally:
            self.connected = False
            self._progress.set()
            try:
                # bounded: a disconnect that never completes must not hold up shutdown
                async with asyncio.timeout(DISCONNECT_TIMEOUT_S):
                    await client.__aexit__(None, None, None)
            except Exception:  # the connection is gone either way (TimeoutError included)
                _force_close(client)

    # -- publishers ----------------------------------------------------------------------------

    async def _seeds_loop(self, client: aiomqtt.Client) -> None:
        slots = asyncio.Semaphore(self.cfg.max_inflight_batches)
        cursor = 0  # highest id handed to a publisher in this session
        async with asyncio.TaskGroup() as tg:
            while True:
                await slots.acquire()
                batch = await self._next_seed_batch(cursor)
                cursor = batch.ids[-1]
                tg.create_task(
                    self._publish_batch(client, batch, slots),
                    name=f"mqtt-seed-batch-{batch.ids[0]}",
                )

    async def _next_seed_batch(self, cursor: int) -> OutboxBatch:
        """A full batch at once, or a partial one once its first record waited batch_max_ms."""
        limit = self.cfg.batch_max_records
        deadline: float | None = None
        while True:
            self._seeds_wake.clear()
            cursor = self._rewind(cursor)
            waiting = self.store.count_pending_seeds(after_id=cursor, cap=limit)
            now = time.monotonic()
            if waiting:
                if deadline is None:
                    deadline = now + self.cfg.batch_max_ms / 1000.0
                if waiting >= limit or now >= deadline or self._draining:
                    if self.store.seeds_on_disk(cursor):  # a backlog: SQLite, off the loop
                        batch = await asyncio.to_thread(
                            self.store.pending_seed_batch, limit, cursor
                        )
                    else:  # the in-memory tail: no disk
                        batch = self.store.pending_seed_batch(limit, after_id=cursor)
                    if batch is not None:
                        return batch
            timeout = None if deadline is None else max(0.0, deadline - now)
            if self._unconfirmed:  # wake to look at the farm server's timeout
                timeout = min(timeout if timeout is not None else 1.0, 1.0)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(timeout):
                    await self._seeds_wake.wait()

    async def _publish(
        self, client: aiomqtt.Client, topic: str, payload: bytes, *, retain: bool = False
    ) -> None:
        """``client.publish`` (QoS 1, until PUBACK), then honour a cancel that its inner
        ``wait_for`` may have swallowed on Python 3.11: a publisher loop that went on after one
        kept the session's TaskGroup, and so the daemon's stop, waiting for ever."""
        await client.publish(topic, payload, qos=1, retain=retain, timeout=self.publish_timeout_s)
        raise_if_cancelled()

    async def _publish_batch(
        self, client: aiomqtt.Client, batch: OutboxBatch, slots: asyncio.Semaphore
    ) -> None:
        try:
            await self._publish(client, self.topics.seeds, batch.payload)
            if self.cfg.farm_server_ack:
                # the broker has it; delivered only once the farm server's watermark says it
                # is committed (``_on_watermark``), else published again (``_rewind``)
                self._unconfirmed.append((time.monotonic(), batch.ids[-1]))
                self._seeds_wake.set()  # the batcher now waits with the ack timeout in view
            else:
                # PUBACK received: only now is the batch delivered.
                self.store.mark_seeds_delivered(batch.ids)
            self._progress.set()
            self.stats.batches_published += 1
            self.stats.seeds_published += len(batch.ids)
        finally:
            slots.release()

    def _rewind(self, cursor: int) -> int:
        """``[mqtt] farm_server_ack``: the cursor to publish from. Back to the oldest record
        the watermark does not cover once a batch holding it was published more than
        ``farm_server_ack_timeout_s`` ago: the broker or the farm server lost it."""
        if not self._unconfirmed:
            return cursor
        oldest = self.store.oldest_pending_seed_id()
        while self._unconfirmed and (oldest is None or self._unconfirmed[0][1] < oldest):
            self._unconfirmed.popleft()  # covered by the watermark meanwhile
        if not self._unconfirmed or oldest is None:
            return cursor
        waited = self.resend_after_s
        if time.monotonic() - self._unconfirmed[0][0] < waited:
            return cursor
        self._unconfirmed.clear()
        self.stats.farm_server_resends += 1
        self.resend_after_s = min(
            waited * 2, self.cfg.farm_server_ack_timeout_s * MAX_RESEND_BACKOFF
        )
        log.warning("mqtt: the farm server has not confirmed seed records from id %d after "
                    "%.0f s; publishing them again", oldest, waited)
        return min(cursor, oldest - 1)

    def on_watermark(self, payload: bytes) -> None:
        """The farm server's retained ``ingested``: ``{"committed_through": N, "committed":
        [[lo, hi], ...]}``. Those ids are delivered; anything malformed is ignored (logged)."""
        try:
            data = orjson.loads(payload)
            through = data["committed_through"]
            ranges = data.get("committed", [])
            if not isinstance(through, int) or isinstance(through, bool) or through < 0:
                raise ValueError("committed_through is not a non-negative integer")
            spans = [(1, through)] if through >= 1 else []
            for item in ranges if isinstance(ranges, list) else []:
                lo, hi = item
                if isinstance(lo, int) and isinstance(hi, int) and 1 <= lo <= hi:
                    spans.append((lo, hi))
        except (ValueError, TypeError, KeyError, AttributeError, RecursionError) as exc:
            log.warning("mqtt: ignored a malformed farm server watermark on %s: %s",
                        self.topics.ingested, exc)
            return
        if self.store.mark_seed_ranges_delivered(spans):
            self.resend_after_s = self.cfg.farm_server_ack_timeout_s
            self._progress.set()
            self._seeds_wake.set()
        self.stats.farm_server_through = max(self.stats.farm_server_through, through)

    async def _alarms_loop(self, client: aiomqtt.Client) -> None:
        cursor = 0
        while True:
            self._alarms_wake.clear()
            while self._live_alarms:  # first: they are about now, and the store lacks them
                await self._publish(
                    client, self.topics.alarms, self._live_alarms[0].model_dump_json().encode()
                )
                self._live_alarms.popleft()
                self.stats.alarms_published += 1
            events = (  # read from SQLite: off the loop (a stalled card must not hold it)
                await asyncio.to_thread(self.store.pending_alarms, ALARMS_PER_READ, cursor)
                if self.store.pending_alarm_count() else []
            )
            for event in events:  # one at a time: alarms are rare and order matters to readers
                await self._publish(client, self.topics.alarms, event.model_dump_json().encode())
                self.store.mark_alarms_delivered([event.id])
                self._progress.set()
                self.stats.alarms_published += 1
                cursor = event.id
            if not events:
                await self._alarms_wake.wait()

    def _snapshot(self) -> StatePayload | None:
        try:
            value = self.state()
            if isinstance(value, StatePayload):
                return value
            return StatePayload.model_validate(value)
        except Exception:  # a bad snapshot must not take the link down
            log.exception("state snapshot failed")
            return None

    async def _state_loop(self, client: aiomqtt.Client) -> None:
        """Publish at ``state_hz``, and at once when the work state, crop, target rate or
        alarms change (``notify_state_changed``, ``StatePayload.same_as``)."""
        period = 1.0 / self.cfg.state_hz
        last: StatePayload | None = None
        last_at = -float("inf")
        while True:
            self._state_wake.clear()
            snap = self._snapshot()
            now = time.monotonic()
            changed = snap is not None and not snap.same_as(last)
            if snap is not None and (changed or now - last_at >= period):
                if changed and now - last_at < STATE_MIN_GAP_S:
                    await asyncio.sleep(STATE_MIN_GAP_S - (now - last_at))
                    continue  # and look again: it may have changed once more meanwhile
                await self._publish(
                    client, self.topics.state, snap.model_dump_json().encode(), retain=True
                )
                self.stats.states_published += 1
                last, last_at = snap, now
            # until the next period is due; a failing snapshot is retried every min gap
            due = last_at + period - time.monotonic()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(max(STATE_MIN_GAP_S if snap is None else 0.0, due)):
                    await self._state_wake.wait()

    # -- commands ------------------------------------------------------------------------------

    async def _commands_loop(self, client: aiomqtt.Client) -> None:
        prefix = self.topics.base + "/cmd/"
        async for message in client.messages:
            topic = message.topic.value
            if topic == self.topics.ingested:
                raw = message.payload
                self.on_watermark(raw if isinstance(raw, bytes) else str(raw or "").encode())
                continue
            if not topic.startswith(prefix):
                continue
            name = topic[len(prefix) :]
            raw = message.payload
            payload = raw if isinstance(raw, bytes) else str(raw or "").encode()
            ack = self.handle_command(name, payload, retained=message.retain)
            try:
                await client.publish(
                    self.topics.ack(name), ack.to_json(), qos=1, timeout=self.publish_timeout_s
                )
            except ValueError as exc:
                # paho refuses the ack topic itself: a name so long that "/ack" takes the
                # topic past MQTT's 65535 bytes. Nowhere to answer; the link is fine.
                log.warning("mqtt command %s: no ack sent: %s", _quote_name(name), exc)
            raise_if_cancelled()  # see _publish

    def handle_command(self, name: str, payload: bytes, *, retained: bool = False) -> CommandAck:
        """Validate and execute one command; every outcome is an ack, nothing raises.

        A refused command is logged as a warning. Any other exception (a bug in the gateway,
        whether in parsing or in executing) is logged once with its traceback and acked as
        an internal error: it must not escape into the session loop, which would drop the
        link to the farm and let one bad message keep it down.
        """
        try:
            ack = self._evaluate(name, payload, retained)
        except Exception as exc:
            failure = exc.failure if isinstance(exc, _ExecutionFailed) else exc
            request_id = exc.request_id if isinstance(exc, _ExecutionFailed) else None
            log.error("mqtt command %s failed in the gateway", _quote_name(name), exc_info=failure)
            self.stats.commands_rejected += 1
            return CommandAck(
                ok=False,
                error=f"internal error: {_exception_text(failure)}"[:ERROR_TEXT_MAX_CHARS],
                request_id=request_id,
            )
        if ack.ok:
            self.stats.commands_ok += 1
        else:
            self.stats.commands_rejected += 1
            log.warning("mqtt command %s refused: %s", _quote_name(name), ack.error)
        return ack

    def _evaluate(self, name: str, payload: bytes, retained: bool) -> CommandAck:
        if name in KNOWN_COMMANDS:  # an unknown name is refused by parse_command, by name
            if name not in self.enabled_commands:
                return CommandAck(
                    ok=False,
                    error=f"command {name!r} is disabled; enable it in [commands] enabled",
                )
            if retained:
                return CommandAck(
                    ok=False,
                    error="retained command ignored: a retained command would replay "
                    "on every reconnect; publish commands with retain=false",
                )
        try:
            parsed = parse_command(name, payload, max_payload_bytes=self.max_payload_bytes)
        except CommandPayloadError as exc:
            return CommandAck(
                ok=False, error=str(exc)[:ERROR_TEXT_MAX_CHARS], request_id=exc.request_id
            )
        try:
            reply = self.commands.execute(parsed.command, "mqtt")
        except CommandError as exc:
            return CommandAck(
                ok=False, error=str(exc)[:ERROR_TEXT_MAX_CHARS], request_id=parsed.request_id
            )
        except Exception as exc:
            raise _ExecutionFailed(exc, parsed.request_id) from exc
        # the result text the cab screen shows (a calibration's factor, ...): the remote
        # operator's only view of it; capped like errors so one ack stays one small message
        message = reply.strip()[:ACK_TEXT_MAX_CHARS] or None
        return CommandAck(ok=True, message=message, request_id=parsed.request_id)


class _ExecutionFailed(Exception):
    """A command's execution raised ``failure``, something other than ``CommandError``."""

    def __init__(self, failure: Exception, request_id: str | None) -> None:
        super().__init__(failure, request_id)
        self.failure = failure
        self.request_id = request_id


def _quote_name(name: str) -> str:
    """A command name from a topic, for the log: a 64 KB topic is not a 64 KB log line."""
    return repr(name if len(name) <= 40 else name[:40] + "…")


def _exception_text(exc: BaseException) -> str:
    try:
        text = str(exc)
    except Exception:  # a broken __str__ must not turn the ack into a second failure
        text = ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _flatten(exc: BaseException) -> str:
    if isinstance(exc, BaseExceptionGroup):
        return "; ".join(_flatten(e) for e in exc.exceptions)
    return f"{type(exc).__name__}: {exc}"


def _force_close(client: aiomqtt.Client) -> None:
    """Close paho's socket if aiomqtt left it open (connect timed out, cancelled mid-connect)."""
    paho = getattr(client, "_client", None)
    reset = getattr(paho, "_reset_sockets", None)
    if callable(reset):
        with contextlib.suppress(Exception):
            reset()


def mqtt_client(
    cfg: MqttSection,
    client_id: str,
    *,
    will: aiomqtt.Will | None = None,
    clean_session: bool | None = None,
    max_inflight_messages: int | None = None,
    protocol: aiomqtt.ProtocolVersion | None = None,
    properties: Properties | None = None,
    queue_type: type[asyncio.Queue[aiomqtt.Message]] | None = None,
) -> aiomqtt.Client:
    """An aiomqtt client for the ``[mqtt]`` section (host, port, user, password file, TLS,
    keepalive). The daemon and the dashboard both connect with it, so a broker that takes one
    takes the other; each adds only what differs (client id, will, persistent session).
    Reads the password file and TLS files now: a missing one raises ``OSError`` naming the key."""
    password = cfg.password
    if cfg.password_file:
        password = _read_named("mqtt.password_file", cfg.password_file).strip()
    tls_context = None
    tls_insecure = None
    if cfg.tls is not None:
        tls_context = _tls_context(cfg.tls)
        tls_insecure = cfg.tls.insecure
    return aiomqtt.Client(
        cfg.host,
        cfg.port,
        identifier=client_id,
        username=cfg.username,
        password=password if cfg.username else None,
        will=will,
        clean_session=clean_session,
        keepalive=cfg.keepalive,
        timeout=max(10.0, float(cfg.keepalive)),
        max_inflight_messages=max_inflight_messages,
        tls_context=tls_context,
        tls_insecure=tls_insecure,
        protocol=protocol,
        properties=properties,
        queue_type=queue_type,
    )


def _read_named(key: str, path: str) -> str:
    """The text of a file the config names; an error says which key and which path, because
    a bare ``[Errno 2] No such file or directory`` retried for ever tells a fitter nothing."""
    problem = file_problem(path)
    if problem is not None:
        raise OSError(f"{key} {path}: {problem}")
    try:
        return Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise OSError(f"{key} {path}: {exc}") from exc


def _tls_context(tls: TlsSection) -> ssl.SSLContext:
    """The client's TLS context, as paho's ``tls_set`` would build it (server certificate and
    host name verified; the system CAs unless ``ca_file``), but with every file checked first
    so that a missing or unreadable one is named by key and path in the error."""
    files = [("mqtt.tls.ca_file", tls.ca_file), ("mqtt.tls.cert_file", tls.cert_file),
             ("mqtt.tls.key_file", tls.key_file)]
    for key, path in files:
        problem = None if path is None else file_problem(path)
        if problem is not None:
            raise OSError(f"{key} {path}: {problem}")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.verify_mode = ssl.CERT_REQUIRED
    if tls.cert_file is not None:
        try:
            context.load_cert_chain(tls.cert_file, tls.key_file)
        except (OSError, ValueError) as exc:
            keys = f"mqtt.tls.cert_file {tls.cert_file}" + (
                f" / mqtt.tls.key_file {tls.key_file}" if tls.key_file else ""
            )
            raise OSError(f"{keys}: {exc}") from exc
    try:
        if tls.ca_file is not None:
            context.load_verify_locations(tls.ca_file)
        else:
            context.load_default_certs()
    except (OSError, ValueError) as exc:
        raise OSError(f"mqtt.tls.ca_file {tls.ca_file}: {exc}") from exc
    return context
