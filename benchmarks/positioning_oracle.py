"""The positioning oracle: where a method that knew every parameter of the field would put a seed.

``bench_positioning`` judges sowgate and paper C's method against an independent truth
(``simulator.field_truth``). The oracle is the floor for any method using the same receiver:
it knows the true lever arm, latencies, antenna height and attitude, the implement's
articulation and this seed lot's mean flight and slide (the truth's ``expected_*`` point of each
seed), but not what is random per seed (its size, its bounce) nor the receiver's error, which
it takes exactly as the receiver made it: the position and heading error of the epochs
bracketing the landing instant, interpolated linearly as an interpolating method would see
them. So its error is the seed's own scatter plus the receiver's noise, nothing else.

Plain arithmetic on plain values: it shares nothing with ``gateway/`` (no lever-arm or heading
helpers), so the floor does not inherit a convention error of the code it judges.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class EpochError:
    """The receiver's error at one epoch instant (reported minus true), in local ENU."""

    t: float
    east_m: float
    north_m: float
    heading_deg: float  # machine heading error, clockwise positive


def interpolated_error(t: float, errors: Sequence[EpochError],
                       times: Sequence[float] | None = None) -> tuple[float, float, float]:
    """(east, north, heading) error at ``t``: linear between the bracketing epochs, the
    nearest epoch's outside their range. ``errors`` sorted by time; ``times`` their instants
    if the caller has them (a drive's seeds share one list instead of one per seed)."""
    if not errors:
        raise ValueError("oracle needs at least one epoch")
    if times is None:
        times = [x.t for x in errors]
    i = bisect.bisect_right(times, t)
    if i == 0 or i >= len(errors):
        x = errors[0 if i == 0 else -1]
        return x.east_m, x.north_m, x.heading_deg
    a, b = errors[i - 1], errors[i]
    w = 0.0 if b.t <= a.t else (t - a.t) / (b.t - a.t)
    return (
        a.east_m + w * (b.east_m - a.east_m),
        a.north_m + w * (b.north_m - a.north_m),
        a.heading_deg + w * (b.heading_deg - a.heading_deg),
    )


def oracle_landing(
    expected: tuple[float, float],
    pivot: tuple[float, float],
    t: float,
    errors: Sequence[EpochError],
    times: Sequence[float] | None = None,
) -> tuple[float, float]:
    """The oracle's landing point for one seed.

    ``expected``: where a mean seed of the lot comes to rest (true parameters, no per-seed
    randomness); ``pivot``: the antenna's reference point on the ground at ``t`` (what the
    receiver's position error moves, and what a heading error turns the outlets around);
    ``t``: the seed's expected landing instant. The vector pivot → expected is turned by the
    interpolated heading error (clockwise), then the whole is shifted by the interpolated
    position error.
    """
    de, dn, dh = interpolated_error(t, errors, times)
    ve, vn = expected[0] - pivot[0], expected[1] - pivot[1]
    c, s = math.cos(math.radians(dh)), math.sin(math.radians(dh))
    return pivot[0] + ve * c + vn * s + de, pivot[1] - ve * s + vn * c + dn
