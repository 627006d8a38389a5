"""The seed position model: geometry, fall time, clock mapping, and both prediction methods."""

from __future__ import annotations

import copy
import math
import random
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta
from typing import Any

import pymap3d
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from gateway.config.recording import (
    DEFAULT_FALL_TIME_TABLE,
    PositioningSection,
    row_lateral_from_width,
)
from gateway.core.records import FixQuality, SeedDrop
from gateway.recording.positioning import (
    PAPER_MM_PER_DEG,
    VECTOR_MIN_SEEDS,
    ClockMap,
    Landing,
    LocalFrame,
    RowOffset,
    SeedPositioner,
    fall_time_s,
    heading_diff,
    interpolate_heading,
    paper_lag_m,
    paper_landing,
    rotate_offset,
    row_offset,
)
from gateway.recording.positioning.gnss_time import STEP_CONFIRM_EPOCHS
from gateway.recording.positioning.landing import _new_drop
from simulator.plant import Drive, Leg, Pose

UTC0 = datetime(2026, 5, 1, 8, 0, 0, tzinfo=UTC)
MONO0 = 5000.0  # host monotonic time at drive t = 0
LATENCY_S = 0.04


@dataclass(frozen=True)
class Epoch:
    """The fields of drivers.gnss_reader.GnssEpoch that the position model reads."""

    utc: datetime
    t_mono: float
    lat: float
    lon: float
    alt_m: float | None
    fix: FixQuality
    speed_kmh: float | None
    course_deg: float | None
    heading_deg: float | None
    heading_valid: bool
    num_sv: int | None = None


def epoch_from_pose(
    pose: Pose,
    frame: LocalFrame,
    *,
    jitter_s: float = 0.0,
    heading_valid: bool = True,
    fix: FixQuality = "rtk_fixed",
    course: bool = True,
) -> Epoch:
    lat, lon = frame.to_geodetic(pose.east, pose.north)
    return Epoch(
        utc=UTC0 + timedelta(seconds=pose.t),
        t_mono=MONO0 + pose.t + LATENCY_S + jitter_s,
        lat=lat,
        lon=lon,
        alt_m=frame.alt0,
        fix=fix,
        speed_kmh=pose.speed_kmh,
        course_deg=pose.heading_deg if course else None,
        heading_deg=pose.heading_deg,
        heading_valid=heading_valid,
    )


# a 3.6 m, 6-row planter (0.6 m rows): long lever arms make heading errors visible
ROW_LATERAL_M = [-1.5, -0.9, -0.3, 0.3, 0.9, 1.5]


def settings(**kw: object) -> PositioningSection:
    base: dict[str, object] = {
        "gnss_output_latency_ms": LATENCY_S * 1000.0,
        "row_lateral_m": ROW_LATERAL_M,
    }
    base.update(kw)
    return PositioningSection.model_validate(base)


def straight(heading: float, kmh: float = 10.0, seconds: float = 6.0) -> Drive:
    """Already at speed (no acceleration) so truth is a clean straight line."""
    d = Drive(legs=[Leg(seconds, kmh)], start_heading_deg=heading, accel_ms2=1000.0)
    return d


def truth_landing(
    drive: Drive, s: PositioningSection, row: int, t_edge: float
) -> tuple[float, float]:
    pose = drive.pose_at(t_edge)
    t_land = t_edge + fall_time_s(pose.speed_kmh, s.fall_time_table)
    p = drive.pose_at(t_land)
    de, dn = rotate_offset(row_offset(s, row), p.heading_deg)
    return p.east + de, p.north + dn


def run(
    pos: SeedPositioner,
    drive: Drive,
    frame: LocalFrame,
    edges: list[tuple[int, float]],
    *,
    until: float,
    jitter: float = 0.0,
    **epoch_kw: object,
) -> list[Landing]:
    """Feed epochs (10 Hz) and edges in host-arrival order; returns ENU landings + drops."""
    out: list[Landing] = []
    for t, kind, what in arrivals(drive, frame, edges, until=until, jitter=jitter, **epoch_kw):
        landed = (
            pos.add_epoch(what)  # type: ignore[arg-type]
            if kind == "epoch"
            else pos.add_edge(what, t)  # type: ignore[arg-type]
        )
        out += landed
    return out


def arrivals(
    drive: Drive,
    frame: LocalFrame,
    edges: list[tuple[int, float]],
    *,
    until: float,
    jitter: float = 0.0,
    **epoch_kw: object,
) -> list[tuple[float, str, object]]:
    """(host time, "epoch" | "edge", epoch | row) for 10 Hz epochs and the edges, in order."""
    rng = random.Random(3)
    events: list[tuple[float, str, object]] = []
    k = 0
    while k * 0.1 <= until:
        e = epoch_from_pose(
            drive.pose_at(k * 0.1), frame, jitter_s=rng.uniform(0, jitter), **epoch_kw  # type: ignore[arg-type]
        )
        events.append((e.t_mono, "epoch", e))
        k += 1
    for row, t in edges:
        events.append((MONO0 + t, "edge", row))
    events.sort(key=lambda x: x[0])
    return events


FRAME = LocalFrame(45.75, 126.63, 150.0)


# ---------------------------------------------------------------- geometry


@pytest.mark.parametrize(
    ("heading", "expected"),
    [
        (0.0, (0.3, -1.2)),  # facing north: outlet south (behind), right row to the east
        (90.0, (-1.2, -0.3)),  # facing east: behind is west, right is south
        (180.0, (-0.3, 1.2)),
        (270.0, (1.2, 0.3)),
        (30.0, (-1.2 * 0.5 + 0.3 * math.sqrt(3) / 2, -1.2 * math.sqrt(3) / 2 - 0.3 * 0.5)),
    ],
)
def test_rotation_by_heading_places_a_right_row_behind_and_right(
    heading: float, expected: tuple[float, float]
) -> None:
    de, dn = rotate_offset(RowOffset(1.2, 0.3), heading)
    assert de == pytest.approx(expected[0], abs=1e-12)
    assert dn == pytest.approx(expected[1], abs=1e-12)


@pytest.mark.parametrize("heading", [0.0, 90.0, 180.0, 270.0, 123.4])
def test_left_and_right_rows_mirror_about_the_centre_line(heading: float) -> None:
    left = rotate_offset(RowOffset(1.2, -0.9), heading)
    right = rotate_offset(RowOffset(1.2, 0.9), heading)
    behind = rotate_offset(RowOffset(1.2, 0.0), heading)
    # the centre outlet is the midpoint, and left/right are 1.8 m apart across the track
    assert (left[0] + right[0]) / 2 == pytest.approx(behind[0], abs=1e-12)
    assert math.dist(left, right) == pytest.approx(1.8)
    # a right row is on the right: cross product of forward × (right − left) is negative
    fwd = (math.sin(math.radians(heading)), math.cos(math.radians(heading)))
    cross = fwd[0] * (right[1] - left[1]) - fwd[1] * (right[0] - left[0])
    assert cross < 0


def test_rows_share_the_working_width_evenly_centred_on_the_antenna() -> None:
    """Paper C's R·m/(n−1) read as row spacing R/n: six 0.6 m rows work 3.6 m."""
    assert row_lateral_from_width(3.6, 6) == pytest.approx(ROW_LATERAL_M)
    assert row_lateral_from_width(2.0, 1) == [0.0]
    with pytest.raises(ValueError, match="rows must be >= 1"):
        row_lateral_from_width(2.0, 0)


def test_a_section_without_row_offsets_is_refused_by_the_position_model() -> None:
    """Only Settings can derive the offsets (it knows the machine); a hand-built section
    without them must fail by name rather than position seeds nowhere."""
    with pytest.raises(ValueError, match=r"positioning\.row_lateral_m is not set"):
        SeedPositioner(PositioningSection())


def test_fall_time_follows_paper_table_interpolates_and_clamps() -> None:
    table = DEFAULT_FALL_TIME_TABLE
    assert fall_time_s(4.0, table) == pytest.approx(0.1142)
    assert fall_time_s(4.5, table) == pytest.approx((0.1142 + 0.1116) / 2)
    assert fall_time_s(0.0, table) == pytest.approx(0.1142)
    assert fall_time_s(30.0, table) == pytest.approx(0.1041)


def test_heading_interpolation_wraps_through_north() -> None:
    assert interpolate_heading(359.0, 1.0, 0.5) == pytest.approx(0.0)
    assert interpolate_heading(350.0, 10.0, 0.25) == pytest.approx(355.0)
    assert interpolate_heading(10.0, 350.0, 0.75) == pytest.approx(355.0)
    assert heading_diff(359.0, 1.0) == pytest.approx(2.0)


@pytest.mark.parametrize("lat", [0.0, 60.0])
def test_local_frame_metres_match_the_ellipsoid_at_latitude(lat: float) -> None:
    """1 m east/north converts to the degrees the WGS84 radii of curvature say."""
    a, e2 = 6378137.0, 6.69437999014e-3
    s = math.sin(math.radians(lat))
    n_radius = a / math.sqrt(1 - e2 * s * s)
    m_radius = a * (1 - e2) / (1 - e2 * s * s) ** 1.5
    frame = LocalFrame(lat, 20.0, 0.0)
    la, lo = frame.to_geodetic(1.0, 1.0)
    assert (la - lat) == pytest.approx(math.degrees(1.0 / m_radius), rel=1e-5)
    assert (lo - 20.0) == pytest.approx(
        math.degrees(1.0 / (n_radius * math.cos(math.radians(lat)))), rel=1e-5
    )


@pytest.mark.parametrize("lat", [0.0, 60.0])
def test_paper_conversion_uses_1112e8_mm_per_degree_and_cos_lat(lat: float) -> None:
    s = settings()
    la, lo = paper_landing(lat, 10.0, 90.0, 0.0, RowOffset(1.0, 0.0), s)  # 1 m west, standing
    assert la == pytest.approx(lat, abs=1e-12)
    assert lo - 10.0 == pytest.approx(-1000.0 / (PAPER_MM_PER_DEG * math.cos(math.radians(lat))))


def test_paper_lag_is_speed_times_total_lag() -> None:
    # 10 km/h · 197.2 ms / 3600 = 0.5478 m
    assert paper_lag_m(10.0, settings()) == pytest.approx(10.0 * 197.2 / 3600.0)


# ---------------------------------------------------------------- clock


def test_clock_map_recovers_the_offset_despite_one_sided_jitter() -> None:
    rng = random.Random(1)
    clock = ClockMap(latency_s=0.04)
    offset = 123.456
    for k in range(50):
        utc = 1.7e9 + k * 0.1
        clock.observe(utc + offset + 0.04 + rng.expovariate(1 / 0.01), utc)
    assert clock.offset_s == pytest.approx(offset, abs=0.002)
    assert clock.utc_of_mono(clock.mono_of_utc(1.7e9)) == pytest.approx(1.7e9)


def test_clock_map_without_epochs_refuses_to_guess() -> None:
    with pytest.raises(ValueError, match="no epoch"):
        _ = ClockMap(0.0).offset_s


# ---------------------------------------------------------------- interpolated method


@pytest.mark.parametrize("heading", [0.0, 90.0, 180.0, 270.0, 37.0])
@pytest.mark.parametrize("row", [1, 6])
def test_interpolated_landing_matches_truth_on_a_clean_straight_pass(
    heading: float, row: int
) -> None:
    drive = straight(heading)
    s = settings()
    pos = SeedPositioner(s)
    out = run(pos, drive, FRAME, [(row, 2.03)], until=4.0, jitter=0.015)
    assert len(out) == 1
    east, north, drop = out[0].east, out[0].north, out[0].drop
    te, tn = truth_landing(drive, s, row, 2.03)
    assert math.hypot(east - te, north - tn) < 0.002
    assert drop.extrapolated is False and drop.heading_source == "dual_antenna"
    # the lat/lon written is the same point
    e2, n2, _ = pymap3d.geodetic2enu(
        drop.lat, drop.lon, FRAME.alt0, FRAME.lat0, FRAME.lon0, FRAME.alt0
    )
    assert math.hypot(e2 - te, n2 - tn) < 0.002


@pytest.mark.parametrize("lat", [0.0, 60.0])
def test_interpolated_positions_hold_at_the_equator_and_at_60_degrees(lat: float) -> None:
    frame = LocalFrame(lat, 10.0, 0.0)
    drive = straight(45.0)
    s = settings()
    out = run(SeedPositioner(s), drive, frame, [(3, 1.5)], until=3.0)
    te, tn = truth_landing(drive, s, 3, 1.5)
    assert math.hypot(out[0].east - te, out[0].north - tn) < 0.002


def test_seed_waits_for_the_epoch_after_its_landing_instant() -> None:
    drive = straight(0.0)
    s = settings()
    pos = SeedPositioner(s)
    for k in range(11):  # epochs up to t = 1.0 s
        pos.add_epoch(epoch_from_pose(drive.pose_at(k * 0.1), FRAME))
    assert pos.add_edge(2, MONO0 + 1.0 + LATENCY_S + 0.001) == []
    assert pos.pending == 1
    # t = 1.1 brackets the landing (≈ 1.147 s)? no: it needs t = 1.2
    assert pos.add_epoch(epoch_from_pose(drive.pose_at(1.1), FRAME)) == []
    landed = pos.add_epoch(epoch_from_pose(drive.pose_at(1.2), FRAME))
    assert len(landed) == 1 and not landed[0].drop.extrapolated
    assert pos.pending == 0


def test_heading_wrap_from_359_to_1_degree_keeps_the_outlet_behind() -> None:
    # turning right through north at 20 deg/s, heading 359 → 1 around the seed
    drive = Drive(legs=[Leg(4.0, 8.0, yaw_rate_dps=20.0)], start_heading_deg=330.0, accel_ms2=100)
    s = settings()
    t_edge = 1.5 - 0.11  # lands close to heading 0 (330 + 20·1.5)
    out = run(SeedPositioner(s), drive, FRAME, [(4, t_edge)], until=3.0)
    drop = out[0].drop
    assert min(drop.heading_deg, 360 - drop.heading_deg) < 1.0
    te, tn = truth_landing(drive, s, 4, t_edge)
    assert math.hypot(out[0].east - te, out[0].north - tn) < 0.005


def test_invalid_heading_falls_back_to_course_when_moving() -> None:
    drive = straight(90.0)
    s = settings()
    out = run(SeedPositioner(s), drive, FRAME, [(1, 2.0)], until=3.0, heading_valid=False)
    drop = out[0].drop
    assert drop.heading_source == "course"
    te, tn = truth_landing(drive, s, 1, 2.0)
    assert math.hypot(out[0].east - te, out[0].north - tn) < 0.005


def test_invalid_heading_while_standing_is_flagged_none() -> None:
    drive = Drive(legs=[Leg(3.0, 0.0)], start_heading_deg=90.0)
    out = run(SeedPositioner(settings()), drive, FRAME, [(1, 1.0)], until=2.0, heading_valid=False)
    drop = out[0].drop
    assert drop.heading_source == "none" and drop.heading_deg is None


def test_course_is_derived_from_positions_when_the_receiver_gives_none() -> None:
    drive = straight(200.0)
    out = run(
        SeedPositioner(settings()), drive, FRAME, [(2, 2.0)], until=3.0,
        heading_valid=False, course=False,
    )
    drop = out[0].drop
    assert drop.heading_source == "course"
    assert drop.heading_deg == pytest.approx(200.0, abs=0.01)


def test_extrapolation_reaches_at_most_one_epoch_ahead_and_flags_it() -> None:
    drive = straight(0.0, kmh=10.0)
    s = settings()
    pos = SeedPositioner(s)
    for k in range(11):
        pos.add_epoch(epoch_from_pose(drive.pose_at(k * 0.1), FRAME))
    # the receiver goes silent; one seed lands 0.05 s past the last fix, one 0.5 s past
    pos.add_edge(1, MONO0 + 1.05 - 0.1075 + LATENCY_S * 0)  # landing ≈ 1.05
    pos.add_edge(2, MONO0 + 1.5 - 0.1075)  # landing ≈ 1.5
    assert pos.poll(MONO0 + 1.2) == []  # not yet timed out
    landed = pos.poll(MONO0 + 3.0)
    assert [la.drop.row for la in landed] == [1, 2]
    near, far = landed
    assert near.drop.extrapolated and far.drop.extrapolated
    assert near.drop.fix == "rtk_fixed"
    te, tn = truth_landing(drive, s, 1, 1.05 - 0.1075)
    assert math.hypot(near.east - te, near.north - tn) < 0.01
    # the far one is capped one epoch (0.1 s · 2.78 m/s) past the last fix and marked no-fix
    last_antenna_north = drive.pose_at(1.0).north
    assert far.north - (last_antenna_north - 1.2) == pytest.approx(0.2778, abs=0.01)
    assert far.drop.fix == "none"
    assert pos.stats.extrapolation_capped == 1


def test_spacing_is_the_distance_to_the_previous_seed_of_the_same_row() -> None:
    drive = straight(90.0, kmh=7.2)  # 2 m/s
    s = settings()
    out = run(
        SeedPositioner(s), drive, FRAME, [(1, 1.0), (2, 1.05), (1, 1.125), (1, 1.25)], until=3.0
    )
    by_row = [(la.drop.row, la.drop.spacing_m) for la in out]
    assert by_row[0] == (1, None) and by_row[1] == (2, None)
    assert by_row[2][1] == pytest.approx(0.25, abs=0.002)
    assert by_row[3][1] == pytest.approx(0.25, abs=0.002)


def test_spacing_restarts_after_a_long_gap_in_the_row() -> None:
    drive = straight(90.0, kmh=7.2, seconds=10.0)
    out = run(SeedPositioner(settings()), drive, FRAME, [(1, 1.0), (1, 5.0)], until=6.0)
    assert [la.drop.spacing_m for la in out] == [None, None]


def test_an_edge_before_any_fix_is_counted_not_positioned() -> None:
    pos = SeedPositioner(settings())
    assert pos.add_edge(1, 10.0) == []
    assert pos.stats.unpositioned == 1


def test_an_edge_for_an_unknown_row_is_refused() -> None:
    pos = SeedPositioner(settings())
    with pytest.raises(ValueError, match=r"row 7 outside 1\.\.6"):
        pos.add_edge(7, 10.0)


def test_repeated_epochs_are_ignored() -> None:
    drive = straight(0.0)
    pos = SeedPositioner(settings())
    e = epoch_from_pose(drive.pose_at(0.5), FRAME)
    pos.add_epoch(e)
    pos.add_epoch(e)
    assert (pos.stats.epochs, pos.stats.epochs_ignored) == (1, 1)


@pytest.mark.parametrize("seeds_per_s", [2_100, 6_000])
def test_a_fast_wide_planter_keeps_every_seed_interpolated(seeds_per_s: int) -> None:
    """Up to a 96-row planter at 20 km/h (~5 000 seeds/s): with epochs coming steadily no seed
    may be pushed out to extrapolation because too many wait for their epoch at once."""
    pos = SeedPositioner(settings())
    seconds = 3.0
    n = int(seeds_per_s * seconds)
    edges = [(1 + k % 6, 0.3 + k / seeds_per_s) for k in range(n)]
    out = run(pos, straight(0.0, kmh=20.0, seconds=seconds + 1.0), FRAME, edges,
              until=seconds + 0.8) + pos.flush()
    assert len(out) == n
    assert pos.stats.pending_overflow == 0
    assert pos.stats.extrapolated == 0


def test_flush_positions_every_pending_seed() -> None:
    drive = straight(0.0)
    pos = SeedPositioner(settings())
    pos.add_epoch(epoch_from_pose(drive.pose_at(0.0), FRAME))
    pos.add_epoch(epoch_from_pose(drive.pose_at(0.1), FRAME))
    pos.add_edge(1, MONO0 + 0.15)
    assert pos.pending == 1
    assert len(pos.flush()) == 1 and pos.pending == 0


# ---------------------------------------------------------------- paper method


def test_paper_method_moves_the_outlet_forward_by_the_constant_lag() -> None:
    drive = straight(0.0, kmh=10.0)
    s = settings(method="paper")
    pos = SeedPositioner(s)
    fix = epoch_from_pose(drive.pose_at(1.0), FRAME)
    pos.add_epoch(fix)
    (landing,) = pos.add_edge(6, fix.t_mono + 0.03)
    expected = paper_landing(fix.lat, fix.lon, 0.0, 10.0, row_offset(s, 6), s)
    assert (landing.drop.lat, landing.drop.lon) == pytest.approx(expected, abs=1e-12)
    assert landing.drop.method == "paper"
    # forward of the lever arm by S_lag: north of the antenna by S_lag − 1.2 m
    assert pos.frame is not None
    north_antenna = pos.frame.to_enu(fix.lat, fix.lon)[1]
    assert landing.north - north_antenna == pytest.approx(paper_lag_m(10.0, s) - 1.2, abs=0.01)


def test_a_receiver_time_step_restarts_the_history_instead_of_ignoring_every_epoch() -> None:
    """A receiver restart that sets UTC back an hour must not make all later epochs 'old':
    once STEP_CONFIRM_EPOCHS epochs in a row agree on the new time line it is taken."""
    drive = straight(0.0)
    s = settings()
    pos = SeedPositioner(s)
    for k in range(10):
        pos.add_epoch(epoch_from_pose(drive.pose_at(k * 0.1), FRAME))
    pos.add_edge(1, MONO0 + 0.95)  # waiting for an epoch after ≈ 1.06 s
    stepped = [
        replace(
            epoch_from_pose(drive.pose_at(k * 0.1), FRAME),
            utc=UTC0 - timedelta(hours=1) + timedelta(seconds=k * 0.1),
        )
        for k in range(10, 30)
    ]
    first: list[Landing] = []
    for e in stepped[:STEP_CONFIRM_EPOCHS]:
        first += pos.add_epoch(e)
    assert [la.drop.row for la in first] == [1]  # the waiting seed was finished, not lost
    assert pos.stats.time_steps == 1
    assert pos.time.events.outliers == 0  # the confirming epochs were the new time line
    for e in stepped[STEP_CONFIRM_EPOCHS:15]:
        pos.add_epoch(e)
    assert pos.stats.epochs_ignored == 0
    out = pos.add_edge(2, MONO0 + 2.0)
    for e in stepped[15:]:
        out += pos.add_epoch(e)
    assert len(out) == 1 and not out[0].drop.extrapolated
    te, tn = truth_landing(drive, s, 2, 2.0)
    assert math.hypot(out[0].east - te, out[0].north - tn) < 0.002
    # stamped on the receiver's new time line, not the old one
    assert out[0].drop.utc == pytest.approx(UTC0 - timedelta(hours=1) + timedelta(seconds=2.0),
                                            abs=timedelta(seconds=0.3))


@given(
    st.floats(0.0, 360.0, exclude_max=True),
    st.floats(-5.0, 5.0),
    st.floats(-5.0, 5.0),
)
def test_rotation_preserves_the_lever_arm_and_is_undone_by_the_opposite_heading(
    heading: float, behind: float, right: float
) -> None:
    de, dn = rotate_offset(RowOffset(behind, right), heading)
    assert math.hypot(de, dn) == pytest.approx(math.hypot(behind, right), abs=1e-9)
    # projecting back onto the machine axes recovers the offsets
    h = math.radians(heading)
    assert -(de * math.sin(h) + dn * math.cos(h)) == pytest.approx(behind, abs=1e-9)
    assert de * math.cos(h) - dn * math.sin(h) == pytest.approx(right, abs=1e-9)


# ---------------------------------------------------------------- the per-seed fast path


def _busy_field(pos: SeedPositioner) -> list[Landing]:
    """Many seeds per epoch on a turn, with jitter: most epochs release a run of seeds."""
    drive = Drive(legs=[Leg(3.0, 14.0, yaw_rate_dps=25.0)], start_heading_deg=340.0,
                  accel_ms2=100)
    edges = [(1 + k % 6, 0.05 + k * 0.004) for k in range(600)]
    return run(pos, drive, FRAME, edges, until=3.0, jitter=0.02)


def test_drops_built_without_validation_equal_validated_drops() -> None:
    """The hot path skips pydantic; what it builds must be what the validator would build."""
    out = _busy_field(SeedPositioner(settings()))
    assert len(out) > 500
    for landing in out:
        drop = landing.drop
        again = SeedDrop.model_validate(dict(drop))  # store-only fields included
        assert type(drop) is SeedDrop
        assert drop == again
        assert drop.model_fields_set == again.model_fields_set
        assert drop.model_dump_json() == again.model_dump_json()


@pytest.mark.parametrize(
    "bad",
    [{"lat": 91.0}, {"lon": -180.5}, {"lat": math.nan}, {"heading_deg": 360.0},
     {"spacing_m": -0.1}, {"speed_kmh": -1.0}, {"row": 129}, {"fix": "bogus"}],
)
def test_values_the_schema_refuses_are_still_refused(bad: dict[str, object]) -> None:
    """Skipping validation is only for values inside the schema; the rest get its error."""
    fields: dict[str, object] = {
        "row": 3, "utc": UTC0, "lat": 45.0, "lon": 126.0, "fix": "rtk_fixed",
        "speed_kmh": 10.0, "heading_deg": 12.0, "heading_source": "dual_antenna",
        "extrapolated": False, "method": "interpolated", "spacing_m": 0.2,
    }
    fields.update(bad)
    with pytest.raises(ValidationError):
        _new_drop(**fields)  # type: ignore[arg-type]


def test_a_run_of_seeds_is_positioned_exactly_as_one_at_a_time() -> None:
    """Per-epoch-pair work is shared across a run of seeds; the numbers must not change."""
    pos = SeedPositioner(settings())
    _busy_field(pos)
    # seeds straddling several epoch pairs, one before the history and one past its end
    t_first = pos._sample_time(pos._samples[0])
    t_last = pos._sample_time(pos._samples[-1])
    ready = [(1 + k % 6, t_last - 1.0 + k * 0.0031, 0.1) for k in range(320)]
    ready += [(2, t_first - 0.05, 0.1), (3, t_last + 0.01, 0.1)]
    assert len(ready) >= VECTOR_MIN_SEEDS  # the numpy path
    one_by_one, batched = copy.deepcopy(pos), copy.deepcopy(pos)
    expected = [one_by_one._interpolate(p) for p in ready]
    got = batched._interpolate_many(ready)
    # numpy's libm may differ from math's in the last ulp: a tolerance, far below a nanometre
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        _assert_landing_close(g, e)
    assert batched.stats == one_by_one.stats
    assert batched._previous.keys() == one_by_one._previous.keys()
    for row, prev in batched._previous.items():
        assert prev == pytest.approx(one_by_one._previous[row], rel=0, abs=1e-9)
    # a short run takes the scalar loop: identical to the last bit
    short_pos = copy.deepcopy(pos)
    short = ready[:VECTOR_MIN_SEEDS - 3] + ready[-2:]
    one_by_one = copy.deepcopy(pos)
    expected_short = [one_by_one._interpolate(p) for p in short]
    assert short_pos._interpolate_many(short) == expected_short
    assert short_pos.stats == one_by_one.stats
    assert short_pos._previous == one_by_one._previous


def test_a_run_inside_the_history_takes_the_column_path_with_the_same_numbers() -> None:
    """Every seed bracketed by epochs with headings: spacings and record rows are computed
    over whole columns. Rows seen before the run, a row new to it, and a row whose previous
    seed is older than the spacing reset gap must all come out as one at a time."""
    pos = SeedPositioner(settings())
    _busy_field(pos)
    t_last = pos._sample_time(pos._samples[-1])
    gap = pos.settings.spacing_reset_gap_s
    ready = [(1 + k % 6, t_last - 1.0 + k * 0.0031, 0.1) for k in range(300)]
    pos._previous.pop(6)  # as if row 6 had no seed before the run
    pos._previous[5] = (0.0, 0.0, t_last - 1.0 - 2 * gap)  # long ago: no spacing for row 5
    one_by_one, batched = copy.deepcopy(pos), copy.deepcopy(pos)
    expected = [one_by_one._interpolate(p) for p in ready]
    calls: list[int] = []
    original = batched._landings_of_columns

    def spy(*args: Any) -> list[Landing]:
        calls.append(len(args[0]))
        return original(*args)

    batched._landings_of_columns = spy  # type: ignore[method-assign]
    got = batched._interpolate_many(ready)
    assert calls == [len(ready)]
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        _assert_landing_close(g, e)
    first_of_row_5 = next(g for g, p in zip(got, ready, strict=True) if p[0] == 5)
    assert first_of_row_5.drop.spacing_m is None
    assert batched.stats == one_by_one.stats
    assert batched._previous.keys() == one_by_one._previous.keys()
    for row, prev in batched._previous.items():
        assert prev == pytest.approx(one_by_one._previous[row], rel=0, abs=1e-9)


def _turning_field_live(
    seconds: float, edge_every_s: float, *, jitter: float
) -> tuple[Drive, list[tuple[int, float]], SeedPositioner, list[Landing]]:
    """A turning field with jittered epochs and its seeds positioned one event at a time:
    the reference the batched ways of feeding the positioner are held to."""
    drive = Drive(legs=[Leg(seconds, 14.0, yaw_rate_dps=25.0)], start_heading_deg=340.0,
                  accel_ms2=100)
    n = int((seconds - 0.35) / edge_every_s)
    edges = [(1 + k % 6, 0.05 + k * edge_every_s) for k in range(n)]
    live = SeedPositioner(settings())
    expected = run(live, drive, FRAME, edges, until=seconds, jitter=jitter) + live.flush()
    return drive, edges, live, expected


def test_edges_handed_over_as_a_run_give_what_one_at_a_time_gives() -> None:
    """``add_edges`` (the recorder's runs of edges between two epochs) against ``add_edge``
    per edge, over a turning field with jittered epochs: the same landings, bit for bit."""
    drive, edges, live, expected = _turning_field_live(3.0, 0.004, jitter=0.02)
    # the same arrival order, edges between two epochs handed over together
    in_runs = SeedPositioner(settings())
    events = arrivals(drive, FRAME, edges, until=3.0, jitter=0.02)
    got: list[Landing] = []
    run_rows: list[int] = []
    run_times: list[float] = []
    for t, kind, what in events:
        if kind == "edge":
            run_rows.append(what)  # type: ignore[arg-type]
            run_times.append(t)
            continue
        got += in_runs.add_edges(run_rows, run_times)
        run_rows, run_times = [], []
        got += in_runs.add_epoch(what)  # type: ignore[arg-type]
    got += in_runs.add_edges(run_rows, run_times)
    got += in_runs.flush()
    assert len(got) == len(expected) > 500
    assert got == expected
    assert in_runs.stats == live.stats


def test_seeds_held_for_a_burst_come_out_as_they_would_have_at_each_epoch() -> None:
    """``defer_resolution``/``settle`` around half-second bursts (the recorder's flush)
    against positioning at every epoch, over a turning field whose epochs arrive with
    jitter, so the clock offset moves now and then and held seeds must be positioned first."""
    drive, edges, live, expected = _turning_field_live(6.0, 0.003, jitter=0.03)
    held = SeedPositioner(settings())
    moves: list[bool] = []
    would_move = held._would_move_held

    def spy(t_mono: float, utc_s: float) -> bool:
        moves.append(would_move(t_mono, utc_s))
        return moves[-1]

    held._would_move_held = spy  # type: ignore[method-assign]
    got: list[Landing] = []
    burst_end = MONO0 + 0.5
    held.defer_resolution()
    for t, kind, what in arrivals(drive, FRAME, edges, until=6.0, jitter=0.03):
        if t > burst_end:
            got += held.settle()
            held.defer_resolution()
            burst_end += 0.5
        got += (held.add_epoch(what) if kind == "epoch"  # type: ignore[arg-type]
                else held.add_edge(what, t))  # type: ignore[arg-type]
    got += held.settle() + held.flush()
    assert any(moves) and not all(moves)  # held seeds were positioned early at times
    assert len(got) == len(expected) == len(edges)
    assert [g.stored[1] for g in got] == [e.stored[1] for e in expected]  # same order
    for g, e in zip(got, expected, strict=True):
        _assert_landing_close(g, e)
    assert held.stats == live.stats


def test_a_run_with_a_row_out_of_range_is_refused_before_anything_is_queued() -> None:
    pos = SeedPositioner(settings())
    run(pos, straight(0.0), FRAME, [], until=0.5)
    with pytest.raises(ValueError, match="row 99 outside"):
        pos.add_edges([1, 2, 99], [MONO0 + 0.5, MONO0 + 0.51, MONO0 + 0.52])
    assert pos.pending == 0


def _assert_landing_close(got: Landing, expected: Landing) -> None:
    g, e = got.drop, expected.drop
    assert got.t_land == expected.t_land
    assert got.east == pytest.approx(expected.east, rel=0, abs=1e-9)
    assert got.north == pytest.approx(expected.north, rel=0, abs=1e-9)
    assert g.lat == pytest.approx(e.lat, rel=0, abs=1e-12)
    assert g.lon == pytest.approx(e.lon, rel=0, abs=1e-12)
    assert g.speed_kmh == pytest.approx(e.speed_kmh, rel=0, abs=1e-12)
    assert g.heading_deg == pytest.approx(e.heading_deg, rel=0, abs=1e-10)
    if e.spacing_m is None:
        assert g.spacing_m is None
    else:
        assert g.spacing_m == pytest.approx(e.spacing_m, rel=0, abs=1e-9)
    approx = {"lat", "lon", "speed_kmh", "heading_deg", "spacing_m"}
    assert g.model_dump(exclude=approx) == e.model_dump(exclude=approx)
    assert got.stored[0] == expected.stored[0]  # the stored utc_us
