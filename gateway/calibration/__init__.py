"""Field calibrations: the fits, the calibration file, applying it at start, the CLI.

- ``fits``: rotation tests (paper A eq. 5/6, paper B g/rev), speed and tilt calibrations, and
  the atomic ``calibration.json`` with undo;
- ``apply``: lays the saved calibrations over the config (at start-up, and again when the
  file changes while the daemon runs: ``gateway.app.live_calibration``);
- ``lots``: rotation tests kept per seed lot, the active lot per crop;
- ``drive``: runs the meter through a rotation test (``--drive modbus|can``), always off after;
- ``presence``: ``daemon.json``, how the CLI learns a daemon runs and what it applied;
- ``cli``: ``sowgate calibrate ...``.
"""

__all__ = [
    "apply",
    "cli",
    "drive",
    "fits",
    "lots",
    "presence",
]
