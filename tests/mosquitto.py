"""A real mosquitto broker for tests and benchmarks, on a free 127.0.0.1 port (never 1883).

``stop()`` then ``start()`` reuses the same port, so a client configured once sees the broker
go away and come back exactly as it would after a broker restart in the field.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import aiomqtt

MOSQUITTO_CANDIDATES = ("/usr/sbin/mosquitto", "/usr/bin/mosquitto", "/usr/local/sbin/mosquitto")
START_TIMEOUT_S = 10.0


def find_mosquitto() -> str:
    for candidate in MOSQUITTO_CANDIDATES:
        if Path(candidate).exists():
            return candidate
    found = shutil.which("mosquitto")
    if found:
        return found
    raise RuntimeError("mosquitto not found: `make mosquitto` or apt-get install -y mosquitto")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    if port == 1883:  # pragma: no cover - the kernel will practically never pick it
        return free_port()
    return port


def port_open(port: int, host: str = "127.0.0.1") -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


class Mosquitto:
    """A mosquitto subprocess with a throwaway config; use as a context manager or fixture."""

    def __init__(
        self,
        port: int | None = None,
        *,
        persistent: bool = False,
        listener_options: str = "",
        password_file: Path | None = None,
    ) -> None:
        self.port = port or free_port()
        self.host = "127.0.0.1"
        self._dir = tempfile.TemporaryDirectory(prefix="sowgate-mosquitto-")
        self.dir = Path(self._dir.name)
        # started as root, mosquitto drops to its own user: without this it silently can write
        # neither its log nor its persistence file, and "persistent" sessions die on restart
        os.chmod(self._dir.name, 0o777)
        self.config = Path(self._dir.name) / "mosquitto.conf"
        self.log = Path(self._dir.name) / "mosquitto.log"
        # persistent=True keeps subscribers' sessions (and their queued QoS 1 messages) across
        # a broker restart, as a production broker would; the default is a scratch broker.
        storage = (
            f"persistence true\npersistence_location {self._dir.name}/\n"
            if persistent
            else "persistence false\n"
        )
        # listener_options (e.g. TLS cafile/certfile/keyfile) apply to the one listener; a
        # password_file (mosquitto_passwd format) turns anonymous access off
        auth = (
            f"allow_anonymous false\npassword_file {password_file}\n"
            if password_file is not None
            else "allow_anonymous true\n"
        )
        self.config.write_text(
            f"listener {self.port} 127.0.0.1\n"
            f"{listener_options}"
            f"{auth}"
            f"{storage}"
            f"log_dest file {self.log}\n"
            "log_type error\nlog_type warning\nlog_type notice\n"
            "max_queued_messages 1000000\n",
            encoding="utf-8",
        )
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> None:
        if self.running:
            return
        self._proc = subprocess.Popen(
            [find_mosquitto(), "-c", str(self.config)],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not port_open(self.port):
            if self._proc.poll() is not None:
                log = self.log.read_text(errors="replace") if self.log.exists() else ""
                raise RuntimeError(f"mosquitto exited with {self._proc.returncode}: {log}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"mosquitto did not listen on {self.port} in time")
            time.sleep(0.05)

    def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def close(self) -> None:
        self.stop()
        self._dir.cleanup()

    def __enter__(self) -> Mosquitto:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class Subscriber:
    """A dashboard: persistent session, reconnects, remembers everything it saw and when it
    arrived (``arrived[i]`` is the monotonic time of ``messages[i]``)."""

    port: int
    base: str
    client_id: str = "dashboard"
    messages: list[tuple[str, bytes, bool]] = field(default_factory=list)
    arrived: list[float] = field(default_factory=list)
    ready: asyncio.Event = field(default_factory=asyncio.Event)

    async def run(self) -> None:
        while True:
            try:
                async with aiomqtt.Client("127.0.0.1", self.port, identifier=self.client_id,
                                          clean_session=False) as client:
                    await client.subscribe(f"{self.base}/#", qos=1)
                    self.ready.set()
                    async for m in client.messages:
                        payload = m.payload if isinstance(m.payload, bytes) else b""
                        self.arrived.append(time.monotonic())
                        self.messages.append((m.topic.value, payload, m.retain))
            except aiomqtt.MqttError:
                await asyncio.sleep(0.1)

    def on(self, suffix: str) -> list[bytes]:
        return [p for _, p in self.timed(suffix)]

    def timed(self, suffix: str) -> list[tuple[float, bytes]]:
        """(arrival time, payload) of every message on ``BASE/suffix``."""
        topic = f"{self.base}/{suffix}"
        return [(t, p) for t, (top, p, _) in zip(self.arrived, self.messages, strict=True)
                if top == topic]

    def seed_ids(self) -> list[int]:
        return [r["id"] for p in self.on("seeds") for r in json.loads(p)["records"]]

    def alarms_between(self, t0: float, t1: float) -> set[str]:
        """Codes shown active between ``t0`` and ``t1``: in the retained state's alarm list or
        raised on the alarms topic."""
        codes: set[str] = set()
        for t, payload in self.timed("state"):
            if t0 <= t <= t1:
                with contextlib.suppress(ValueError, KeyError, TypeError):
                    codes.update(a["code"] for a in json.loads(payload)["alarms"])
        for t, payload in self.timed("alarms"):
            if t0 <= t <= t1:
                with contextlib.suppress(ValueError, KeyError, TypeError):
                    event = json.loads(payload)
                    if event["active"]:
                        codes.add(event["code"])
        return codes


@contextlib.asynccontextmanager
async def subscriber(
    port: int, base: str = "sowgate/seeder-01", client_id: str = "dashboard"
) -> AsyncIterator[Subscriber]:
    """A ``Subscriber`` running for the block, subscribed before the block starts."""
    sub = Subscriber(port, base, client_id)
    task = asyncio.create_task(sub.run(), name=f"test-subscriber-{client_id}")
    try:
        await asyncio.wait_for(sub.ready.wait(), 10)
        yield sub
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
