"""Simulated planter rows: when seeds fall, where they truly land, and the pty they talk on."""

from __future__ import annotations

import asyncio
import itertools
import math
import os
import statistics
import time

import pytest

from gateway.config import parse_config
from gateway.config.recording import PositioningSection
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg, field_passes
from simulator.seed_tubes import PlanterModel, SeedTubeEmulator, landing_point, plan_seeds

EXACT = PlanterModel(
    row_lateral_m=(-1.5, -0.9, -0.3, 0.3, 0.9, 1.5),
    spacing_cv=0.0,
    miss_prob=0.0,
    double_prob=0.0,
    fall_time_sigma_s=0.0,
)


def test_landing_point_is_behind_the_antenna_and_left_rows_are_left() -> None:
    drive = Drive(legs=[Leg(2.0, 0.0)], start_heading_deg=90.0)  # standing, facing east
    e1, n1 = landing_point(drive.pose_at, EXACT, 1, 1.0)  # row 1: 1.5 m left
    e6, n6 = landing_point(drive.pose_at, EXACT, 6, 1.0)  # row 6: 1.5 m right
    assert (e1, n1) == pytest.approx((-1.2, 1.5))  # left of east-facing is north
    assert (e6, n6) == pytest.approx((-1.2, -1.5))


def test_fall_time_follows_paper_c_table_1() -> None:
    assert EXACT.fall_time_s(4.0) == pytest.approx(0.1142)
    assert EXACT.fall_time_s(6.5) == pytest.approx((0.1093 + 0.1082) / 2)
    assert EXACT.fall_time_s(20.0) == pytest.approx(0.1041)


def test_seeds_fall_at_the_set_spacing_along_a_straight_pass() -> None:
    drive = Drive(legs=[Leg(10.0, 8.0)], accel_ms2=100.0)
    seeds = [s for s in plan_seeds(drive, EXACT) if s.row == 3 and s.t_edge > 0.5]  # at speed
    gaps = [math.dist((a.east, a.north), (b.east, b.north)) for a, b in itertools.pairwise(seeds)]
    assert statistics.mean(gaps) == pytest.approx(0.2, abs=0.002)
    assert max(gaps) - min(gaps) < 0.01
    # distance travelled / spacing seeds per row
    assert len(seeds) == pytest.approx(8.0 / 3.6 * 9.5 / 0.2, abs=2)


def test_the_landing_instant_is_the_edge_plus_the_fall_time() -> None:
    drive = Drive(legs=[Leg(5.0, 10.0)], accel_ms2=100.0)
    for s in [s for s in plan_seeds(drive, EXACT) if s.t_edge > 0.5][:20]:
        assert s.t_land - s.t_edge == pytest.approx(EXACT.fall_time_s(10.0), abs=1e-6)
        truth = landing_point(drive.pose_at, EXACT, s.row, s.t_land)
        assert (s.east, s.north) == pytest.approx(truth)


def test_no_seeds_while_raised_or_standing() -> None:
    drive = Drive(legs=[Leg(2.0, 0.0), Leg(4.0, 6.0, raised=True), Leg(4.0, 6.0), Leg(3.0, 0.0)])
    seeds = plan_seeds(drive, EXACT)
    assert seeds
    assert all(not drive.pose_at(s.t_edge).raised for s in seeds)
    assert all(drive.pose_at(s.t_edge).speed_kmh >= 1.0 for s in seeds)
    assert min(s.t_edge for s in seeds) >= 6.0 - 0.01


def test_misses_and_doubles_happen_at_their_rates() -> None:
    model = PlanterModel(miss_prob=0.1, double_prob=0.1, spacing_cv=0.0)
    drive = Drive(legs=[Leg(60.0, 8.0)], accel_ms2=100.0)
    seeds = [s for s in plan_seeds(drive, model, seed=4) if s.row == 1]
    gaps = [math.dist((a.east, a.north), (b.east, b.north)) for a, b in itertools.pairwise(seeds)]
    doubles = sum(g <= 0.1 for g in gaps) / len(gaps)
    misses = sum(g > 0.3 for g in gaps) / len(gaps)
    assert 0.05 < doubles < 0.15
    assert 0.05 < misses < 0.15


def test_bounce_scatters_along_the_furrow_only() -> None:
    drive = Drive(legs=[Leg(20.0, 8.0)], start_heading_deg=0.0, accel_ms2=100.0)
    clean = plan_seeds(drive, EXACT, seed=1)
    bouncy = plan_seeds(drive, PlanterModel(**{**EXACT.__dict__, "bounce_sigma_m": 0.02}), seed=1)
    along = [b.north - c.north for c, b in zip(clean, bouncy, strict=True)]
    across = [b.east - c.east for c, b in zip(clean, bouncy, strict=True)]
    assert 0.01 < statistics.pstdev(along) < 0.03
    assert max(abs(x) for x in across) < 1e-9


def test_a_field_day_covers_every_row() -> None:
    seeds = plan_seeds(field_passes(speeds_kmh=(4.0, 12.0), pass_length_m=20.0))
    assert {s.row for s in seeds} == set(range(1, 7))
    assert [s.t_edge for s in seeds] == sorted(s.t_edge for s in seeds)


def test_a_non_positive_spacing_is_refused() -> None:
    with pytest.raises(ValueError, match="spacing_m must be > 0"):
        plan_seeds(Drive(legs=[Leg(1.0, 5.0)]), PlanterModel(spacing_m=0.0))


async def test_emulator_writes_one_line_per_seed_at_its_edge_time() -> None:
    drive = Drive(legs=[Leg(1.5, 10.0)], accel_ms2=100.0)
    received = bytearray()
    stamps: list[float] = []
    async with SeedTubeEmulator(drive, EXACT) as tubes:
        fd = os.open(tubes.device_path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
        try:
            deadline = time.monotonic() + 4.0
            while not tubes.done and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
                try:
                    chunk = os.read(fd, 4096)
                except BlockingIOError:
                    continue
                received += chunk
                stamps += [time.monotonic()] * chunk.count(b"\n")
            await asyncio.sleep(0.05)
            try:
                chunk = os.read(fd, 4096)
                received += chunk
                stamps += [time.monotonic()] * chunk.count(b"\n")
            except BlockingIOError:
                pass
        finally:
            os.close(fd)
        assert tubes.t0_mono is not None
        t0 = tubes.t0_mono
        truth = tubes.truth
    lines = received.decode().split("\r\n")[:-1]
    assert lines == [f"D,{s.row}" for s in truth]
    assert len(truth) == len(plan_seeds(drive, EXACT)) > 30
    # each line arrived after its edge instant and not absurdly late
    for s, t in zip(truth, stamps, strict=True):
        assert t0 + s.t_edge - 0.001 <= t < t0 + s.t_edge + 0.5


async def test_an_edge_written_late_is_in_the_truth_as_sent_not_as_planned() -> None:
    """A starved host fires the emulator's timer late: the daemon hears of the seed late
    and stamps it then, so the truth must be the seed as sent (edge, landing and place moved
    by the lateness), or the daemon is blamed for the simulator's stall (a fault-matrix
    row once failed on two seeds written 0.17 s late)."""
    drive = Drive(legs=[Leg(1.2, 10.0)], accel_ms2=100.0)
    stall_s = 0.25
    async with SeedTubeEmulator(drive, EXACT) as tubes:
        assert tubes.t0_mono is not None
        await asyncio.sleep(max(0.0, tubes.t0_mono + 0.3 - time.monotonic()))
        time.sleep(stall_s)  # noqa: ASYNC251 - the event loop starved: no timer fires meanwhile
        await asyncio.wait_for(tubes.wait_done(), 10.0)
        truth = tubes.truth
    plan = plan_seeds(drive, EXACT)
    assert len(truth) == len(plan) > 30
    late = [(p, s) for p, s in zip(plan, truth, strict=True) if s.late_s]
    assert tubes.late_writes == len(late)
    assert max(s.late_s for _, s in late) > stall_s - 0.1
    for planned, sent in late:
        assert sent.row == planned.row
        assert sent.t_edge == pytest.approx(planned.t_edge + sent.late_s)
        assert sent.t_land == pytest.approx(planned.t_land + sent.late_s)
        if sent.t_land > drive.duration_s:  # a loaded host: landed after the drive's end
            assert (sent.east, sent.north) == (planned.east, planned.north)
            continue
        east, north = landing_point(drive.pose_at, EXACT, sent.row, sent.t_land)
        assert (sent.east, sent.north) == (pytest.approx(east), pytest.approx(north))
        moved = math.hypot(sent.east - planned.east, sent.north - planned.north)
        assert moved == pytest.approx(10 / 3.6 * sent.late_s, rel=0.02)
    on_time = [s for p, s in zip(plan, truth, strict=True) if not s.late_s]
    assert on_time and all(s in plan for s in on_time)


def test_the_planter_can_be_taken_from_a_daemon_positioning_config() -> None:
    section = PositioningSection(
        outlet_behind_antenna_m=0.9, row_lateral_m=[-0.35, 0.35], target_spacing_m=0.25
    )
    model = PlanterModel.from_positioning(section, miss_prob=0.0)
    assert model.row_lateral_m == (-0.35, 0.35)
    assert model.outlet_behind_antenna_m == 0.9
    assert model.spacing_m == 0.25 and model.miss_prob == 0.0
    assert model.fall_time_table == tuple(section.fall_time_table)


def test_the_default_planter_is_the_one_a_default_daemon_config_describes() -> None:
    """Ground truth and the position model must agree on the outlets, or every seed is
    'wrong' by the difference: the old default planter kept a fixed 3.6 m layout after the
    daemon's default began to follow [machine] (6 rows, 2 m)."""
    assert list(PlanterModel().row_lateral_m) == parse_config({}).positioning.row_lateral_m


async def test_a_simulated_machine_plants_the_rows_its_daemon_config_has() -> None:
    drive = Drive(legs=[Leg(0.2, 0.0), Leg(1.0, 5.0)])
    four_rows = {"machine": {"rows": 4, "working_width_m": 3.0}}
    async with SimulatedMachine(
        drive=drive, with_gnss=True, with_seed_tubes=True, settings_overrides=four_rows
    ) as machine:
        daemon = machine.settings()
        assert daemon.positioning.row_lateral_m == pytest.approx([-1.125, -0.375, 0.375, 1.125])
        assert list(machine.seed_tubes.model.row_lateral_m) == daemon.positioning.row_lateral_m
        # a daemon for another planter than the one whose seeds are simulated is refused
        with pytest.raises(ValueError, match="settings_overrides"):
            machine.settings(machine={"rows": 6})


async def test_injected_junk_reaches_the_line_between_the_seeds() -> None:
    drive = Drive(legs=[Leg(1.0, 0.0)])  # standing: no seed of its own
    async with SeedTubeEmulator(drive, EXACT) as tubes:
        fd = os.open(tubes.device_path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
        try:
            assert tubes.inject(b"\x00junk\r\n") == 7
            await asyncio.sleep(0.05)
            assert os.read(fd, 64) == b"\x00junk\r\n"
        finally:
            os.close(fd)
