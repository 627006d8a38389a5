"""The MQTT link against a real mosquitto: no record lost, retained status/state, commands acked."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import aiomqtt
import pytest

from drivers.tasks import cancel_all
from gateway.config import Settings, parse_config
from gateway.core.alarms import AlarmBoard
from gateway.core.commands import Command, SetRate, Start
from gateway.core.errors import CommandError
from gateway.core.records import SeedDrop
from gateway.link.mqtt import MqttLink
from gateway.link.payloads import StatePayload
from gateway.recording.store import RecordStore
from tests.helpers import eventually
from tests.mosquitto import Mosquitto, subscriber

MACHINE = "seeder-t"
BASE = f"sowgate/{MACHINE}"
REPO = Path(__file__).resolve().parents[3]
T0 = datetime(2026, 4, 20, 8, 0, tzinfo=UTC)


def make_settings(
    port: int, enabled: list[str] | None = None, max_payload_bytes: int = 256
) -> Settings:
    return parse_config({
        "machine": {"id": MACHINE},
        "mqtt": {
            "enabled": True, "host": "127.0.0.1", "port": port, "keepalive": 5,
            "reconnect_max_s": 0.5, "batch_max_records": 200, "batch_max_ms": 100,
            "max_inflight_batches": 4, "state_hz": 2,
        },
        "commands": {"enabled": enabled or [], "max_payload_bytes": max_payload_bytes},
    })


def drops(n: int) -> list[SeedDrop]:
    return [
        SeedDrop(row=1 + i % 6, utc=T0 + timedelta(milliseconds=i), lat=52.0, lon=13.0,
                 fix="rtk_fixed", speed_kmh=8.0)
        for i in range(n)
    ]


CROP_RANGES = {"wheat": (50.0, 400.0), "maize": (10.0, 60.0)}


class StubController:
    """A CommandSink that validates like the HMI path: known crop, rate within its range."""

    def __init__(self) -> None:
        self.executed: list[Command] = []

    def execute(self, command: Command, source: str) -> str:
        assert source == "mqtt"
        if isinstance(command, SetRate):
            if command.crop not in CROP_RANGES:
                raise CommandError(f"unknown crop {command.crop!r}")
            lo, hi = CROP_RANGES[command.crop]
            if not lo <= command.rate_kg_ha <= hi:
                raise CommandError(
                    f"rate {command.rate_kg_ha:g} kg/ha outside {lo:g}–{hi:g} for {command.crop}"
                )
        self.executed.append(command)
        if isinstance(command, SetRate):
            return f"{command.crop} {command.rate_kg_ha:g} kg/ha"
        return ""  # a command with no result text: its ack is a bare {"ok": true}


def state_now() -> StatePayload:
    return StatePayload(machine_id=MACHINE, utc=datetime.now(UTC), work_state="working",
                        speed_kmh=8.0, speed_source="radar", area_ha=1.5, seed_mass_kg=300.0)


@dataclass
class Running:
    link: MqttLink
    store: RecordStore
    alarms: AlarmBoard
    sink: StubController


LINK_STOP_S = 30.0  # cancel to stopped, on a loaded machine


@contextlib.asynccontextmanager
async def running_link(
    settings: Settings, db: Path, state: Callable[[], StatePayload] = state_now
) -> AsyncIterator[Running]:
    store = RecordStore(db, MACHINE, commit_interval_s=0.05, backlog_alarm_records=100_000)
    alarms = AlarmBoard(MACHINE)
    sink = StubController()
    link = MqttLink(settings, store, sink, state, alarms)
    store_task = asyncio.create_task(store.run(), name="test-store")
    link_task = asyncio.create_task(link.run(), name="test-link")
    try:
        yield Running(link, store, alarms, sink)
    finally:
        # stopped as the daemon stops it (drivers.tasks.cancel_all: cancelled again while it
        # survives, since a 3.11 wait_for can swallow one cancel); bounded, and said: a link
        # that does not stop is a bug to see by name, not a pytest-timeout with tasks leaked
        pending = await cancel_all([link_task], timeout_s=LINK_STOP_S)
        store_task.cancel()
        await asyncio.gather(store_task, return_exceptions=True)
        store.close()
        assert not pending, f"the link still runs {LINK_STOP_S:g} s after its cancel"



async def send(port: int, topic: str, payload: bytes, retain: bool = False) -> None:
    async with aiomqtt.Client("127.0.0.1", port, identifier="operator") as client:
        await client.publish(topic, payload, qos=1, retain=retain)


async def test_records_alarms_state_and_status_reach_the_broker(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """Birth, retained state, every seed id once, one alarm message per event, offline at stop."""
    async with subscriber(mosquitto.port, BASE) as sub:
        async with running_link(make_settings(mosquitto.port), tmp_path / "r.db") as run:
            run.store.add_seeds(drops(1000))
            run.alarms.raise_("radar.lost", "radar not answering", "critical")
            run.alarms.clear("radar.lost")
            await eventually(lambda: len(sub.seed_ids()) >= 1000, what="1000 seed ids")
            await eventually(lambda: len(sub.on("alarms")) == 2, what="2 alarms")
            await eventually(lambda: run.store.backlog() == 0, what="outbox drained")
            assert sorted(set(sub.seed_ids())) == list(range(1, 1001))
            assert all(len(json.loads(p)["records"]) <= 200 for p in sub.on("seeds"))
            assert sub.on("status")[0] == b"online"
            state = json.loads(sub.on("state")[-1])
            assert state["work_state"] == "working" and state["area_ha"] == 1.5
            raised, cleared = (json.loads(p) for p in sub.on("alarms"))
            assert (raised["code"], raised["active"], cleared["active"]) == (
                "radar.lost", True, False)
            assert raised["id"] < cleared["id"]
            assert run.link.connected and run.link.stats.seeds_published >= 1000
        await eventually(lambda: sub.on("status")[-1] == b"offline", 5, "offline on shutdown")
    retained = [r for t, _, r in sub.messages if t == f"{BASE}/status"]
    assert retained  # status is retained on the broker


async def test_state_goes_out_at_state_hz_and_at_once_on_a_work_state_change(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """The daemon says after each control tick that the state may have changed. Steady seeding
    changes speed and duty on every tick: that is published at state_hz, not per tick (it was
    86 messages in 29 s at 1 Hz). A work-state change goes out at once, and a burst of them is
    capped at 10 messages/s."""
    settings = parse_config({
        "machine": {"id": MACHINE},
        "mqtt": {"enabled": True, "port": mosquitto.port, "keepalive": 5, "state_hz": 1},
    })
    now = {"speed": 8.0, "work_state": "seeding"}

    def state() -> StatePayload:
        return StatePayload(machine_id=MACHINE, utc=datetime.now(UTC),
                            work_state=str(now["work_state"]), speed_kmh=float(now["speed"]),
                            motor_duty_pct=float(now["speed"]) * 5.1, speed_source="radar")

    def states() -> list[dict[str, object]]:
        return [json.loads(p) for p in sub.on("state")]

    async with (
        subscriber(mosquitto.port, BASE) as sub,
        running_link(settings, tmp_path / "r.db", state) as run,
    ):
        await eventually(lambda: len(states()) == 1, 5, "the first state")
        started = time.monotonic()
        while time.monotonic() - started < 3.0:  # 3 s of seeding, a control tick every 0.1 s
            now["speed"] = 8.0 + 0.1 * (time.monotonic() % 1.0)  # jitters on every tick
            run.link.notify_state_changed()
            await asyncio.sleep(0.1)
        periodic = len(states()) - 1
        assert 2 <= periodic <= 4  # ~1 per second, not ~30
        assert all(isinstance(s["speed_kmh"], float) and round(s["speed_kmh"], 2) == s["speed_kmh"]
                   for s in states())

        now["work_state"] = "turning"
        run.link.notify_state_changed()
        await eventually(lambda: states()[-1]["work_state"] == "turning", 0.5,
                         "the work-state change, well before the next period")
        before = len(states())
        for i in range(20):  # a work state flapping on every 10 ms tick
            now["work_state"] = "seeding" if i % 2 else "paused"
            run.link.notify_state_changed()
            await asyncio.sleep(0.01)
        await eventually(lambda: states()[-1]["work_state"] == now["work_state"], 1.0,
                         "the final work state")
        assert 1 <= len(states()) - before <= 5  # ~0.3 s of changes at <= 10 messages/s


async def test_an_alarm_publishes_the_state_at_once(mosquitto: Mosquitto, tmp_path: Path) -> None:
    settings = parse_config({
        "machine": {"id": MACHINE},
        "mqtt": {"enabled": True, "port": mosquitto.port, "keepalive": 5, "state_hz": 0.2},
    })
    board: list[AlarmBoard] = []

    def state() -> StatePayload:
        from gateway.link.payloads import ActiveAlarmInfo

        active = board[0].active if board else []
        return StatePayload(
            machine_id=MACHINE, utc=datetime.now(UTC), work_state="seeding",
            alarms=[ActiveAlarmInfo(code=a.code, severity=a.severity, message=a.message,
                                    since=a.since) for a in active],
        )

    async with (
        subscriber(mosquitto.port, BASE) as sub,
        running_link(settings, tmp_path / "r.db", state) as run,
    ):
        board.append(run.alarms)
        await eventually(lambda: len(sub.on("state")) == 1, 5, "the first state")
        run.alarms.raise_("speed.lost", "no valid ground speed", "critical")
        def codes() -> list[str]:
            return [a["code"] for a in json.loads(sub.on("state")[-1])["alarms"]]

        await eventually(lambda: codes() == ["speed.lost"], 1.0,
                         "the alarm in the state, long before the 5 s period")


async def test_bad_commands_get_precise_error_acks_and_change_nothing(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    settings = make_settings(mosquitto.port, enabled=["rate", "start", "zero_tilt"])
    cases: list[tuple[str, bytes, str | None]] = [
        ("rate", b'{"crop": "wheat", "rate_kg_ha": 225.0, "request_id": "r1"}', None),
        ("rate", b'{"crop": "wheat", "rate_kg_ha": "lots"}', "rate_kg_ha"),
        # strict: no lax coercion of a string or a boolean into a number, no NaN
        ("rate", b'{"crop": "wheat", "rate_kg_ha": "200"}',
         "rate_kg_ha: must be a number (got string '200')"),
        ("rate", b'{"crop": "wheat", "rate_kg_ha": true}',
         "rate_kg_ha: must be a number (got true)"),
        ("rate", b'{"crop": "wheat", "rate_kg_ha": NaN}',
         "rate_kg_ha: must be a finite number (got NaN)"),
        ("rate", b'{"crop": 7, "rate_kg_ha": 100}', "crop: must be a string (got number 7)"),
        ("rate", b'{"crop": "wheat", "rate_kg_ha": 900}', "outside 50–400"),
        ("rate", b'{"crop": "barley", "rate_kg_ha": 100}', "unknown crop"),
        ("rate", b'{"crop": "wheat"}', "rate_kg_ha: required field is missing"),
        ("rate", b"[1, 2]", "payload must be a JSON object, got array"),
        ("rate", b"not json", "not valid JSON"),
        ("rate", b'{"crop": "' + b"w" * 300 + b'", "rate_kg_ha": 1}', "too large"),
        ("fly", b"{}", "unknown command 'fly'"),
        ("stop", b"{}", "disabled"),
        ("start", b'{"force": true}', "force: unknown field (allowed: request_id)"),
        ("start", b"", None),
    ]
    # A stale retained command would replay on every reconnect: it must be refused.
    await send(mosquitto.port, f"{BASE}/cmd/zero_tilt", b"{}", retain=True)
    async with (
        subscriber(mosquitto.port, BASE) as sub,
        running_link(settings, tmp_path / "r.db") as run,
    ):
        await eventually(lambda: run.link.connected, what="link connected")
        await eventually(lambda: bool(sub.on("cmd/zero_tilt/ack")), what="retained refused")
        await eventually(lambda: bool(sub.on("status")), what="birth")
        for name, payload, expected_error in cases:
            before = len(sub.on(f"cmd/{name}/ack"))
            await send(mosquitto.port, f"{BASE}/cmd/{name}", payload)
            await eventually(lambda n=name, b=before: len(sub.on(f"cmd/{n}/ack")) > b,
                             what=f"ack for {name} {payload[:40]!r}")
            ack = json.loads(sub.on(f"cmd/{name}/ack")[-1])
            if expected_error is None:
                assert ack["ok"] is True, ack
            else:
                assert ack["ok"] is False and expected_error in ack["error"], ack
        # an OK ack carries the command's result text, and omits it when there is none
        assert json.loads(sub.on("cmd/rate/ack")[0]) == {
            "ok": True, "message": "wheat 225 kg/ha", "request_id": "r1"}
        assert json.loads(sub.on("cmd/start/ack")[-1]) == {"ok": True}
        # the retained command left on the broker before the link came up is not executed
        assert "retained" in json.loads(sub.on("cmd/zero_tilt/ack")[0])["error"]
        assert run.sink.executed == [SetRate("wheat", 225.0), Start()]
        assert run.link.stats.commands_ok == 2


async def test_a_deeply_nested_payload_gets_an_error_ack_and_the_session_stays_up(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """``[`` x 2000 (2 KB, under the size cap) used to raise RecursionError in the JSON parser,
    which took the MQTT session down: anyone allowed to publish on cmd/ could keep the link
    down. Now it is one refused command, on a known and on an unknown topic alike."""
    settings = make_settings(mosquitto.port, enabled=["rate", "start"], max_payload_bytes=4096)
    hostile = b"[" * 2000
    async with (
        subscriber(mosquitto.port, BASE) as sub,
        running_link(settings, tmp_path / "r.db") as run,
    ):
        await eventually(lambda: sub.on("status") == [b"online"], what="birth")
        for name, expected_error in [
            ("rate", "nested more than"),
            ("start", "nested more than"),
            ("whatever", "unknown command 'whatever'"),
        ]:
            await send(mosquitto.port, f"{BASE}/cmd/{name}", hostile)
            await eventually(lambda n=name: bool(sub.on(f"cmd/{n}/ack")), what=f"{name} ack")
            ack = json.loads(sub.on(f"cmd/{name}/ack")[0])
            assert ack["ok"] is False and expected_error in ack["error"], ack
        # the link still works: a good command afterwards is executed and acked
        await send(mosquitto.port, f"{BASE}/cmd/rate", b'{"crop": "wheat", "rate_kg_ha": 200}')
        await eventually(lambda: len(sub.on("cmd/rate/ack")) == 2, what="second rate ack")
        assert json.loads(sub.on("cmd/rate/ack")[1])["ok"] is True
        assert run.sink.executed == [SetRate("wheat", 200.0)]
        # ... and it is the same session: no reconnect, no second birth
        assert (run.link.stats.connects, run.link.stats.disconnects) == (1, 0)
        assert run.link.stats.last_error == ""
        assert sub.on("status") == [b"online"]


async def test_hostile_commands_over_the_broker_never_restart_the_session(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """A handful of the worst payloads and topics, through a real broker: each one is a
    refused command with an ack that says why, and the session they arrive on survives."""
    settings = make_settings(mosquitto.port, enabled=["rate", "start", "speed_cal"],
                             max_payload_bytes=65536)
    # a topic of exactly MQTT's 65535 bytes: "/ack" makes the ack topic too long to publish
    longest_name = "n" * (65535 - len(f"{BASE}/cmd/"))
    hostile: list[tuple[str, bytes, str]] = [
        ("rate", b"[" * 2000, "nested more than"),
        ("rate", b'{"a": ' * 5000, "nested more than"),
        ("rate", b'{"crop": "w", "rate_kg_ha": ' + b"9" * 5000 + b"}", "number out of range"),
        ("rate", b'{"crop": "w", "rate_kg_ha": ' + b"9" * 400 + b"}", "integer too large"),
        ("rate", b'{"crop": "w", "rate_kg_ha": -Infinity}', "must be a finite number"),
        ("rate", b'{"crop": "w", "rate_kg_ha": "200"}', "must be a number (got string '200')"),
        ("rate", b"\xff\xfe\x00\x00", "not UTF-8"),
        ("rate", json.dumps({f"k{i}": [i] for i in range(3000)}).encode(),
         "unknown fields k0, k1, k2, k3, k4 and 2995 more"),
        ("speed_cal", b'{"action": {"action": "start"}}', "action: must be 'start'"),
        ("start", b"[" * 60_000, "nested more than"),
        ("", b"{}", "unknown command ''"),
        ("r\u00e4te", b"{}", "unknown command 'r\u00e4te'"),
        ("x" * 5000, b"[" * 2000, "unknown command 'xxxx"),
    ]
    async with (
        subscriber(mosquitto.port, BASE) as sub,
        running_link(settings, tmp_path / "r.db") as run,
    ):
        await eventually(lambda: sub.on("status") == [b"online"], what="birth")
        for name, payload, expected_error in hostile:
            before = len(sub.on(f"cmd/{name}/ack"))
            await send(mosquitto.port, f"{BASE}/cmd/{name}", payload)
            await eventually(lambda n=name, b=before: len(sub.on(f"cmd/{n}/ack")) > b,
                             what=f"ack for {name[:20]!r} {payload[:20]!r}")
            ack = json.loads(sub.on(f"cmd/{name}/ack")[-1])
            assert ack["ok"] is False and expected_error in ack["error"], ack
            assert len(ack["error"]) <= 500
        rejected = run.link.stats.commands_rejected
        await send(mosquitto.port, f"{BASE}/cmd/{longest_name}", b"[" * 2000)
        await eventually(lambda: run.link.stats.commands_rejected > rejected, what="refusal")
        # the session is the first one, and it still executes a good command
        await send(mosquitto.port, f"{BASE}/cmd/rate", b'{"crop": "wheat", "rate_kg_ha": 200}')
        await eventually(lambda: json.loads(sub.on("cmd/rate/ack")[-1])["ok"] is True,
                         what="a good command afterwards")
        assert run.sink.executed == [SetRate("wheat", 200.0)]
        assert (run.link.stats.connects, run.link.stats.disconnects) == (1, 0)
        assert sub.on("status") == [b"online"]


async def test_a_command_that_fails_inside_the_gateway_is_an_error_ack_logged_once(
    mosquitto: Mosquitto, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Not a refusal (CommandError) but a bug: any exception while executing a command is
    acked as an internal error, logged once with its traceback, and the session goes on."""

    class FailingController:
        def execute(self, command: Command, source: str) -> str:
            if isinstance(command, Start):
                raise RecursionError("maximum recursion depth exceeded")
            raise ZeroDivisionError("float division by zero")

    settings = make_settings(mosquitto.port, enabled=["rate", "start"])
    async with (
        subscriber(mosquitto.port, BASE) as sub,
        running_link(settings, tmp_path / "r.db") as run,
    ):
        run.link.commands = FailingController()
        await eventually(lambda: sub.on("status") == [b"online"], what="birth")
        await send(mosquitto.port, f"{BASE}/cmd/rate",
                   b'{"crop": "wheat", "rate_kg_ha": 200, "request_id": "r9"}')
        await send(mosquitto.port, f"{BASE}/cmd/start", b"")
        await eventually(lambda: bool(sub.on("cmd/rate/ack") and sub.on("cmd/start/ack")),
                         what="both acks")
        assert json.loads(sub.on("cmd/rate/ack")[0]) == {
            "ok": False, "error": "internal error: ZeroDivisionError: float division by zero",
            "request_id": "r9"}
        assert json.loads(sub.on("cmd/start/ack")[0])["error"] == (
            "internal error: RecursionError: maximum recursion depth exceeded")
        assert (run.link.stats.connects, run.link.stats.disconnects) == (1, 0)
        assert run.link.stats.commands_rejected == 2
    command_logs = [r for r in caplog.records if "mqtt command" in r.getMessage()]
    assert [(r.levelname, r.exc_info is not None) for r in command_logs] == [
        ("ERROR", True), ("ERROR", True)]


async def test_broker_restart_mid_stream_loses_no_record(
    persistent_mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """Broker down 3 s while seeds keep coming: afterwards every id arrived (dedup by id)."""
    broker = persistent_mosquitto
    async with subscriber(broker.port, BASE) as sub, \
            running_link(make_settings(broker.port), tmp_path / "r.db") as run:
        added = 0

        async def feed(seconds: float) -> None:
            nonlocal added
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                added += len(run.store.add_seeds(drops(20)))
                await asyncio.sleep(0.02)

        await eventually(lambda: run.link.connected, what="connected")
        await feed(0.6)
        broker.stop()
        await feed(3.0)
        assert not run.link.connected
        assert run.store.backlog() > 0  # the outage piles up in the outbox, nothing dropped
        broker.start()
        await feed(0.5)
        await eventually(lambda: set(sub.seed_ids()) >= set(range(1, added + 1)), 20,
                         "every id after the restart")
        assert sorted(set(sub.seed_ids())) == list(range(1, added + 1))
        assert run.link.stats.connects >= 2


async def test_broker_unreachable_at_start_records_wait_then_flow(
    stopped_mosquitto: Mosquitto, tmp_path: Path
) -> None:
    broker = stopped_mosquitto
    async with running_link(make_settings(broker.port), tmp_path / "r.db") as run:
        run.store.add_seeds(drops(500))
        await asyncio.sleep(1.0)
        assert not run.link.connected
        assert run.store.backlog() == 500
        assert run.link.stats.last_error  # the reason is kept for diagnostics
        broker.start()
        async with subscriber(broker.port, BASE) as sub:
            # the subscriber may come up after the first batches: the retained state and
            # a full drain of the outbox are what matter here
            await eventually(lambda: run.store.backlog() == 0, what="outbox drained")
            await eventually(lambda: bool(sub.on("state")), what="retained state")
            assert run.link.stats.seeds_published >= 500


DAEMON = textwrap.dedent(
    """
    import asyncio, sys
    from datetime import UTC, datetime, timedelta
    from gateway.core.alarms import AlarmBoard
    from gateway.config import parse_config
    from gateway.link.mqtt import MqttLink
    from gateway.link.payloads import StatePayload
    from gateway.core.records import SeedDrop
    from gateway.recording.store import RecordStore

    port, db, mode = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    settings = parse_config({"machine": {"id": "seeder-t"}, "mqtt": {
        "enabled": True, "port": port, "keepalive": 5, "reconnect_max_s": 0.5,
        "batch_max_records": 200, "batch_max_ms": 100, "max_inflight_batches": 4}})

    class Sink:
        def execute(self, command, source):
            return "ok"

    def state():
        return StatePayload(machine_id="seeder-t", utc=datetime.now(UTC), work_state="working")

    async def main():
        store = RecordStore(db, "seeder-t", commit_interval_s=0.05)
        link = MqttLink(settings, store, Sink(), state, AlarmBoard("seeder-t"))
        t0 = datetime(2026, 4, 20, tzinfo=UTC)
        batch = [SeedDrop(row=1, utc=t0 + timedelta(milliseconds=i), lat=52.0, lon=13.0,
                          fix="rtk_fixed", speed_kmh=8.0) for i in range(50)]
        async with asyncio.TaskGroup() as tg:
            tg.create_task(store.run())
            tg.create_task(link.run())
            while mode == "feed":
                store.add_seeds(batch)
                await asyncio.sleep(0.01)

    asyncio.run(main())
    """
)


def _spawn(port: int, db: Path, mode: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-c", DAEMON, str(port), str(db), mode], cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
    )


def _reap(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=5)


async def test_sigkill_mid_stream_resends_unacked_and_the_will_says_offline(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """A daemon killed mid-stream: broker publishes the will; the restart resends the rest."""
    db = tmp_path / "daemon.db"
    async with subscriber(mosquitto.port, BASE) as sub:
        proc = _spawn(mosquitto.port, db, "feed")
        try:
            await eventually(lambda: len(sub.seed_ids()) >= 2000, 20, "seeds from the daemon")
            assert sub.on("status")[-1] == b"online"
            kill_index = len(sub.messages)
            proc.send_signal(signal.SIGKILL)
            await asyncio.to_thread(proc.wait, 5)
        finally:
            _reap(proc)
        await eventually(
            lambda: any(t == f"{BASE}/status" and p == b"offline"
                        for t, p, _ in sub.messages[kill_index:]),
            10, "last will 'offline'",
        )
        with RecordStore.open_readonly(db, MACHINE) as ro:
            stored = [r.id for r in ro.query_seeds()]
            unacked = ro.backlog()
        assert stored == list(range(1, len(stored) + 1))
        assert unacked > 0 or set(sub.seed_ids()) == set(stored)
        proc = _spawn(mosquitto.port, db, "drain")

        def statuses_after_kill() -> list[bytes]:
            return [p for t, p, _ in sub.messages[kill_index:] if t == f"{BASE}/status"]

        try:
            await eventually(lambda: set(sub.seed_ids()) >= set(stored), 20, "resent records")
            # the restarted process announces itself after the will (the broker may deliver
            # the will and the new birth in either order if it notices the dead socket late;
            # and when every record had arrived before the kill, the resend is instant)
            await eventually(lambda: b"online" in statuses_after_kill(), 20, "the new birth")
        finally:
            _reap(proc)
        assert sorted(set(sub.seed_ids())) == stored


def test_tilt_critical_topic_maps_to_the_live_critical_angle_command() -> None:
    from gateway.core.commands import CriticalTilt
    from gateway.link.command_payloads import KNOWN_COMMANDS, _to_command
    from gateway.link.payloads import EmptyCommand

    assert KNOWN_COMMANDS["tilt_critical"] is EmptyCommand
    assert _to_command("tilt_critical", EmptyCommand()) == CriticalTilt()
    assert parse_config({"commands": {"enabled": ["tilt_critical"]}}).commands.enabled == [
        "tilt_critical"
    ]


def test_channel_rate_topic_maps_to_the_channel_rate_command() -> None:
    from pydantic import ValidationError

    from gateway.core.commands import SetChannelRate
    from gateway.link.command_payloads import KNOWN_COMMANDS, _to_command
    from gateway.link.payloads import ChannelRateCommand

    payload = KNOWN_COMMANDS["channel_rate"].model_validate_json(
        '{"channel": "deep", "rate_kg_ha": 280}'
    )
    assert isinstance(payload, ChannelRateCommand)
    assert _to_command("channel_rate", payload) == SetChannelRate("deep", 280.0)
    with pytest.raises(ValidationError):
        ChannelRateCommand.model_validate_json('{"channel": "deep", "rate_kg_ha": 0}')


async def test_stop_while_the_birth_awaits_its_puback_still_leaves_offline(
    mosquitto: Mosquitto, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stop between connect and the end of the birth (two round trips on 4G) used to
    disconnect cleanly, which discards the will: the retained status stayed 'online'."""
    published_online = asyncio.Event()
    original = aiomqtt.Client.publish

    async def slow_birth(self: aiomqtt.Client, topic: str, payload: object = None,
                         *args: object, **kwargs: object) -> None:
        await original(self, topic, payload, *args, **kwargs)  # type: ignore[arg-type]
        if payload == b"online":
            published_online.set()
            await asyncio.Event().wait()  # the PUBACK "has not arrived yet"

    monkeypatch.setattr(aiomqtt.Client, "publish", slow_birth)
    async with subscriber(mosquitto.port, BASE) as sub:
        async with running_link(make_settings(mosquitto.port), tmp_path / "r.db"):
            await asyncio.wait_for(published_online.wait(), 10)
            await eventually(lambda: sub.on("status")[-1:] == [b"online"], what="birth")
        await eventually(lambda: sub.on("status")[-1:] == [b"offline"], 5, "offline at stop")


async def test_two_boxes_with_one_client_id_back_off_instead_of_thrashing(
    mosquitto: Mosquitto, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Cloned SD images: each connect takes the other's session over. The backoff used to be
    reset at every CONNACK, so the pair reconnected ~3 times a second forever (22 connects
    in 8 s), flapping the retained status; now sessions this short keep backing off."""
    settings = parse_config({
        "machine": {"id": MACHINE},
        "mqtt": {"enabled": True, "port": mosquitto.port, "keepalive": 5,
                 "reconnect_max_s": 30},
    })
    async with (
        running_link(settings, tmp_path / "a.db") as a,
        running_link(settings, tmp_path / "b.db") as b,
    ):
        def connects() -> int:
            return a.link.stats.connects + b.link.stats.connects

        # The takeovers start when both have connected once; how soon a box notices its
        # session was taken depends on the broker (at worst its keepalive), so wait for them
        # rather than assume they happened within a fixed time.
        await eventually(
            lambda: a.link.stats.disconnects + b.link.stats.disconnects >= 2, 20.0,
            "the two boxes taking each other's session over",
        )
        before = connects()
        await asyncio.sleep(6.0)
        # the delay keeps growing (attempts were reset to 0 at every CONNACK before, which
        # made ~16 connects in 6 s)
        attempts = a.link.backoff.attempts + b.link.backoff.attempts
        assert attempts >= 4, attempts
        assert connects() - before <= 8, (before, connects())
    assert "another client using client id 'sowgate-seeder-t'" in caplog.text


def slow_batch_settings(port: int) -> Settings:
    """Partial batches wait 10 s: longer than a stop's drain may take."""
    return parse_config({
        "machine": {"id": MACHINE},
        "mqtt": {"enabled": True, "host": "127.0.0.1", "port": port, "keepalive": 5,
                 "reconnect_max_s": 0.5, "batch_max_ms": 10_000},
    })


async def test_drain_on_stop_publishes_the_last_commit_at_once(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """What the store committed last (the recorder's final flush on a stop) is published and
    acknowledged within the drain, not held back for its batch window: the link is
    cancelled right after the drain, and seeds left in the outbox wait for the next start."""
    async with subscriber(mosquitto.port, BASE) as sub, \
            running_link(slow_batch_settings(mosquitto.port), tmp_path / "r.db") as run:
        await eventually(lambda: run.link.connected, what="connected")
        ids = [r.id for r in run.store.add_seeds(drops(30))]
        run.store.flush()
        assert run.store.backlog() == 30
        started = time.monotonic()
        await run.link.drain(timeout_s=2.0)
        assert time.monotonic() - started < 1.0  # not the 10 s batch window, nor the 2 s bound
        assert run.store.backlog() == 0
        await eventually(lambda: set(sub.seed_ids()) == set(ids), 5.0, "the drained seeds")


async def test_drain_with_the_broker_down_returns_at_once_and_says_what_waits(
    stopped_mosquitto: Mosquitto, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """No broker: the stop is not held up; the records stay in the outbox (nothing is lost)
    and the log says how many wait for the next start."""
    async with running_link(make_settings(stopped_mosquitto.port), tmp_path / "r.db") as run:
        run.store.add_seeds(drops(12))
        run.store.flush()
        started = time.monotonic()
        await run.link.drain(timeout_s=2.0)
        assert time.monotonic() - started < 0.5
        assert run.store.backlog() == 12
    assert "12 records not acknowledged by the broker at stop (not connected)" in caplog.text
    with RecordStore.open_readonly(tmp_path / "r.db", MACHINE) as store:
        assert store.count_pending_seeds() == 12
