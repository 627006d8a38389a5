"""The positioning oracle: the landing point the best possible method would report.

``oracle_landing`` knows the true trajectory and the true landing instant, and adds exactly
the GNSS error the receiver made (position and heading noise of the bracketing epochs,
linearly interpolated to the landing instant). Its error is the receiver's noise through the
lever arm, nothing else: the floor against which ``bench_positioning`` measures paper C's
method and the interpolated one.

It lives here, not in ``gateway/``, because only the benchmarks and their tests use it: the
daemon never knows the truth. It shares the product's geometry (lever arm, heading
arithmetic) so that the comparison is between methods, not between conventions.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from gateway.recording.positioning import RowOffset, heading_diff, rotate_offset, wrap_deg


class PoseLike(Protocol):
    """A true antenna pose in local ENU (``simulator.plant.Pose``)."""

    @property
    def east(self) -> float: ...
    @property
    def north(self) -> float: ...
    @property
    def heading_deg(self) -> float: ...


@dataclass(frozen=True)
class MeasuredEpoch:
    """A receiver epoch at its TRUE instant, in the same local ENU as the ground truth."""

    t_true: float
    east: float
    north: float
    heading_deg: float


def oracle_landing(
    offset: RowOffset,
    t_land: float,
    true_pose_at: Callable[[float], PoseLike],
    epochs: Sequence[MeasuredEpoch],
) -> tuple[float, float]:
    """The landing point the best possible method would report with this receiver.

    Definition: for each epoch k the receiver's error is ``measured_k − true(t_k)`` in east,
    north and heading (wrapped). The oracle takes the TRUE antenna pose at the TRUE landing
    instant, adds the error linearly interpolated between the epochs bracketing ``t_land``
    (the nearest epoch's error outside the range), and applies the row's lever arm with the
    erroneous heading. It has no timing error and no trajectory-model error; what remains is
    the GNSS noise as an interpolating method would see it. ``epochs`` must be sorted by time.
    """
    if not epochs:
        raise ValueError("oracle needs at least one measured epoch")
    times = [ep.t_true for ep in epochs]
    i = bisect.bisect_right(times, t_land)
    if i == 0:
        ks, a = (0, 0), 0.0
    elif i >= len(epochs):
        ks, a = (len(epochs) - 1, len(epochs) - 1), 0.0
    else:
        t0, t1 = times[i - 1], times[i]
        ks, a = (i - 1, i), (0.0 if t1 <= t0 else (t_land - t0) / (t1 - t0))

    def error(k: int) -> tuple[float, float, float]:
        ep = epochs[k]
        truth = true_pose_at(ep.t_true)
        return (
            ep.east - truth.east,
            ep.north - truth.north,
            heading_diff(truth.heading_deg, ep.heading_deg),
        )

    e0, e1 = error(ks[0]), error(ks[1])
    err = [x0 + a * (x1 - x0) for x0, x1 in zip(e0, e1, strict=True)]
    truth = true_pose_at(t_land)
    de, dn = rotate_offset(offset, wrap_deg(truth.heading_deg + err[2]))
    return truth.east + err[0] + de, truth.north + err[1] + dn
