"""``sowgate demo``: the daemon driving the simulated machine, with a scripted operator."""

from __future__ import annotations

import asyncio
import logging
import tempfile
from pathlib import Path
from typing import Any

from drivers.tasks import cancel_and_wait
from gateway.daemon import Daemon

log = logging.getLogger(__name__)


async def run_demo(duration_s: float | None, tui: bool, crop: str = "rapeseed") -> int:
    from simulator.machine import SimulatedMachine

    code = {"rapeseed": 1, "wheat": 2}[crop]
    with tempfile.TemporaryDirectory(prefix="sowgate-demo-") as tmp:
        async with SimulatedMachine(
            crop=crop, loop_drive=True, with_gnss=True, with_seed_tubes=True
        ) as machine:
            settings = machine.settings()
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
                applied = machine.truth.applied_kg_ha()
                target = daemon.controller.rate_kg_ha
                return {
                    "applied_kg_ha": applied if applied else None,
                    "rate_error_pct": (applied / target - 1) * 100 if applied else None,
                }

            op = asyncio.create_task(operator(), name="demo-operator")
            try:
                if tui:
                    from gateway.cli import _with_live_view

                    await _with_live_view(daemon, daemon.run(), truth)
                else:
                    await daemon.run()
            finally:
                await cancel_and_wait(op)
            t = truth()
            print(
                f"demo finished: applied {t['applied_kg_ha'] or 0:.2f} kg/ha "
                f"(target {daemon.controller.rate_kg_ha:g}), error "
                f"{t['rate_error_pct'] or 0:+.2f} %"
            )
    return 0
