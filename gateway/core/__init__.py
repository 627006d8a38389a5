"""What every domain shares, and nothing domain-specific.

- ``alarms``: the alarm board (raise, clear, subscribe) every part reports through;
- ``alarm_codes``: the registry of every alarm code, its severity, meaning and remedy (the
  alarm table in docs/mqtt.md is generated from it);
- ``commands``: the operator commands (start, stop, rate, ...) the touchscreen and MQTT send;
- ``records``: the stored seed row and alarm event, and UTC <-> microseconds;
- ``errors``: the exception types the gateway raises.

Imports nothing from the rest of ``gateway`` but ``gateway.config``.
"""

__all__ = [
    "alarm_codes",
    "alarms",
    "commands",
    "errors",
    "records",
]
