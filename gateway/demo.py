"""``sowgate demo``: the daemon driving the simulated machine, with a scripted operator.

With ``channels=True`` paper B's three metering channels (shallow and deep fertiliser, seed)
run as well: simulated PID controllers and hydraulic motors (``simulator.can_pid``) answer on
a python-can ``virtual`` bus, and the daemon drives them through the DBC like real ones.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.tasks import cancel_and_wait
from gateway.daemon import Daemon
from simulator.machine import STARTUP_TRANSIENT_S

if TYPE_CHECKING:
    from simulator.machine import Truth

log = logging.getLogger(__name__)

# paper B: targets at 5 km/h (kg/ha) and the weighed displacement per outlet (g/rev)
PAPER_B_CHANNELS = (
    ("shallow", "fertiliser", 150.0, 16.97),
    ("deep", "fertiliser", 300.0, 29.31),
    ("seed", "wheat", 225.0, 11.20),
)
PAPER_B_OUTLETS = 10  # 10 rows


MIN_MEASURED_M = 1.0  # sown before the demo shows an applied rate: less is no measurement


def _error_pct(applied: float | None, target: float) -> float | None:
    return None if applied is None or target <= 0 else (applied / target - 1.0) * 100.0


def _pct(value: float) -> str:
    return f"{round(value, 2) + 0.0:+.2f} %"  # + 0.0: never print "-0.00 %"


def truth_report(truth: Truth, target_kg_ha: float) -> dict[str, Any]:
    """The simulator's ground truth as the demo shows it: the whole-run applied rate and, apart,
    the rate after each pass's start-up transient (see ``simulator.machine.Truth``).

    A rate is None until ``MIN_MEASURED_M`` has been sown: over the first centimetres off
    standstill nothing has left the meter yet, and the view showed "rate error -100.00 %"
    for what was no measurement at all.
    """
    applied = truth.applied_kg_ha() if truth.sown_m >= MIN_MEASURED_M else None
    settled = truth.settled_kg_ha() if truth.settled_m >= MIN_MEASURED_M else None
    return {
        "sown_m": truth.sown_m,
        "applied_kg_ha": applied,
        "rate_error_pct": _error_pct(applied, target_kg_ha),
        "settled_m": truth.settled_m,
        "settled_kg_ha": settled,
        "settled_rate_error_pct": _error_pct(settled, target_kg_ha),
    }


def summary(report: dict[str, Any], target_kg_ha: float) -> str:
    """The closing line of ``sowgate demo``.

    Why not just the whole-run error: a drive starts from standstill, and for the first seconds
    of every pass the speed filter and the motor lag the tractor, so a demo of a few seconds
    reports -10 % or worse although the controller holds the rate once under way (and
    printed "+0.00 %" when nothing had been sown at all). The line says how much was sown and
    keeps the start-up part apart, so neither figure is read out of context.
    """
    applied = report["applied_kg_ha"]
    if applied is None:
        return (
            "demo finished: nothing sown yet (the simulated tractor had not started a pass); "
            "run longer, e.g. --duration 60"
        )
    whole = (
        f"{report['sown_m']:.1f} m sown, applied {applied:.2f} kg/ha "
        f"(target {target_kg_ha:g}, error {_pct(report['rate_error_pct'])})"
    )
    settled = report["settled_kg_ha"]
    if settled is None:
        return (
            f"demo finished: {whole}, all of it in the start-up of a pass (speed filter and "
            "motor catching up from standstill), so not representative; "
            "run longer, e.g. --duration 60"
        )
    return (
        f"demo finished: {whole}; after the first {STARTUP_TRANSIENT_S:g} s of each pass "
        f"{settled:.2f} kg/ha (error {_pct(report['settled_rate_error_pct'])} "
        f"over {report['settled_m']:.1f} m)"
    )


def paper_b_channel_config(can_channel: str) -> dict[str, Any]:
    """Config overrides for the three CAN channels on the virtual bus ``can_channel``."""
    return {
        "can": {"enabled": True, "interface": "virtual", "channel": can_channel},
        "channel": [
            {
                "name": name,
                "product": product,
                "target_rate_kg_ha": rate,
                "drive": "can_pid",
                "node_id": node,
                "grams_per_rev": g_per_rev,
                "outlets": PAPER_B_OUTLETS,
            }
            for node, (name, product, rate, g_per_rev) in enumerate(PAPER_B_CHANNELS, start=1)
        ],
    }


async def run_demo(
    duration_s: float | None, tui: bool, crop: str = "rapeseed", channels: bool = False
) -> int:
    from simulator.machine import SimulatedMachine

    code = {"rapeseed": 1, "wheat": 2}[crop]
    with tempfile.TemporaryDirectory(prefix="sowgate-demo-") as tmp:
        async with contextlib.AsyncExitStack() as stack:
            machine = await stack.enter_async_context(
                SimulatedMachine(crop=crop, loop_drive=True, with_gnss=True, with_seed_tubes=True)
            )
            overrides: dict[str, Any] = {}
            plants: dict[str, Any] = {}
            if channels:
                overrides = paper_b_channel_config(f"sowgate-demo-{os.getpid()}")
                plants = await _start_controllers(stack, overrides["can"]["channel"])
            settings = machine.settings(**overrides)
            daemon = Daemon(settings, Path(tmp) / "state")
            assert machine.hmi is not None
            model = settings.control.crops[crop]

            async def operator() -> None:
                await asyncio.sleep(1.0)
                assert machine.hmi is not None
                machine.hmi.select(code, model.default_rate_kg_ha)
                await asyncio.sleep(0.5)
                machine.hmi.press_start()
                if duration_s is not None:
                    await asyncio.sleep(max(0.0, duration_s - 1.5))
                    daemon.request_stop()

            def truth() -> dict[str, Any]:
                return truth_report(machine.truth, daemon.controller.rate_kg_ha)

            op = asyncio.create_task(operator(), name="demo-operator")
            try:
                if tui:
                    from gateway.cli import _with_live_view

                    await _with_live_view(daemon, daemon.run(), truth)
                else:
                    await daemon.run()
            finally:
                await cancel_and_wait(op)
            print(summary(truth(), daemon.controller.rate_kg_ha))
            area_ha = machine.truth.area_m2 / 1e4
            for name, _product, rate, _g in PAPER_B_CHANNELS if channels else ():
                mass_kg = plants[name].mass_g / 1000
                applied_ch = mass_kg / area_ha if area_ha > 0 else 0.0
                print(f"channel {name}: applied {applied_ch:.1f} kg/ha (target {rate:g})")
    return 0


async def _start_controllers(stack: contextlib.AsyncExitStack, can_channel: str) -> dict[str, Any]:
    """Paper B's PID controllers + hydraulic motors answering on the virtual CAN bus."""
    from drivers.can_bus import CanBus
    from simulator.can_pid import MeteringControllerSim, MeterPlant

    bus = await stack.enter_async_context(CanBus("virtual", can_channel))
    plants = {
        name: MeterPlant(grams_per_rev=g_per_rev, outlets=PAPER_B_OUTLETS)
        for name, _product, _rate, g_per_rev in PAPER_B_CHANNELS
    }
    sim = MeteringControllerSim(
        bus, {node: plants[name] for node, (name, *_) in enumerate(PAPER_B_CHANNELS, start=1)}
    )
    task = asyncio.create_task(sim.run(), name="demo-can-controllers")

    async def stop() -> None:
        await cancel_and_wait(task)

    stack.push_async_callback(stop)
    return plants
