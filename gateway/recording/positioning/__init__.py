"""Where each seed landed: outlet geometry, fall time, timing, and the two prediction methods.

The package is split by what each part owns; the names callers use are re-exported here, so
``from gateway.recording.positioning import SeedPositioner`` keeps working:

- :mod:`.geometry`: row lever arms, their rotation by the heading, heading arithmetic and the
  WGS84 <-> local ENU frame (no time, no GNSS);
- :mod:`.clock`: :class:`ClockMap`, receiver UTC <-> host monotonic time;
- :mod:`.gnss_time`: :class:`GnssTimeGuard`, which receiver time stamps to believe (outliers,
  time steps, GPS week rollover, leap seconds);
- :mod:`.attitude`: :class:`EpochAttitude`, the machine's roll and pitch and a trailed
  implement's heading at each epoch;
- :mod:`.methods`: paper C's model, the fall time, and the antenna interpolated or
  extrapolated between epochs (the model in plain per-seed form);
- :mod:`.landing`: :class:`Landing`, a positioned seed and the record it becomes;
- :mod:`.positioner`: :class:`SeedPositioner`, the stateful part (epoch history, pending
  seeds, timeouts, the fast paths, the machine's attitude and a trailed implement's
  heading per epoch) and its :class:`PositionerStats`;
- :mod:`.survey`: re-positioning stored records with another model, and fitting delay and
  lever arm to surveyed seeds (``sowgate calibrate positions``).

On a slope the antenna is not above the ground point it stands for: with
``positioning.antenna_height_m`` and an ``attitude_source`` the lever arm is corrected by
the machine's roll and pitch (:func:`.geometry.terrain_offset`; positive roll = right side
down, positive pitch = nose up). With ``[positioning.hitch]`` a trailed implement's outlets
follow its own heading (:func:`.geometry.follow_hitch`). See docs/positioning.md.

The benchmarks' oracle (the best any method could do with the same receiver) is not part of
the product: it lives in ``benchmarks/positioning_oracle.py``.

Conventions used throughout (and by the simulator's ground truth):

- local ENU metres (east, north) around a fixed origin, WGS84 via pymap3d;
- heading clockwise from north, so the machine's forward unit vector is (sin ψ, cos ψ) and its
  right-hand unit vector is (cos ψ, −sin ψ). A single rotation replaces paper C's four
  quadrant sign tables;
- a row outlet sits ``behind_m`` behind and ``right_m`` right of the main antenna
  (``positioning.outlet_behind_antenna_m`` and ``positioning.row_lateral_m[row-1]``);
- all times are host ``time.monotonic()`` seconds unless named ``utc``.

Methods:

``paper`` — paper C exactly, the baseline: at the sensor edge take the latest fix, assume the
fix is ``t2 + t3`` old and the seed falls for ``t1``, move the outlet forward by
``S_lag = v·(t1+t2+t3)/3600`` and convert millimetres to degrees with 1.112e8 mm/°. Its error
grows with speed because the true fix age is uniform in 0…T, not T/2.

``interpolated`` (default) — put the antenna epochs on the host clock (see :class:`ClockMap`),
compute the instant the seed reaches the furrow (edge + fall time at the current speed), and
interpolate the antenna position and heading at that instant between the two epochs that
bracket it. Because the bracketing epoch usually arrives *after* the edge, the seed waits in a
short pending queue; only when the next epoch does not come in time is it extrapolated, at most
one epoch period ahead, and flagged.
"""

from gateway.recording.positioning.clock import CLOCK_WINDOW_EPOCHS, ClockMap
from gateway.recording.positioning.geometry import (
    LocalFrame,
    RowOffset,
    heading_diff,
    interpolate_heading,
    rotate_offset,
    row_offset,
    wrap_deg,
)
from gateway.recording.positioning.gnss_time import GnssTimeGuard, TimeCheck, TimeEvents
from gateway.recording.positioning.landing import Landing, utc_us_of
from gateway.recording.positioning.methods import (
    FIX_RANK,
    HEADING_RANK,
    KMH_PER_MS,
    MIN_COURSE_SPEED_KMH,
    PAPER_MM_PER_DEG,
    AntennaSample,
    AntennaState,
    choose_heading,
    extrapolate_state,
    fall_time_s,
    interpolate_state,
    paper_lag_m,
    paper_landing,
    worst_fix,
    worst_heading_source,
)
from gateway.recording.positioning.positioner import (
    DEFAULT_EPOCH_PERIOD_S,
    EPOCH_HISTORY,
    HISTORY_EVICTION_MARGIN_S,
    MAX_EXTRAPOLATION_EPOCHS,
    MAX_PENDING_SEEDS,
    VECTOR_MIN_SEEDS,
    AntennaEpoch,
    Method,
    PositionerStats,
    SeedPositioner,
)

__all__ = [
    "CLOCK_WINDOW_EPOCHS",
    "DEFAULT_EPOCH_PERIOD_S",
    "EPOCH_HISTORY",
    "FIX_RANK",
    "HEADING_RANK",
    "HISTORY_EVICTION_MARGIN_S",
    "KMH_PER_MS",
    "MAX_EXTRAPOLATION_EPOCHS",
    "MAX_PENDING_SEEDS",
    "MIN_COURSE_SPEED_KMH",
    "PAPER_MM_PER_DEG",
    "VECTOR_MIN_SEEDS",
    "AntennaEpoch",
    "AntennaSample",
    "AntennaState",
    "ClockMap",
    "GnssTimeGuard",
    "Landing",
    "LocalFrame",
    "Method",
    "PositionerStats",
    "RowOffset",
    "SeedPositioner",
    "TimeCheck",
    "TimeEvents",
    "choose_heading",
    "extrapolate_state",
    "fall_time_s",
    "heading_diff",
    "interpolate_heading",
    "interpolate_state",
    "paper_lag_m",
    "paper_landing",
    "rotate_offset",
    "row_offset",
    "utc_us_of",
    "worst_fix",
    "worst_heading_source",
    "wrap_deg",
]
