"""Rows about the hopper scale (issue 13 §3): the weight transmitter silent, answering values no
working scale reports, or jumping, on one daemon seeding wheat with a drill 8 % off its model.
The daemon first learns its correction from the scale (small noise, short windows: the
evidence comes in a minute); each fault must leave that correction and the motor alone."""

from __future__ import annotations

import asyncio
import json
import math
import random
import time
from pathlib import Path
from typing import Any

from simulator.plant import HopperTruth
from tests.helpers import eventually
from tests.mosquitto import Mosquitto, Subscriber
from tests.reliability.harness import (
    DaemonProcess,
    RowResult,
    Steady,
    TracedMachine,
    dashboard,
    finish_row,
    mqtt_overrides,
    steady_drive,
    steady_duty,
)
from tests.reliability.rows import (
    DUTY_TOLERANCE_PCT,
    HOPPER_BIAS,
    HOPPER_FACTOR_TOLERANCE,
    HOPPER_FAULT_S,
    HOPPER_FROZEN_FAULTS,
    HOPPER_JUMP_KG,
    HOPPER_LEARN_MAX_S,
)

HOPPER_FAULTS = ("silent", "nan", "out_of_range", "jump")


def _latest_state(dash: Subscriber, since: float = 0.0) -> dict[str, Any] | None:
    for t, payload in reversed(dash.timed("state")):
        if t < since:
            break
        try:
            state: dict[str, Any] = json.loads(payload)
        except ValueError:
            continue
        return state
    return None


def _hopper(dash: Subscriber) -> dict[str, Any]:
    state = _latest_state(dash)
    return (state or {}).get("hopper") or {}


def _factors_between(dash: Subscriber, t0: float, t1: float) -> list[float]:
    out = []
    for t, payload in dash.timed("state"):
        if t0 <= t <= t1:
            try:
                hopper = json.loads(payload).get("hopper") or {}
            except ValueError:
                continue
            if "discharge_correction" in hopper:
                out.append(float(hopper["discharge_correction"]))
    return out


def _messages_between(dash: Subscriber, code: str, t0: float, t1: float) -> list[str]:
    out = []
    for t, payload in dash.timed("state"):
        if t0 <= t <= t1:
            try:
                alarms = json.loads(payload)["alarms"]
            except (ValueError, KeyError):
                continue
            out += [a.get("message", "") for a in alarms if a.get("code") == code]
    return out


# how late a state on MQTT may show what the daemon held at the fault's start (a state
# period, 1 s at the default [mqtt] state_hz, plus a loaded host's delay); far below HOPPER_FAULT_S
PUBLISH_LAG_S = 2.0


async def _hopper_fault(machine: TracedMachine, dash: Subscriber, daemon: DaemonProcess,
                        steady: Steady, fault: str) -> RowResult:
    res = RowResult()
    sim, hopper = machine.rs485, machine.hopper
    assert sim is not None and hopper is not None
    scale_id = sim.device_ids["hopper_scale"]
    tb0 = daemon.tracebacks()
    before = _hopper(dash).get("discharge_correction")
    t0 = time.monotonic()
    if fault == "silent":
        sim.set_silent(scale_id, True)
    elif fault == "nan":
        hopper.fault_kg = math.nan
    elif fault == "out_of_range":
        hopper.fault_kg = 1e7  # what a transmitter sends on overload: far beyond capacity
    else:  # a load cell slips: the weight falls by hundreds of kg at once, for a while
        now_kg = hopper.mass_kg(machine.now(), machine.plant.mass_g / 1000.0)
        hopper.fault_kg = now_kg - HOPPER_JUMP_KG
    await asyncio.sleep(HOPPER_FAULT_S)
    sim.set_silent(scale_id, False)
    hopper.fault_kg = None
    t1 = time.monotonic()
    await asyncio.sleep(3.0)
    t2 = time.monotonic()

    during = machine.duty_between(t0, t1)
    lo, hi = steady.low - DUTY_TOLERANCE_PCT, steady.high + DUTY_TOLERANCE_PCT
    res.duty = (f"{min(during, default=0.0):.1f}–{max(during, default=0.0):.1f} "
                f"(steady {steady})")
    res.check(bool(during) and min(during) >= lo and max(during) <= hi,
              f"motor duty {res.duty} left the steady band {lo:.1f}–{hi:.1f} % during the fault "
              "(the daemon must sow on with its correction)")
    factors = _factors_between(dash, t0, t2)
    res.check(before is not None and bool(factors), "no discharge_correction published")
    if fault in HOPPER_FROZEN_FAULTS and factors:
        # The state on MQTT lags the daemon by up to a state period (more on a loaded host): a
        # window the daemon fitted just before the scale went quiet may show after t0. What
        # the row guards against, a window fitted across the silence, can only come after the
        # scale answers again (t1, HOPPER_FAULT_S later), so the baseline is the correction
        # shown PUBLISH_LAG_S into the fault.
        settled = _factors_between(dash, t0, t0 + PUBLISH_LAG_S)
        if settled:
            before = settled[-1]
        factors = _factors_between(dash, t0 + PUBLISH_LAG_S, t2) or factors
    if before is not None and factors:
        worst = max(factors, key=lambda f: abs(f - before))
        res.recovery = f"x{before:.4f} -> x{worst:.4f}"
        if fault in HOPPER_FROZEN_FAULTS:  # no usable reading: nothing may be learnt
            res.check(worst == before,
                      f"the correction moved from x{before:.4f} to x{worst:.4f} while the scale "
                      "gave no usable reading (it must stay frozen)")
        else:
            res.check(abs(worst - before) <= HOPPER_FACTOR_TOLERANCE,
                      f"the correction moved from x{before:.4f} to x{worst:.4f} during the "
                      f"fault (allowed ±{HOPPER_FACTOR_TOLERANCE:g})")
    alarms = dash.alarms_between(t0, t1 + 1.0)
    wanted = {"silent": "hopper_scale.unavailable", "nan": "hopper_scale.bad_reading",
              "out_of_range": "hopper_scale.bad_reading", "jump": "hopper_scale.jump"}[fault]
    res.check(wanted in alarms, f"{wanted} not published (seen: {sorted(alarms)})")
    if wanted == "hopper_scale.bad_reading":
        msgs = _messages_between(dash, wanted, t0, t1 + 1.0)
        counts = [int(m.split(" readings rejected")[0].rsplit(" ", 1)[-1])
                  for m in msgs if " readings rejected" in m]
        res.check(bool(counts) and max(counts) >= 2,
                  f"the rejected readings are not counted in the alarm (messages: {msgs[-1:]})")
        res.notes.append(f"rejected readings counted: {max(counts, default=0)}")
    state = _latest_state(dash, since=t2 - 1.0) or {}
    still = {a["code"] for a in state.get("alarms", [])}
    if fault != "jump":  # the jump alarm stays until a window is fitted after it
        res.check(wanted not in still, f"{wanted} still active 3 s after the scale recovered")
    res.check(daemon.running, "daemon exited")
    res.notes.append(f"alarms: {', '.join(sorted(alarms)) or 'none'}")
    finish_row(res, daemon, tb0)
    return res


async def group_hopper(tmp: Path) -> dict[str, RowResult]:
    out: dict[str, RowResult] = {}
    machine = TracedMachine(
        crop="wheat",
        discharge_bias=HOPPER_BIAS,
        drive=steady_drive(kmh=5.0),
        hopper=HopperTruth(initial_kg=500.0, noise_kg=0.05, rng=random.Random(13)),
        settings_overrides={"hopper_scale": {"window_s": 10.0, "data_type": "float32",
                                             "scale": 1000.0}},
    )
    with Mosquitto() as broker:
        async with dashboard(broker.port) as dash, machine:
            cfg = machine.write_config(tmp / "sowgate.toml", rs485={"poll_hz": 10.0},
                                       **mqtt_overrides(broker.port))
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: machine.motor_pct() > 0.0, 30.0, "metering")
                await eventually(lambda: bool(_hopper(dash).get("correction_applied")),
                                 HOPPER_LEARN_MAX_S, "the hopper correction applied")
                await asyncio.sleep(5.0)  # the duty settles on the corrected model
                steady = await steady_duty(machine, 5.0)
                learnt = _hopper(dash).get("discharge_correction")
                for fault in HOPPER_FAULTS:
                    res = await _hopper_fault(machine, dash, daemon, steady, fault)
                    res.notes.append(f"correction learnt before the faults: x{learnt} "
                                     f"(drill +{HOPPER_BIAS:.0%} off its model)")
                    out[f"hopper_scale_{fault}"] = res
            finally:
                await daemon.close()
    return out
