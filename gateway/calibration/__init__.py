"""Field calibrations: the fits, the calibration file, applying it at start, the CLI.

- ``fits``: rotation tests (paper A eq. 5/6, paper B g/rev), speed and tilt calibrations, and
  the atomic ``calibration.json`` with undo;
- ``apply``: lays the saved calibrations over the config at start-up;
- ``cli``: ``sowgate calibrate ...``.
"""

__all__ = [
    "apply",
    "cli",
    "fits",
]
