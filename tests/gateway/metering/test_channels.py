"""Multi-channel metering: rate -> shaft speed, alarms, and the component on a virtual bus."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import pytest

from drivers.can_bus import CanBus
from gateway.config import Settings, parse_config
from gateway.core.errors import ConfigError, RateError
from gateway.metering.channels import (
    ChannelAlarm,
    ChannelSupervisor,
    MeteringComponent,
    rate_from_shaft,
    target_shaft_rpm,
)
from gateway.metering.prescription import AsAppliedLog, Pose, load_prescription
from simulator.can_pid import MeteringControllerSim, MeterPlant
from tests.helpers import eventually

PAPER_B = [("shallow", 1, 150.0, 16.97), ("deep", 2, 300.0, 29.31), ("seed", 3, 225.0, 11.20)]


def settings(**can: Any) -> Settings:
    return parse_config({
        "machine": {"working_width_m": 2.55},
        "can": {"enabled": True, "interface": "virtual", "channel": "unused", **can},
        "channel": [
            {"name": n, "product": n, "node_id": node, "target_rate_kg_ha": rate,
             "grams_per_rev": g, "outlets": 10, "drive": "can_pid"}
            for n, node, rate, g in PAPER_B
        ],
    })


def test_shaft_speed_for_paper_b_shallow_fertiliser() -> None:
    """150 kg/ha at 5 km/h over 2.55 m with 10 outlets x 16.97 g/rev."""
    n = target_shaft_rpm(150, 5.0, 2.55, 169.7)
    assert n == pytest.approx(150 * 2.55 * 5.0 / (0.6 * 169.7))
    assert n == pytest.approx(18.78, abs=0.01)
    assert rate_from_shaft(n, 5.0, 2.55, 169.7) == pytest.approx(150)


@pytest.mark.parametrize("n", [10.0, 20.0, 45.0])
@pytest.mark.parametrize("v_mps", [1.0, 1.389, 2.5])
def test_general_relation_reproduces_paper_b_constant_for_the_sown_width(n: float,
                                                                        v_mps: float) -> None:
    """G = 100n/(9v) (15 g/rev x 10 rows) holds for B = 2.25 m; 2.55 m gives 9.80 n/v."""
    assert rate_from_shaft(n, v_mps * 3.6, 2.25, 150.0) == pytest.approx(100 * n / (9 * v_mps))
    assert rate_from_shaft(n, v_mps * 3.6, 2.55, 150.0) == pytest.approx(9.804 * n / v_mps,
                                                                         rel=1e-3)


def test_standing_still_has_no_applied_rate_and_bad_inputs_raise() -> None:
    assert rate_from_shaft(20, 0.0, 2.55, 150) is None
    with pytest.raises(RateError):
        target_shaft_rpm(100, 5, 2.55, 0)
    with pytest.raises(RateError):
        target_shaft_rpm(-1, 5, 2.55, 10)


def sup() -> ChannelSupervisor:
    return ChannelSupervisor(["a", "b"], feedback_timeout_s=1.0, off_target_pct=5.0,
                             off_target_s=3.0, start=0.0)


def kinds(alarms: list[ChannelAlarm]) -> set[tuple[str, str, bool]]:
    return {(a.channel, a.kind, a.active) for a in alarms}


def test_missing_feedback_for_more_than_1_s_raises_a_channel_alarm() -> None:
    s = sup()
    s.feedback("a", 0.0, 0.5)
    s.feedback("b", 0.0, 0.5)
    assert s.evaluate(1.4) == []
    s.feedback("b", 0.0, 1.4)
    assert kinds(s.evaluate(1.6)) == {("a", "feedback_lost", True)}
    assert s.evaluate(1.7) == []  # reported once
    s.feedback("a", 0.0, 1.8)
    assert ("a", "feedback_lost", False) in kinds(s.evaluate(1.8))


def test_a_steady_shortfall_beyond_5_percent_alarms_once_a_full_window_shows_it() -> None:
    """6 % low against a steady target: the window opens 1 s after the start
    (SETTLE_AFTER_START_S), is full 3.3 s later (off_target_s + RESPONSE_LAG_S) and the error
    is held 1 s (OFF_TARGET_HOLD_S) before it alarms; back on target, the window clears it."""
    s = ChannelSupervisor(["a"], start=0.0)
    s.command("a", 20.0, 0.0)
    alarms: list[ChannelAlarm] = []
    t = 0.0
    while t < 5.2:
        t = round(t + 0.1, 1)
        s.feedback("a", 18.8, t)
        alarms += s.evaluate(t)
    assert alarms == []
    for _ in range(4):
        t = round(t + 0.1, 1)
        s.feedback("a", 18.8, t)
        alarms += s.evaluate(t)
    assert kinds(alarms) == {("a", "off_target", True)}
    assert "-6%" in alarms[0].message
    cleared: list[ChannelAlarm] = []
    for _ in range(40):  # on target: the shortfall leaves the 3 s window
        t = round(t + 0.1, 1)
        s.feedback("a", 20.0, t)
        cleared += s.evaluate(t)
    assert kinds(cleared) == {("a", "off_target", False)}


def test_within_5_percent_never_alarms_and_a_step_followed_within_its_lag_costs_nothing(
) -> None:
    s = ChannelSupervisor(["a"], start=0.0)
    s.command("a", 20.0, 0.0)
    for i in range(1, 60):
        s.feedback("a", 19.1, i * 0.1)  # 4.5 % low
        assert s.evaluate(i * 0.1) == []
    s = ChannelSupervisor(["a"], start=0.0)
    s.command("a", 20.0, 0.0)
    for i in range(1, 60):
        s.feedback("a", 20.0, i * 0.1)
        assert s.evaluate(i * 0.1) == []
    s.command("a", 40.0, 6.0)  # the shaft follows a 100 % step within RESPONSE_LAG_S
    for i in range(1, 60):
        t = 6.0 + i * 0.1
        s.feedback("a", 20.0 if i <= 2 else 40.0, t)
        assert s.evaluate(t) == []


def test_turning_while_told_to_stop_alarms_after_off_target_s() -> None:
    s = ChannelSupervisor(["a"], start=0.0)
    s.command("a", 0.0, 0.0)
    alarms: list[ChannelAlarm] = []
    for i in range(1, 45):
        s.feedback("a", 8.0, i * 0.1)
        alarms += s.evaluate(i * 0.1)
    assert kinds(alarms) == {("a", "off_target", True)}
    assert "commanded to stop" in alarms[0].message


# The issue-20 cases, judged against the simulated controller's own PID, valve and motor
# (simulator.can_pid.MeterPlant): the target follows a radar with 3 % noise, a new value every
# 0.3 s, commands at 10 Hz and feedback at 20 Hz, as on the bus.
RADAR_NOISE = 0.03
GRAMS_PER_REV = 200.0  # per revolution of the shaft, all outlets: 30 r/min at 8 km/h
WIDTH_M = 3.0
RATE_KG_HA = 150.0


def drive_channel(plant: MeterPlant, seconds: float, *, speed_kmh: float = 8.0,
                  accelerate_to_kmh: float | None = None,
                  max_rpm: float = 60.0) -> list[ChannelAlarm]:
    """``seconds`` of the channel with a noisy, moving target; every alarm change seen."""
    import random

    rng = random.Random(3)
    sup = ChannelSupervisor(["seed"], start=0.0, max_rpm={"seed": max_rpm})
    alarms: list[ChannelAlarm] = []
    radar = speed_kmh
    dt = 0.05
    for step in range(round(seconds / dt)):
        t = round((step + 1) * dt, 3)
        true_kmh = speed_kmh
        if accelerate_to_kmh is not None:  # 1 km/h a second from 20 s on
            true_kmh = min(accelerate_to_kmh, speed_kmh + max(0.0, t - 20.0))
        if step % 6 == 0:  # the radar's new reading every 0.3 s
            radar = true_kmh * (1 + rng.gauss(0.0, RADAR_NOISE))
        if step % 2 == 0:  # commands at 10 Hz
            target = target_shaft_rpm(RATE_KG_HA, radar, WIDTH_M, GRAMS_PER_REV)
            plant.command(target, True, step)
            sup.command("seed", target, t)
        plant.advance(dt)
        status = plant.status(1)
        sup.feedback("seed", status.measured_rpm, t)
        alarms += sup.evaluate(t)
    return alarms


def test_a_healthy_shaft_under_a_noisy_moving_target_never_alarms() -> None:
    assert drive_channel(MeterPlant(GRAMS_PER_REV), 60.0) == []
    assert drive_channel(MeterPlant(GRAMS_PER_REV), 40.0, speed_kmh=4.0,
                         accelerate_to_kmh=12.0) == []


def test_a_shaft_held_at_55_percent_of_a_moving_target_alarms_off_target() -> None:
    """Issue 20 item 1: ~52 g/s delivered against 100 g/s asked, for 15 s, raised nothing
    because the radar's noise restarted the timer on every poll."""
    alarms = drive_channel(MeterPlant(GRAMS_PER_REV, held_fraction=0.55), 15.0)
    raised = [a for a in alarms if a.active]
    assert [a.kind for a in raised] == ["off_target"]
    assert raised[0].since <= 1.0 + 3.0 + 1.0 + 0.5  # settle + window + hold, one poll late
    assert "-45%" in raised[0].message


def test_a_node_reporting_ten_times_its_speed_alarms_impossible_and_off_target() -> None:
    """Issue 20 item 1: a node reporting 10x its speed for 10 s raised nothing."""
    alarms = drive_channel(MeterPlant(GRAMS_PER_REV, report_scale=10.0), 10.0)
    raised = {a.kind: a for a in alarms if a.active}
    assert set(raised) == {"impossible_speed", "off_target"}
    assert raised["impossible_speed"].since <= 1.0
    assert "max_shaft_rpm 60" in raised["impossible_speed"].message


def test_controller_fault_is_its_own_alarm() -> None:
    s = ChannelSupervisor(["a"], start=0.0)
    s.feedback("a", 0.0, 0.1, fault="stall")
    assert kinds(s.evaluate(0.1)) == {("a", "controller_fault", True)}


class Inputs:
    def __init__(self) -> None:
        self.speed: float | None = 5.0
        self.working = True
        self.pose: Pose | None = None
        self.alarms: list[ChannelAlarm] = []


def component(inputs: Inputs, s: Settings | None = None, **kw: Any) -> MeteringComponent:
    return MeteringComponent(
        s or settings(), lambda: inputs.speed, lambda: inputs.working, lambda: inputs.pose,
        inputs.alarms.append, **kw,
    )


def test_component_targets_every_channel_from_speed_and_rate() -> None:
    inp = Inputs()
    c = component(inp)
    targets = c.tick(0.0)
    for name, _node, rate, g in PAPER_B:
        assert targets[name] == pytest.approx(target_shaft_rpm(rate, 5.0, 2.55, g * 10))


def test_raised_implement_stops_every_channel_even_while_moving() -> None:
    inp = Inputs()
    c = component(inp)
    assert all(v > 0 for v in c.tick(0.0).values())
    inp.working = False
    assert set(c.tick(0.1).values()) == {0.0}
    inp.working, inp.speed = True, None  # no speed: stop too
    assert set(c.tick(0.2).values()) == {0.0}


def test_too_fast_clamps_to_max_shaft_speed_and_raises_an_alarm() -> None:
    inp = Inputs()
    inp.speed = 10.0  # seed needs 85 r/min > 60; the fertilisers stay below
    c = component(inp)
    targets = c.tick(0.0)
    assert targets["seed"] == 60.0  # max_shaft_rpm default
    too_fast = [a for a in inp.alarms if a.kind == "too_fast"]
    assert {a.channel for a in too_fast} == {"seed"}
    assert "max" in too_fast[0].message and "km/h" in too_fast[0].message


def test_prescription_sets_the_channel_rate_with_look_ahead(tmp_path: Path) -> None:
    """A zone starting 5 m ahead is applied already once it is within the look-ahead."""
    deg = 1 / 111_320
    zone = [[-1.0, 5 * deg], [1.0, 5 * deg], [1.0, 100 * deg], [-1.0, 100 * deg], [-1.0, 5 * deg]]
    mp = tmp_path / "rx.geojson"
    mp.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [zone]},
         "properties": {"seed_rate": 180.0}}]}))
    raw = settings().model_dump()
    raw["prescription"] = {"enabled": True, "path": str(mp), "lookahead_s": 2.0}
    raw["channel"][2]["prescription_attribute"] = "seed_rate"
    s = parse_config(raw)
    inp = Inputs()
    log = AsAppliedLog()
    c = component(inp, s, as_applied=log, prescription=load_prescription(s))
    inp.pose = Pose(0.0, 0.0, 0.0, 5.0)  # 2 s at 5 km/h = 2.8 m ahead: still outside
    c.tick(0.0)
    assert c.state["seed"].target_rate_kg_ha == 225.0  # channel default
    inp.pose = Pose(0.0, 2.5 * deg, 0.0, 5.0)  # 2.5 + 2.8 m > 5 m: inside
    c.tick(1.0)
    assert c.state["seed"].target_rate_kg_ha == 180.0
    assert c.state["shallow"].target_rate_kg_ha == 150.0  # no attribute: fixed rate
    assert [r.target_kg_ha for r in log.rows if r.channel == "seed"] == [225.0, 180.0]


async def test_component_runs_channels_against_simulated_controllers() -> None:
    """Real CAN (virtual) + the PID simulator: shafts reach target; a silent node alarms."""
    ch = f"comp-{uuid.uuid4().hex[:8]}"
    s = settings(channel=ch, command_hz=20)
    inp = Inputs()
    comp = component(inp, s)
    plants = {node: MeterPlant(g, outlets=10) for _n, node, _r, g in PAPER_B}
    async with CanBus("virtual", ch) as sim_bus:
        sim = MeteringControllerSim(sim_bus, plants, status_hz=20, time_scale=2.0)
        async with asyncio.TaskGroup() as tg:
            t_sim = tg.create_task(sim.run(), name="sim")
            t_comp = tg.create_task(comp.run(), name="metering")
            # settled: every shaft within 3 % of its target in 5 status readings in a row
            # (not a fixed 6 s: a loaded machine only slows the simulated plant's approach)
            settled = 0

            def on_target() -> bool:
                nonlocal settled
                snap = comp.status().channels
                within = bool(snap) and all(
                    v.measured_rpm is not None
                    and abs(v.measured_rpm - v.target_rpm) < 0.03 * v.target_rpm
                    for v in snap.values()
                )
                settled = settled + 1 if within else 0
                return settled >= 5

            await eventually(on_target, 60.0, "every shaft on its target",
                             interval=0.1, unless=t_comp,
                             detail=lambda: comp.status().channels)
            good = comp.status()
            plants[2].silent = True
            await eventually(
                lambda: any(a.kind == "feedback_lost" and a.active for a in inp.alarms),
                30.0, "the silent node's feedback_lost alarm", unless=t_comp)
            t_comp.cancel()
            await asyncio.sleep(0.1)
            t_sim.cancel()
    for name, v in good.channels.items():
        assert v.measured_rpm == pytest.approx(v.target_rpm, rel=0.03), name
        assert v.applied_rate_kg_ha == pytest.approx(v.target_rate_kg_ha, rel=0.03)
    assert not [a for a in inp.alarms if a.kind != "feedback_lost"]
    lost = [a for a in inp.alarms if a.kind == "feedback_lost" and a.active]
    assert [a.channel for a in lost] == ["deep"]
    assert all(not p.enabled for p in plants.values())  # stopped on shutdown


def test_can_channel_needs_an_addressable_node_id() -> None:
    raw = settings().model_dump()
    raw["channel"][0]["node_id"] = 0
    with pytest.raises(ConfigError, match=r"channel\[0\].*node_id 1\.\.15"):
        parse_config(raw)


def test_can_channels_without_the_can_bus_enabled_alarm_instead_of_doing_nothing(
    tmp_path: Path,
) -> None:
    from gateway.app.daemon import Daemon

    rx = tmp_path / "rx.geojson"  # the map must exist (start check); never read without a drive
    rx.write_text('{"type": "FeatureCollection", "features": []}')
    settings = parse_config({
        "hmi": {"enabled": False},
        "channel": [{"name": "deep", "target_rate_kg_ha": 300.0}],
        "prescription": {"enabled": True, "path": str(tmp_path / "rx.geojson")},
    })
    daemon = Daemon(settings, tmp_path / "state")
    active = {a.code: a for a in daemon.alarms.active}
    assert active["channel.can_disabled"].severity == "critical"
    assert "deep" in active["channel.can_disabled"].message
    assert "prescription.unused" in active
    assert daemon.parts.metering is None


def test_operator_changes_a_channel_rate_through_the_one_command_path(tmp_path: Path) -> None:
    from gateway.app.daemon import Daemon
    from gateway.core import commands as cmd
    from gateway.core.errors import CommandError

    settings = parse_config({
        "hmi": {"enabled": False},
        "can": {"enabled": True, "interface": "virtual", "channel": "unused"},
        "channel": [
            {"name": "deep", "target_rate_kg_ha": 300.0, "node_id": 2},
            {"name": "seed", "drive": "pwm_modbus", "product": "wheat",
             "target_rate_kg_ha": 200.0},
        ],
    })
    daemon = Daemon(settings, tmp_path / "state")
    metering = daemon.parts.metering
    deep = metering.channels[0]
    assert metering.target_rate(deep, None) == 300.0
    assert daemon.execute(cmd.SetChannelRate("deep", 280.0), "mqtt") == "deep 280 kg/ha"
    assert metering.target_rate(deep, None) == 280.0
    daemon.execute(cmd.SetChannelRate("seed", 210.0), "mqtt")  # paper A's motor: crop rate
    assert (daemon.controller.crop, daemon.controller.rate_kg_ha) == ("wheat", 210.0)
    with pytest.raises(CommandError, match="outside 120-225"):
        daemon.execute(cmd.SetChannelRate("seed", 300.0), "mqtt")
    with pytest.raises(CommandError, match="unknown channel 'shallow'; known: deep, seed"):
        daemon.execute(cmd.SetChannelRate("shallow", 100.0), "mqtt")
    with pytest.raises(CommandError, match=r"0\.\.2000"):
        metering.set_rate("deep", -1.0)
    assert metering.target_rate(deep, None) == 280.0  # a refused command changes nothing
