"""Simulated paper B controller + hydraulic motor, and the ISOBUS tractor, on a virtual bus."""

from __future__ import annotations

import asyncio
import itertools
import time
import uuid
from collections.abc import AsyncIterator

import pytest

from drivers.backoff import Backoff
from drivers.can_bus import CanBus, IsobusListener, MeteringCanLink
from gateway.metering.isobus import TractorInputs
from protocol.can_metering import FaultCode, MeterStatus
from protocol.isobus import InWork
from simulator.can_pid import (
    PAPER_B_KP,
    PAPER_B_TD_S,
    PAPER_B_TI_S,
    MeteringControllerSim,
    MeterPlant,
    TractorSimulator,
)
from tests.helpers import eventually


def commanded(plant: MeterPlant, rpm: float, seconds: float, period: float = 0.1) -> None:
    """Advance while a terminal keeps commanding ``rpm`` every ``period`` (like the CAN link)."""
    for i in range(round(seconds / period)):
        plant.command(rpm, True, i % 256)
        plant.advance(period)


def test_plant_uses_paper_b_gains_by_default() -> None:
    p = MeterPlant(grams_per_rev=10.0)
    assert (p.kp, p.ti_s, p.td_s) == (PAPER_B_KP, PAPER_B_TI_S, PAPER_B_TD_S) == (0.2, 0.15, 0.15)


def test_pid_brings_the_shaft_to_target_within_5_percent_in_under_3_s() -> None:
    p = MeterPlant(grams_per_rev=16.97, outlets=10)
    commanded(p, 40.0, 2.5)
    assert p.rpm == pytest.approx(40.0, rel=0.05)
    commanded(p, 40.0, 5.0)
    assert p.rpm == pytest.approx(40.0, rel=0.002)  # integral action: no steady-state error


def test_delivered_mass_is_grams_per_rev_times_revolutions() -> None:
    p = MeterPlant(grams_per_rev=29.31, outlets=1)
    commanded(p, 30.0, 3.0)
    m0, r0 = p.mass_g, p.revs
    commanded(p, 30.0, 60.0)
    assert (p.mass_g - m0) / (p.revs - r0) == pytest.approx(29.31, rel=0.01)
    assert p.revs - r0 == pytest.approx(30.0, rel=0.01)  # 30 r/min for a minute


def test_grams_per_turn_fall_with_shaft_speed_and_move_with_the_lot() -> None:
    """Issue 25's truth: g/rev falls by ``fill_fall`` from 10 to 60 r/min (a power law, not
    the controller's piecewise cubic) and scales with the seed lot."""
    p = MeterPlant(grams_per_rev=16.97, outlets=10, fill_fall=0.2, fill_shape=0.7)
    assert p.per_rev_g(10.0) == pytest.approx(16.97)
    assert p.per_rev_g(60.0) == pytest.approx(16.97 * 0.8)
    mids = [p.per_rev_g(n) for n in (20.0, 30.0, 40.0, 50.0)]
    assert all(b < a for a, b in itertools.pairwise(mids))
    late = MeterPlant(grams_per_rev=16.97, fill_fall=0.2, fill_shape=1.6)
    assert late.per_rev_g(30.0) > p.per_rev_g(30.0)  # the shape moves where it falls
    for rpm in (15.0, 55.0):
        q = MeterPlant(grams_per_rev=16.97, outlets=1, fill_fall=0.2, fill_shape=0.7,
                       lot_factor=1.03, delivery_noise_pct=0.0, pulsation_pct=0.0)
        commanded(q, rpm, 3.0)
        m0, r0 = q.mass_g, q.revs
        commanded(q, rpm, 30.0)
        assert (q.mass_g - m0) / (q.revs - r0) == pytest.approx(
            1.03 * p.per_rev_g(rpm), rel=0.005)


def test_a_knee_keeps_the_cells_full_up_to_it_then_the_change_runs_to_60_rpm() -> None:
    """bench_multichannel's drawn meters: g/rev flat up to ``fill_knee_rpm``, the whole change
    between it and 60 r/min (so a straight line from 10 to 60 r/min misses it); a knee at or
    below 10 r/min is the plain power law."""
    k = MeterPlant(grams_per_rev=11.2, fill_fall=0.15, fill_shape=1.2, fill_knee_rpm=30.0)
    assert k.per_rev_g(12.0) == k.per_rev_g(30.0) == pytest.approx(11.2)
    assert k.per_rev_g(60.0) == pytest.approx(11.2 * 0.85)
    assert k.per_rev_g(45.0) < 11.2
    plain = MeterPlant(grams_per_rev=11.2, fill_fall=0.15, fill_shape=1.2)
    assert plain.per_rev_g(30.0) < k.per_rev_g(30.0)
    rise = MeterPlant(grams_per_rev=11.2, fill_fall=-0.05, fill_knee_rpm=20.0)
    assert rise.per_rev_g(60.0) == pytest.approx(11.2 * 1.05)


def test_a_5_ms_cycle_still_regulates() -> None:
    p = MeterPlant(grams_per_rev=16.97, outlets=10, inner_dt_s=0.005)
    commanded(p, 40.0, 5.0)
    assert p.rpm == pytest.approx(40.0, rel=0.005)


def test_controller_stops_the_shaft_when_commands_stop() -> None:
    p = MeterPlant(grams_per_rev=10.0)
    commanded(p, 30.0, 2.0)
    p.advance(2.0)
    assert p.rpm < 1.0
    assert p.status(1).fault is FaultCode.COMMAND_TIMEOUT


def test_stall_is_detected_and_reported() -> None:
    p = MeterPlant(grams_per_rev=10.0)
    p.stall = True
    commanded(p, 30.0, 1.5)
    st = p.status(2)
    assert st.stalled and st.fault is FaultCode.STALL and st.measured_rpm < 0.5


def test_injected_fault_code_stops_the_shaft() -> None:
    p = MeterPlant(grams_per_rev=10.0)
    commanded(p, 30.0, 2.0)
    p.fault_code = FaultCode.OVERPRESSURE
    commanded(p, 30.0, 1.0)
    assert p.rpm < 1.0 and p.status(1).fault is FaultCode.OVERPRESSURE


@pytest.fixture
async def buses() -> AsyncIterator[tuple[CanBus, CanBus]]:
    ch = f"sim-{uuid.uuid4().hex[:8]}"
    fast = Backoff(initial_s=0.01, cap_s=0.05)
    async with CanBus("virtual", ch, backoff=fast) as a, CanBus("virtual", ch, backoff=fast) as b:
        yield a, b


async def test_simulated_controller_follows_targets_sent_over_can(
    buses: tuple[CanBus, CanBus],
) -> None:
    """End to end on the virtual bus: link commands 30 r/min, status frames report it."""
    terminal_bus, sim_bus = buses
    sim = MeteringControllerSim(sim_bus, {1: MeterPlant(16.97, outlets=10)}, status_hz=20,
                                time_scale=2.0)
    link = MeteringCanLink(terminal_bus, [1], command_hz=20)
    statuses: list[tuple[MeterStatus, float]] = []
    link.set_target(1, 30.0)
    async with asyncio.TaskGroup() as tg:
        t_sim = tg.create_task(sim.run(), name="sim")
        t_link = tg.create_task(link.run(lambda s, t: statuses.append((s, t))), name="link")
        await eventually(
            lambda: statuses and abs(statuses[-1][0].measured_rpm - 30.0) < 0.6, 5.0, "30 rpm"
        )
        t_sim.cancel()
        t_link.cancel()
    assert statuses, "no status frames"
    assert statuses[-1][0].measured_rpm == pytest.approx(30.0, abs=0.6)
    assert statuses[-1][0].enabled
    times = [t for _, t in statuses]
    rate = (len(times) - 1) / (times[-1] - times[0])
    assert 8.0 <= rate <= 25.0  # 10-20 Hz with scheduling slack


async def test_silent_controller_sends_nothing(buses: tuple[CanBus, CanBus]) -> None:
    terminal_bus, sim_bus = buses
    plant = MeterPlant(10.0)
    plant.silent = True
    sim = MeteringControllerSim(sim_bus, {2: plant}, status_hz=20)
    task = asyncio.create_task(sim.run(), name="sim")
    try:
        assert await terminal_bus.recv(max_wait_s=0.4) is None
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_tractor_simulator_feeds_the_isobus_listener(buses: tuple[CanBus, CanBus]) -> None:
    implement_bus, tractor_bus = buses
    tractor = TractorSimulator(tractor_bus, speed_kmh=5.0, hitch_pct=10.0,
                               in_work=InWork.IN_WORK)
    lis = IsobusListener(implement_bus)
    inputs = TractorInputs(lis)  # the daemon's reading of them: priority, 300 ms staleness
    async with asyncio.TaskGroup() as tg:
        t1 = tg.create_task(tractor.run(), name="tractor")
        t2 = tg.create_task(lis.run(), name="isobus")
        await eventually(
            lambda: inputs.speed(time.monotonic()) is not None
            and inputs.working(time.monotonic()) is not None,
            2.0, "speed and work state from the tractor", interval=0.02,
        )
        now = time.monotonic()
        speed, working = inputs.speed(now), inputs.working(now)
        tractor.silent = True
        await asyncio.sleep(0.5)
        stale = inputs.speed(time.monotonic())
        t1.cancel()
        t2.cancel()
    assert speed is not None and speed.source == "machine_selected"
    assert speed.speed_kmh == pytest.approx(5.0, abs=0.004)
    assert working is True
    assert stale is None
