"""Paper B's multi-channel metering over CAN.

- ``channels``: each channel's target shaft speed from rate, width and speed, supervised
  against the shaft feedback; lift detection stops every shaft;
- ``prescription``: prescription maps (target rate by position) and the as-applied log;
- ``isobus``: the tractor's speed and hitch as the machine acts on them (source priority,
  staleness, hitch in work).
"""

__all__ = [
    "channels",
    "isobus",
    "prescription",
]
