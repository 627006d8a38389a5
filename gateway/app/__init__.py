"""The daemon and its command line: the one place that composes everything.

- ``daemon``: the supervisor, the RS485 poll/control loop and the ordered stop;
- ``wiring``: builds the optional parts (recording, MQTT, CAN metering) from the config;
- ``rejected_input``: the counters of input received and not used, and their summary;
- ``cli``: ``sowgate run | check-config | export | calibrate | ...``.
"""

__all__ = [
    "cli",
    "daemon",
    "rejected_input",
    "wiring",
]
