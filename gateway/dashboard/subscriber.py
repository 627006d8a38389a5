"""The dashboard's MQTT session: subscribe to every machine, feed the model, send commands.

The same ``[mqtt]`` settings as the daemon (host, port, user, password file, TLS), under its
own client id (``[dashboard] client_id``) with a persistent session: seeds the daemons
published while the dashboard was away, or while the broker was restarting, are redelivered
by the broker (docs/mqtt.md), and ``Fleet`` drops what it has already (dedupe by id).

Reconnecting is an outer loop around ``async with aiomqtt.Client(...)`` (aiomqtt 2.x has no
reconnect of its own); while it is away the page says so (``Fleet.set_broker``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
from collections.abc import Callable
from typing import Any

import aiomqtt

from drivers.backoff import Backoff
from gateway.config import Settings
from gateway.dashboard.guard import LogLimiter
from gateway.dashboard.model import Fleet
from gateway.link.mqtt import mqtt_client

log = logging.getLogger(__name__)

COMMAND_TIMEOUT_S = 10.0


class CommandRefused(Exception):
    """A command the dashboard does not send (disabled, broker away): the page shows why."""


class DashboardSubscriber:
    def __init__(
        self,
        settings: Settings,
        fleet: Fleet,
        *,
        on_change: Callable[[], None] = lambda: None,
        backoff: Backoff | None = None,
    ) -> None:
        self.cfg = settings.mqtt
        self.client_id = settings.dashboard.client_id
        self.prefix = self.cfg.topic_prefix.rstrip("/")
        self.fleet = fleet
        self.enabled_commands = frozenset(settings.commands.enabled)
        self.on_change = on_change
        self.backoff = backoff or Backoff(initial_s=0.5, cap_s=min(5.0, self.cfg.reconnect_max_s))
        self._client: aiomqtt.Client | None = None
        self.connects = 0
        self._refused_log = LogLimiter(logger=log)

    def _make_client(self) -> aiomqtt.Client:
        return mqtt_client(self.cfg, self.client_id, clean_session=False)

    async def run(self) -> None:
        """Connect, receive, reconnect; for ever. Only ``CancelledError`` escapes."""
        while True:
            try:
                async with self._make_client() as client:
                    self._client = client
                    for suffix in ("status", "state", "seeds", "alarms", "cmd/+/ack"):
                        await client.subscribe(f"{self.prefix}/+/{suffix}", qos=1)
                    self.connects += 1
                    self.backoff.reset()
                    log.info("dashboard: connected to %s:%s", self.cfg.host, self.cfg.port)
                    self.fleet.set_broker(True)
                    self.on_change()
                    async for message in client.messages:
                        raw = message.payload
                        payload = raw if isinstance(raw, bytes) else str(raw or "").encode()
                        refused = self.fleet.machines_refused
                        if self.fleet.handle(message.topic.value, payload, message.retain):
                            self.on_change()
                        elif self.fleet.machines_refused != refused:
                            self._refused_log.warning(
                                "dashboard: message of machine %r dropped: %d machines shown "
                                "already ([dashboard] max_machines); %d dropped so far",
                                self.fleet.last_refused_id, len(self.fleet.machines),
                                self.fleet.machines_refused)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # every failure means: reconnect later
                error = f"{type(exc).__name__}: {exc}"
                log.warning("dashboard: mqtt %s:%s: %s", self.cfg.host, self.cfg.port, error)
                self.fleet.set_broker(False, f"{self.cfg.host}:{self.cfg.port}: {exc}")
                self.on_change()
            finally:
                self._client = None
            await asyncio.sleep(self.backoff.next_delay())

    async def send_command(
        self, machine_id: str, name: str, payload: dict[str, Any]
    ) -> str:
        """Publish ``cmd/<name>`` for ``machine_id`` with a new request id (returned): the ack
        comes back on ``cmd/<name>/ack`` and the page matches it by that id."""
        if name not in self.enabled_commands:
            raise CommandRefused(f"command {name!r} is not enabled in [commands] enabled")
        view = self.fleet.machines.get(machine_id)
        if view is None:
            raise CommandRefused(f"unknown machine {machine_id!r}")
        if view.status != "online":
            # docs/mqtt.md: a box that is offline never executes it and never answers
            raise CommandRefused(f"{machine_id} is offline: the command would not be executed")
        client = self._client
        if client is None:
            raise CommandRefused("not connected to the MQTT broker")
        request_id = secrets.token_hex(6)
        body = json.dumps({**payload, "request_id": request_id}).encode()
        await client.publish(
            f"{self.prefix}/{machine_id}/cmd/{name}", body, qos=1, retain=False,
            timeout=COMMAND_TIMEOUT_S,
        )
        return request_id
