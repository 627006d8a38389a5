"""A dashboard on the real broker that remembers when each message arrived.

Like ``tests.mosquitto.Subscriber`` (persistent session, reconnects), plus the arrival time of
every message, so a row can ask "was this alarm published while the fault lasted?".
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field

import aiomqtt

from tests.reliability.harness import BASE


@dataclass
class Watcher:
    port: int
    base: str = BASE
    client_id: str = "reliability-dashboard"
    messages: list[tuple[float, str, bytes]] = field(default_factory=list)
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
                        self.messages.append((time.monotonic(), m.topic.value, payload))
            except aiomqtt.MqttError:
                await asyncio.sleep(0.1)

    def on(self, suffix: str) -> list[tuple[float, bytes]]:
        topic = f"{self.base}/{suffix}"
        return [(t, p) for t, top, p in self.messages if top == topic]

    def seed_ids(self) -> set[int]:
        out: set[int] = set()
        for _, payload in self.on("seeds"):
            out.update(r["id"] for r in json.loads(payload)["records"])
        return out

    def alarms_between(self, t0: float, t1: float) -> set[str]:
        """Codes shown active between ``t0`` and ``t1``: in the retained state's alarm list or
        raised on the alarms topic."""
        codes: set[str] = set()
        for t, payload in self.on("state"):
            if t0 <= t <= t1:
                with contextlib.suppress(ValueError, KeyError, TypeError):
                    codes.update(a["code"] for a in json.loads(payload)["alarms"])
        for t, payload in self.on("alarms"):
            if t0 <= t <= t1:
                with contextlib.suppress(ValueError, KeyError, TypeError):
                    event = json.loads(payload)
                    if event["active"]:
                        codes.add(event["code"])
        return codes


@contextlib.asynccontextmanager
async def watching(port: int, base: str = BASE) -> AsyncIterator[Watcher]:
    watcher = Watcher(port, base)
    task = asyncio.create_task(watcher.run(), name="reliability-watcher")
    try:
        await asyncio.wait_for(watcher.ready.wait(), 10)
        yield watcher
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
