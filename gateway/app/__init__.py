"""The daemon and its command line: the one place that composes everything.

- ``daemon``: the supervisor, the RS485 poll/control loop and the ordered stop;
- ``wiring``: builds the optional parts (recording, MQTT, CAN metering) from the config;
- ``rejected_input``: the counters of input received and not used, and their summary;
- ``live_calibration``: a calibration saved while running applied at once; seed-lot switches;
- ``rotation_test``: paper A's rotation test started from the touchscreen;
- ``cli``: ``sowgate run | check-config | export | calibrate | ...``.
"""

__all__ = [
    "cli",
    "daemon",
    "live_calibration",
    "rejected_input",
    "rotation_test",
    "wiring",
]
