"""Sections for the link to the farm: MQTT and remote commands."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

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
    "seed_lot",
]


class CommandsSection(Section):
    enabled: list[CommandName] = Field(default_factory=list)
    max_payload_bytes: int = Field(4096, ge=64, le=65536)
