"""The farm link: MQTT and what travels on it.

- ``mqtt``: the aiomqtt session (outbox, alarms, state, commands, reconnects);
- ``command_payloads``: strict parsing of command payloads (pure, fuzzed);
- ``payloads``: the pydantic models of every topic (docs/schemas is generated from them);
- ``sdnotify``: systemd readiness and watchdog.
"""

__all__ = [
    "command_payloads",
    "mqtt",
    "payloads",
    "sdnotify",
]
