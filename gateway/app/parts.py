"""The optional parts of one machine, typed: what the wiring built and the daemon runs.

A field is None when the config leaves that part off. The daemon, the state payload and the
tests read parts by attribute, so mypy sees every type (they used to travel in a
``dict[str, Any]`` read back by string key).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.agopengps_udp import AgOpenGpsEndpoint
    from drivers.can_bus import IsobusListener
    from drivers.gnss_reader import GnssReader
    from drivers.seed_sensors import GpioSeedSensors, SerialSeedSensors
    from gateway.app.rejected_input import RejectedInputs
    from gateway.link.mqtt import MqttLink
    from gateway.metering.agopengps import CabInputs
    from gateway.metering.channels import MeteringComponent
    from gateway.metering.pwm_channel import PwmChannelPart
    from gateway.recording.alarm_recorder import AlarmRecorder
    from gateway.recording.health import RecordingHealth
    from gateway.recording.recorder import SeedRecorder
    from gateway.recording.row_alarms import RowAlarms
    from gateway.recording.store import RecordStore


@dataclass
class Parts:
    store: RecordStore | None = None
    alarm_recorder: AlarmRecorder | None = None  # alarm events into the store, MQTT or not
    gnss: GnssReader | None = None
    seeds: SeedRecorder | None = None  # the seed recorder
    seed_sensors: SerialSeedSensors | GpioSeedSensors | None = None
    recording_health: RecordingHealth | None = None
    mqtt: MqttLink | None = None
    pwm_channel: PwmChannelPart | None = None
    metering: MeteringComponent | None = None
    isobus: IsobusListener | None = None
    rejected: RejectedInputs | None = None
    row_alarms: RowAlarms | None = None
    agopengps: AgOpenGpsEndpoint | None = None
    agopengps_cab: CabInputs | None = None

