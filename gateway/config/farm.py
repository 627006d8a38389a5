"""Sections for the link to the farm: MQTT and remote commands."""

from __future__ import annotations

import re
import socket
from typing import Literal

from pydantic import Field, field_validator, model_validator

from gateway.config._base import OptionalPart, Section


class TlsSection(Section):
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    insecure: bool = False

    @model_validator(mode="after")
    def _key_needs_cert(self) -> TlsSection:
        if self.key_file is not None and self.cert_file is None:
            raise ValueError("key_file needs cert_file (the client certificate it belongs to)")
        return self


class MqttSection(OptionalPart):
    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(1883, ge=1, le=65535)
    client_id: str | None = None  # default: sowgate-<machine id>
    username: str | None = None
    password: str | None = None
    password_file: str | None = None
    tls: TlsSection | None = None
    keepalive: int = Field(30, ge=5, le=3600)
    topic_prefix: str = Field("sowgate", min_length=1, pattern=r"^[^#+]+$")
    batch_max_records: int = Field(500, ge=1, le=5000)
    batch_max_ms: float = Field(500.0, gt=0, le=10000)
    max_inflight_batches: int = Field(8, ge=1, le=64)
    reconnect_max_s: float = Field(30.0, gt=0, le=600)
    state_hz: float = Field(1.0, gt=0, le=10)
    # End to end (docs/mqtt.md "The farm server's watermark"): a seed record counts as
    # delivered only once `sowgate ingest` says it is committed in PostgreSQL (retained
    # `ingested`), not on the broker's PUBACK; records not covered after this timeout are
    # published again. Off: a cab without a farm server behaves as before (PUBACK = delivered).
    farm_server_ack: bool = False
    farm_server_ack_timeout_s: float = Field(60.0, ge=1, le=3600)

    @model_validator(mode="after")
    def _credentials(self) -> MqttSection:
        # Both would be silently resolved one way; a password without a user name is never
        # sent (the box would connect anonymously and fail on an ACL far from the cause).
        if self.password is not None and self.password_file is not None:
            raise ValueError("set password or password_file, not both")
        if (self.password is not None or self.password_file is not None) and not self.username:
            raise ValueError("password/password_file needs username (MQTT sends no password "
                             "without a user name)")
        return self


CommandName = Literal[
    "rate", "channel_rate", "start", "stop", "zero_tilt", "tilt_critical", "speed_cal",
    "ack_alarm",
    "seed_lot",
]


class CommandsSection(Section):
    enabled: list[CommandName] = Field(default_factory=list)
    max_payload_bytes: int = Field(4096, ge=64, le=65536)


LOCAL_HOSTS = frozenset({"127.0.0.1", "localhost", "::1", "[::1]"})
# the commands the dashboard's page can send, of those [commands] enabled allows
DASHBOARD_COMMANDS = ("start", "stop", "rate", "ack_alarm")
LISTEN_FORM = r"^(\[[0-9a-fA-F:.]+\]|[^:\s\[\]]+):(\d{1,5})$"


class DashboardSection(Section):
    """``sowgate dashboard``: the web page served by an MQTT subscriber (its own process).

    It reads the same file as the daemon: ``[mqtt]`` says where the broker is, ``[commands]
    enabled`` which controls the page offers. On a cab box the page must work without internet,
    so every asset is in the package; ``tile_url`` (an XYZ template such as
    ``https://tile.example/{z}/{x}/{y}.png``) only adds a background map where there is one.
    """

    listen: str = "127.0.0.1:8080"
    tile_url: str | None = Field(None, pattern=r"^https?://.*\{z\}.*\{x\}.*\{y\}")
    password_file: str | None = None
    # a persistent MQTT session under this id: seeds published while the dashboard was away
    # are redelivered by the broker when it comes back (docs/mqtt.md)
    client_id: str = Field("sowgate-dashboard", min_length=1, max_length=128)
    # seeds kept per machine for the map (the oldest go first); the page draws all of them
    max_seeds: int = Field(300_000, ge=1000, le=5_000_000)
    # The names the page may be reached under (the ``Host`` a browser sends); every other is
    # refused, so a web page elsewhere cannot reach the machine through the farmer's browser
    # by pointing its own name at this box (DNS rebinding). None: the listen address and
    # localhost, 127.0.0.1, ::1, plus this machine's host name (and NAME.local) when listening
    # beyond loopback. "*.farm.lan" takes every name under farm.lan. See gateway/dashboard/guard.py.
    allowed_hosts: list[str] | None = None
    # machines shown: topics from further machine ids are counted, logged and dropped (each
    # machine holds up to max_seeds seeds; 20 000 stray ids must not grow the process)
    max_machines: int = Field(64, ge=1, le=10_000)
    # pages open at once (each holds a queue and gets every update); more are refused
    max_clients: int = Field(16, ge=1, le=1000)

    @field_validator("allowed_hosts")
    @classmethod
    def _allowed_hosts(cls, value: list[str] | None) -> list[str] | None:
        if value is None:
            return None
        out = []
        for raw in value:
            name = raw.strip().lower().strip("[]")
            if not re.fullmatch(r"(\*\.)?[a-z0-9_.-]+|[0-9a-f.]*:[0-9a-f.]*:[0-9a-f:.]*", name):
                raise ValueError(
                    f"{raw!r} is not a host name: give names or addresses without scheme or "
                    'port, e.g. ["cab-box.local", "192.168.1.20", "*.farm.lan"]'
                )
            out.append(name)
        if not out:
            raise ValueError("an empty list would refuse every request; leave it out for "
                             "the default (the listen address and localhost names)")
        return out

    @field_validator("listen")
    @classmethod
    def _listen(cls, value: str) -> str:
        match = re.fullmatch(LISTEN_FORM, value.strip())
        if match is None:
            raise ValueError(
                "must be HOST:PORT, e.g. 127.0.0.1:8080 (this box only), 0.0.0.0:8080 (every "
                "network; needs password_file when the page offers commands) or [::1]:8080"
            )
        if not 1 <= int(match.group(2)) <= 65535:
            raise ValueError(f"the port must be 1-65535, not {match.group(2)}")
        return value.strip()

    @property
    def host(self) -> str:
        return self.listen.rsplit(":", 1)[0].strip("[]")

    @property
    def port(self) -> int:
        return int(self.listen.rsplit(":", 1)[1])

    @property
    def local_only(self) -> bool:
        return self.host in LOCAL_HOSTS or self.host.startswith("127.")

    def trusted_hosts(self) -> frozenset[str]:
        """The host names requests may name: ``allowed_hosts``, or the default."""
        if self.allowed_hosts is not None:
            return frozenset(self.allowed_hosts)
        names = {"localhost", "127.0.0.1", "::1"}
        if self.host not in ("0.0.0.0", "::"):
            names.add(self.host.lower())
        if not self.local_only:
            hostname = socket.gethostname().lower()
            if hostname:
                names.update((hostname, hostname.split(".")[0] + ".local"))
        return frozenset(names)


class FarmServerSection(Section):
    """``sowgate ingest``: the farm-side process that writes every machine's records into
    PostgreSQL (gateway/farm_server, docs/farm-server.md). Read from the same file as the
    daemon, so one config can serve both; the daemon ignores it."""

    # postgresql://user@host/dbname (libpq URL or key=value string); None: ingest refuses to
    # start, naming this key
    database_url: str | None = Field(None, min_length=1)
    # the MQTT 5 shared-subscription group: every ingest process of one farm uses the same
    share_group: str = Field("sowgate-ingest", min_length=1, max_length=64,
                             pattern=r"^[A-Za-z0-9_.-]+$")
    topic_prefix: str = Field("sowgate", min_length=1, pattern=r"^[^#+]+$")
    client_id: str | None = Field(None, min_length=1, max_length=128)  # default: host + pid
    # records are committed at least this often, and at once when a batch reaches batch_rows
    flush_interval_s: float = Field(0.5, gt=0, le=60)
    batch_rows: int = Field(5000, ge=1, le=1_000_000)
    # one state sample kept per machine per this many seconds (the rest are dropped)
    state_sample_s: float = Field(10.0, ge=0, le=3600)
    # machines accepted: further machine ids are counted, logged and dropped
    max_machines: int = Field(1000, ge=1, le=100_000)
    max_payload_bytes: int = Field(4_000_000, ge=1024, le=64_000_000)
    # rows waiting for the database (≈ 0.3 kB each, as binary COPY rows): at this many ingest
    # stops reading from the broker until a commit makes room (back-pressure; the broker keeps
    # the rest, and the cabs publish again whatever no watermark covers)
    max_queued_rows: int = Field(1_000_000, ge=1000, le=50_000_000)
