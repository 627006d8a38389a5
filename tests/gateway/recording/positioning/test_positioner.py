"""The positioner's order of resolution when the receiver comes back after a gap."""

from __future__ import annotations

import math

from gateway.recording.positioning import SeedPositioner
from tests.gateway.recording.test_positioning import (
    FRAME,
    MONO0,
    epoch_from_pose,
    settings,
    straight,
    truth_landing,
)


def test_seeds_bracketed_by_the_epoch_after_a_gap_are_interpolated_in_edge_order() -> None:
    """An epoch that arrives when some pending seeds are already past ``pending_timeout_s``
    (the receiver was silent and no edge or poll came since) brackets them all: every seed
    is interpolated across the gap, and the records come out in edge order (the spacing
    and the store's order rely on it). An epoch that expired the overdue seeds before
    resolving the ones it brackets put the extrapolated, older seeds after the newer ones."""
    drive = straight(0.0, kmh=10.0)
    s = settings()
    pos = SeedPositioner(s)
    for k in range(11):  # epochs up to t = 1.0 s, then silence until 2.0 s
        pos.add_epoch(epoch_from_pose(drive.pose_at(k * 0.1), FRAME))
    edges = [(1, 1.0), (2, 1.55)]  # landing ≈ 1.11 (overdue at 2.04) and ≈ 1.66 (not)
    out = []
    for row, t in edges:
        out += pos.add_edge(row, MONO0 + t)
    assert out == []
    out += pos.add_epoch(epoch_from_pose(drive.pose_at(2.0), FRAME))  # arrives at 2.04
    assert [la.drop.row for la in out] == [1, 2]
    assert not any(la.drop.extrapolated for la in out)
    for la, (row, t) in zip(out, edges, strict=True):
        te, tn = truth_landing(drive, s, row, t)
        assert math.hypot(la.east - te, la.north - tn) < 0.01
