"""Terrain compensation and a trailed implement: where the outlets are when the ground is not
level and the implement does not follow the tractor's lever arm."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config.recording import HitchSection, PositioningSection
from gateway.recording.positioning import RowOffset, SeedPositioner, rotate_offset
from gateway.recording.positioning.geometry import (
    antenna_ground_shift,
    articulation_on_circle_deg,
    baseline_attitude,
    heading_diff,
    terrain_offset,
)
from simulator.plant import Drive, Leg
from tests.gateway.recording.test_positioning import (
    FRAME,
    MONO0,
    UTC0,
    Epoch,
    arrivals,
    epoch_from_pose,
    settings,
    straight,
    truth_landing,
)

H = 2.5  # antenna height above the ground


# ---------------------------------------------------------------- geometry


def test_three_degrees_of_roll_at_2_5_m_puts_the_ground_point_13_1_cm_left_of_the_antenna(
) -> None:
    forward, right = antenna_ground_shift(3.0, 0.0, H)
    assert forward == 0.0
    assert right == pytest.approx(-0.1308, abs=0.0001)  # right side down: antenna leans right


def test_nose_up_puts_the_ground_point_ahead_of_the_antenna() -> None:
    forward, right = antenna_ground_shift(0.0, 2.0, H)
    assert forward == pytest.approx(H * math.sin(math.radians(2.0)))
    assert right == 0.0


angles = st.floats(-15.0, 15.0)
lengths = st.floats(-5.0, 5.0)


@given(lengths, lengths)
def test_level_ground_leaves_the_lever_arm_as_measured(behind: float, right: float) -> None:
    assert terrain_offset(RowOffset(behind, right), 0.0, 0.0, H) == RowOffset(behind, right)


@given(lengths, lengths, angles, angles, st.floats(0.0, 4.0))
def test_rolling_the_other_way_mirrors_the_lateral_correction(
    behind: float, right: float, roll: float, pitch: float, height: float
) -> None:
    a = terrain_offset(RowOffset(behind, right), roll, pitch, height)
    b = terrain_offset(RowOffset(behind, -right), -roll, pitch, height)
    assert a.behind_m == pytest.approx(b.behind_m, abs=1e-12)
    assert a.right_m == pytest.approx(-b.right_m, abs=1e-12)


@given(lengths, lengths, angles, angles)
def test_the_outlets_offsets_shorten_to_their_horizontal_projection(
    behind: float, right: float, roll: float, pitch: float
) -> None:
    t = terrain_offset(RowOffset(behind, right), roll, pitch, 0.0)
    assert abs(t.behind_m) <= abs(behind) + 1e-12 and abs(t.right_m) <= abs(right) + 1e-12


@pytest.mark.parametrize(
    ("offset", "expected"),
    [
        (90.0, (3.0, None)),  # secondary antenna on the left: baseline up = right side down
        (-90.0, (-3.0, None)),  # on the right: baseline up = left side down
        (0.0, (None, 3.0)),  # ahead: baseline up = nose up
        (180.0, (None, -3.0)),
    ],
)
def test_the_baseline_pitch_is_roll_side_by_side_and_pitch_fore_and_aft(
    offset: float, expected: tuple[float | None, float | None]
) -> None:
    roll, pitch = baseline_attitude(3.0, offset)
    assert (roll, pitch) == pytest.approx(expected)


# ---------------------------------------------------------------- the positioner on a slope


@dataclass(frozen=True)
class TiltedEpoch(Epoch):
    baseline_pitch_deg: float | None = None


def rolled_run(
    pos: SeedPositioner, drive: Drive, edges: list[tuple[int, float]], roll: float,
    *, heading_offset: float = 90.0, until: float = 4.0,
) -> list[Any]:
    """Epochs of an antenna leaning H·sin(roll) right of the drive's ground line, with the
    baseline pitch side-by-side antennas report; edges as in test_positioning.run."""
    out: list[Any] = []
    lean = H * math.sin(math.radians(roll))
    for t, kind, what in arrivals(drive, FRAME, edges, until=until):
        if kind == "edge":
            out += pos.add_edge(what, t)  # type: ignore[arg-type]
            continue
        e: Epoch = what  # type: ignore[assignment]
        pose = drive.pose_at((e.utc - UTC0).total_seconds())
        de, dn = rotate_offset(RowOffset(0.0, lean), pose.heading_deg)
        lat, lon = FRAME.to_geodetic(pose.east + de, pose.north + dn)
        base = epoch_from_pose(pose, FRAME)
        tilted = TiltedEpoch(**{**base.__dict__, "t_mono": e.t_mono, "lat": lat, "lon": lon},
                             baseline_pitch_deg=roll * math.sin(math.radians(heading_offset)))
        out += pos.add_epoch(tilted)
    return out + pos.flush()


def ground_truth(drive: Drive, s: PositioningSection, row: int, t_edge: float,
                 roll: float) -> tuple[float, float]:
    """The outlet on the rolled ground: the ground line, lateral offsets shortened."""
    flat = s.model_copy(update={"row_lateral_m": [
        r * math.cos(math.radians(roll)) for r in s.lateral_offsets()]})
    return truth_landing(drive, flat, row, t_edge)


EDGES = [(1 + k % 6, 1.0 + k * 0.013) for k in range(120)]


def errors(out: list[Any], drive: Drive, s: PositioningSection, roll: float) -> list[float]:
    """Each seed's distance from its truth (in FRAME: the positioner's own frame starts at
    its first epoch, the leaning antenna)."""
    out_enu = [FRAME.to_enu(la.drop.lat, la.drop.lon) for la in out]
    return [
        math.hypot(e - te, n - tn)
        for (e, n, _), (row, t) in zip(out_enu, EDGES, strict=True)
        for te, tn in [ground_truth(drive, s, row, t, roll)]
    ]


def test_the_dual_antenna_roll_puts_seeds_back_on_the_rolled_ground() -> None:
    drive = straight(37.0)
    s = settings(antenna_height_m=H, attitude_source="dual_antenna")
    out = rolled_run(SeedPositioner(s, baseline_offset_deg=90.0), drive, EDGES, 3.0)
    assert len(out) == len(EDGES)
    assert max(errors(out, drive, s, 3.0)) < 0.002
    assert {la.drop.attitude for la in out} == {"dual_antenna"}
    assert {round(la.drop.roll_deg, 6) for la in out} == {3.0}
    assert {la.drop.pitch_deg for la in out} == {None}  # side by side: pitch not measured


def test_without_an_attitude_source_seeds_are_off_by_the_lean_and_say_so() -> None:
    drive = straight(37.0)
    # attitude_source = "none": a config refuses the height alone (it corrects nothing, as
    # this shows), so the section is built past the check
    s = settings().model_copy(update={"antenna_height_m": H})
    out = rolled_run(SeedPositioner(s, baseline_offset_deg=90.0), drive, EDGES, 3.0)
    assert min(errors(out, drive, s, 3.0)) > 0.12  # the 13 cm of the antenna's lean
    assert {(la.drop.attitude, la.drop.roll_deg) for la in out} == {("none", None)}


def test_a_sensor_mounted_the_other_way_is_inverted_by_its_key() -> None:
    drive = straight(37.0)
    s = settings(antenna_height_m=H, attitude_source="dual_antenna", attitude_invert=True)
    # the antennas' baseline reads -3 on a slope that is +3 (mounted the other way round)
    out = rolled_run(SeedPositioner(s, baseline_offset_deg=90.0), drive, EDGES, 3.0)
    assert {round(la.drop.roll_deg, 6) for la in out} == {-3.0}
    flipped = rolled_run(SeedPositioner(s, baseline_offset_deg=-90.0), drive, EDGES, 3.0)
    assert {round(la.drop.roll_deg, 6) for la in flipped} == {3.0}
    assert max(errors(flipped, drive, s, 3.0)) < 0.002


def test_the_inclinometer_roll_corrects_while_fresh_and_is_not_used_stale() -> None:
    drive = straight(37.0)
    s = settings(antenna_height_m=H, attitude_source="inclinometer")
    pos = SeedPositioner(s)
    pos.add_attitude(MONO0 + 0.5, 3.0)  # one reading, then the sensor goes quiet
    out = rolled_run(pos, drive, EDGES, 3.0)
    fresh = [la for la, (_, t) in zip(out, EDGES, strict=True) if t < 1.3]
    stale = [la for la, (_, t) in zip(out, EDGES, strict=True) if t > 1.8]
    assert fresh and stale
    assert {la.drop.attitude for la in fresh} == {"inclinometer"}
    assert {(la.drop.attitude, la.drop.roll_deg) for la in stale} == {("none", None)}


def test_runs_on_a_slope_take_the_fast_paths_with_the_same_numbers() -> None:
    """The vector and pair paths correct exactly as the per-seed model does."""
    drive = Drive(legs=[Leg(6.0, 10.0, yaw_rate_dps=4.0)], start_heading_deg=10.0,
                  accel_ms2=1000.0)
    s = settings(antenna_height_m=H, attitude_source="dual_antenna")
    pos = SeedPositioner(s, baseline_offset_deg=90.0)
    rolled_run(pos, drive, [], 3.0, until=5.0)
    t_last = pos._sample_time(pos._samples[-1])
    ready = [(1 + k % 6, t_last - 1.0 + k * 0.0031, 0.1) for k in range(300)]
    for run in (ready, ready[:20]):  # the numpy path, and the per-pair loop
        one, many = copy.deepcopy(pos), copy.deepcopy(pos)
        expected = [one._interpolate(p) for p in run]
        got = many._interpolate_many(run)
        for g, e in zip(got, expected, strict=True):
            assert math.hypot(g.east - e.east, g.north - e.north) < 1e-9
            ge, ee = g.drop, e.drop
            assert (ge.attitude, ge.roll_deg) == (ee.attitude, pytest.approx(ee.roll_deg))
            assert ge.offset_east_m == pytest.approx(ee.offset_east_m, abs=1e-9)
            assert ge.delay_ms == pytest.approx(ee.delay_ms)


# ---------------------------------------------------------------- a trailed implement


HITCH = HitchSection(behind_antenna_m=1.5, outlets_behind_hitch_m=4.0)


def circle_drive(radius_m: float, kmh: float, seconds: float) -> Drive:
    v = kmh / 3.6
    yaw = math.degrees(v / radius_m)
    return Drive(legs=[Leg(seconds, kmh, yaw_rate_dps=yaw)], accel_ms2=1000.0, dt=0.005)


def hitch_landings(s: PositioningSection, drive: Drive, edges: list[tuple[int, float]],
                   until: float) -> list[Any]:
    pos = SeedPositioner(s)
    out: list[Any] = []
    for t, kind, what in arrivals(drive, FRAME, edges, until=until):
        out += pos.add_epoch(what) if kind == "epoch" else pos.add_edge(what, t)  # type: ignore[arg-type]
    return out + pos.flush()


@pytest.mark.parametrize("radius", [15.0, 40.0])
def test_on_a_circle_the_implement_settles_at_its_steady_articulation_inside_the_track(
    radius: float,
) -> None:
    drive = circle_drive(radius, 8.0, 60.0)
    s = settings(hitch=HITCH)
    pos = SeedPositioner(s)
    for _, kind, what in arrivals(drive, FRAME, [], until=55.0):
        if kind == "epoch":
            pos.add_epoch(what)  # type: ignore[arg-type]
    last = pos._samples[-1]
    assert last.heading_deg is not None and last.implement_heading_deg is not None
    articulation = heading_diff(last.implement_heading_deg, last.heading_deg)
    expected = articulation_on_circle_deg(radius, HITCH.behind_antenna_m,
                                          HITCH.outlets_behind_hitch_m)
    assert articulation == pytest.approx(expected, abs=0.05)
    # the middle of the implement (row lateral 0 lies between rows 3 and 4): on the circle
    # of radius sqrt(R_h^2 - L^2) about the centre of the antenna's circle
    edges = [(3, 50.0), (4, 50.0)]
    a, b = hitch_landings(s, drive, edges, until=52.0)
    mid_e, mid_n = (a.east + b.east) / 2, (a.north + b.north) / 2
    pose = drive.pose_at(50.0 + 0.1)
    h = math.radians(pose.heading_deg)
    centre = (pose.east + radius * math.cos(h), pose.north - radius * math.sin(h))
    r_h = math.hypot(radius, HITCH.behind_antenna_m)
    expected_r = math.sqrt(r_h**2 - HITCH.outlets_behind_hitch_m**2)
    assert math.hypot(mid_e - centre[0], mid_n - centre[1]) == pytest.approx(expected_r,
                                                                             abs=0.02)
    # a rigid lever arm of the same length would put it well outside that circle
    rigid_r = math.hypot(radius, HITCH.behind_antenna_m + HITCH.outlets_behind_hitch_m)
    assert rigid_r - expected_r > 0.3


def test_driving_straight_the_implement_is_the_rigid_lever_arm_of_hitch_plus_drawbar() -> None:
    drive = straight(37.0)
    edges = [(1 + k % 6, 1.0 + k * 0.05) for k in range(40)]
    trailed = hitch_landings(settings(hitch=HITCH), drive, edges, until=4.0)
    rigid = hitch_landings(settings(outlet_behind_antenna_m=5.5), drive, edges, until=4.0)
    for a, b in zip(trailed, rigid, strict=True):
        assert math.hypot(a.east - b.east, a.north - b.north) < 0.001


def test_a_hitch_table_needs_both_lengths_in_range() -> None:
    with pytest.raises(ValueError, match="outlets_behind_hitch_m"):
        settings(hitch={"behind_antenna_m": 1.0, "outlets_behind_hitch_m": 0.0})
    with pytest.raises(ValueError, match="behind_antenna_m"):
        settings(hitch={"outlets_behind_hitch_m": 3.0})



def test_a_raised_hitch_swings_the_implement_downhill_by_its_height_on_a_rolled_slope() -> None:
    """The hitch leans with the tractor (0.5 m up: 26 mm at 3°) while the implement rests on
    the ground behind it: the outlets move downhill (to the right for positive roll) by
    height·sin(roll) against a hitch at ground level, and not at all on level ground."""
    drive = straight(37.0)
    edges = [(1 + k % 6, 1.0 + k * 0.05) for k in range(40)]
    low = settings(antenna_height_m=H, attitude_source="dual_antenna", hitch=HITCH)
    raised = low.model_copy(update={"hitch": HITCH.model_copy(update={"height_m": 0.5})})
    right = (math.cos(math.radians(37.0)), -math.sin(math.radians(37.0)))
    for roll, expected in ((3.0, 0.5 * math.sin(math.radians(3.0))), (0.0, 0.0)):
        a = rolled_run(SeedPositioner(low, baseline_offset_deg=90.0), drive, edges, roll)
        b = rolled_run(SeedPositioner(raised, baseline_offset_deg=90.0), drive, edges, roll)
        assert len(a) == len(b) == len(edges)
        for la, lb in zip(a, b, strict=True):
            de, dn = lb.east - la.east, lb.north - la.north
            assert de * right[0] + dn * right[1] == pytest.approx(expected, abs=1e-4)
            assert de * right[1] - dn * right[0] == pytest.approx(0.0, abs=1e-4)


def test_a_hitch_height_out_of_range_names_the_key() -> None:
    with pytest.raises(ValueError, match="height_m"):
        settings(hitch={"behind_antenna_m": 1.0, "outlets_behind_hitch_m": 3.0, "height_m": -0.1})


def test_a_record_of_a_raised_hitch_on_a_slope_repositions_where_it_was_recorded() -> None:
    """``reposition`` (survey calibration, export --reposition) leans the hitch as the
    positioner does: the model a record was made with puts it back where it is."""
    from gateway.recording.positioning.survey import reposition

    drive = straight(37.0)
    edges = [(1 + k % 6, 1.0 + k * 0.05) for k in range(40)]
    s = settings(antenna_height_m=H, attitude_source="dual_antenna",
                 hitch=HITCH.model_copy(update={"height_m": 0.5}))
    out = rolled_run(SeedPositioner(s, baseline_offset_deg=90.0), drive, edges, 3.0)
    assert len(out) == len(edges)
    for la in out:
        e, n, _ = FRAME.to_enu(*reposition(la.drop, s))
        e0, n0, _ = FRAME.to_enu(la.drop.lat, la.drop.lon)
        assert math.hypot(e - e0, n - n0) < 0.002


# ---------------------------------------------------------------- pitch from the track


def climbing_run(pos: SeedPositioner, drive: Drive, edges: list[tuple[int, float]],
                 slope_deg: float, *, fix: str = "rtk_fixed") -> list[Any]:
    """A straight drive up a slope: the ground point rises tan(slope) per metre, the antenna
    stands H up the machine's Z axis (leaning back H·sin(slope)), the antennas side by side
    report no roll (baseline pitch 0)."""
    out: list[Any] = []
    th = math.radians(slope_deg)
    start = drive.pose_at(0.0)
    for t, kind, what in arrivals(drive, FRAME, edges, until=4.0):
        if kind == "edge":
            out += pos.add_edge(what, t)  # type: ignore[arg-type]
            continue
        e: Epoch = what  # type: ignore[assignment]
        pose = drive.pose_at((e.utc - UTC0).total_seconds())
        s = math.hypot(pose.east - start.east, pose.north - start.north)
        de, dn = rotate_offset(RowOffset(H * math.sin(th), 0.0), pose.heading_deg)
        lat, lon = FRAME.to_geodetic(pose.east + de, pose.north + dn)
        base = epoch_from_pose(pose, FRAME)
        out += pos.add_epoch(TiltedEpoch(
            **{**base.__dict__, "t_mono": e.t_mono, "lat": lat, "lon": lon, "fix": fix,
               "alt_m": FRAME.alt0 + s * math.tan(th) + H * math.cos(th)},
            baseline_pitch_deg=0.0))
    return out + pos.flush()


CLIMB_EDGES = [(1 + k % 6, 2.0 + k * 0.013) for k in range(120)]


def climb_errors(out: list[Any], drive: Drive, s: PositioningSection) -> list[float]:
    out_enu = [FRAME.to_enu(la.drop.lat, la.drop.lon) for la in out]
    return [math.hypot(e - te, n - tn)
            for (e, n, _), (row, t) in zip(out_enu, CLIMB_EDGES, strict=True)
            for te, tn in [truth_landing(drive, s, row, t)]]


def test_side_by_side_antennas_climbing_a_slope_get_the_pitch_from_the_track() -> None:
    """2° up the pass: the antenna 2.5 m up leans 87 mm back, which side-by-side antennas
    cannot see; the climb over the last 3 m of track gives the pitch and the seeds land on
    the ground line (the outlets' offsets shortened by cos 2°: under 1 mm)."""
    drive = straight(37.0)
    s = settings(antenna_height_m=H, attitude_source="dual_antenna", pitch_from_track_m=3.0)
    out = climbing_run(SeedPositioner(s, baseline_offset_deg=90.0), drive, CLIMB_EDGES, 2.0)
    assert len(out) == len(CLIMB_EDGES)
    assert max(climb_errors(out, drive, s)) < 0.002
    assert {round(la.drop.pitch_deg, 3) for la in out} == {2.0}
    assert {la.drop.attitude for la in out} == {"dual_antenna"}
    off = s.model_copy(update={"pitch_from_track_m": 0.0})
    blind = climbing_run(SeedPositioner(off, baseline_offset_deg=90.0), drive, CLIMB_EDGES, 2.0)
    assert min(climb_errors(blind, drive, off)) > 0.08
    assert {la.drop.pitch_deg for la in blind} == {None}


def test_pitch_from_the_track_waits_for_its_window_and_ignores_float_heights() -> None:
    drive = straight(37.0)
    s = settings(antenna_height_m=H, attitude_source="dual_antenna", pitch_from_track_m=30.0)
    out = climbing_run(SeedPositioner(s, baseline_offset_deg=90.0), drive, CLIMB_EDGES, 2.0)
    assert {la.drop.pitch_deg for la in out} == {None}  # 30 m of track not driven yet
    s = s.model_copy(update={"pitch_from_track_m": 3.0})
    out = climbing_run(SeedPositioner(s, baseline_offset_deg=90.0), drive, CLIMB_EDGES, 2.0,
                       fix="rtk_float")
    assert {la.drop.pitch_deg for la in out} == {None}
