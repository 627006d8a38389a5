"""Paper B's multi-channel metering over CAN.

- ``channels``: each channel's target shaft speed from rate, width and speed, supervised
  against the shaft feedback; lift detection stops every shaft;
- ``prescription``: prescription maps (target rate by position) and the as-applied log.
"""

__all__ = [
    "channels",
    "prescription",
]
