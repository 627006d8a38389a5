"""The campaign: the groups of the selected rows, run concurrently in one event loop.

Rows that need their own daemon run beside each other (the broker outage alone takes a
minute); rows whose faults do not interfere share one daemon inside their group. Every group
returns a ``RowResult`` per row.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Iterable
from pathlib import Path

from tests.reliability.agopengps_faults import group_agopengps
from tests.reliability.device_faults import group_modbus, group_serial
from tests.reliability.farm_faults import group_farm
from tests.reliability.gnss_time_faults import group_gnss_time
from tests.reliability.harness import RowResult
from tests.reliability.hopper_faults import group_hopper
from tests.reliability.input_faults import group_commands, group_config
from tests.reliability.recording_faults import group_broker, group_disk, group_kills
from tests.reliability.row_faults import group_rows
from tests.reliability.rows import ROWS, ROWS_BY_NAME
from tests.reliability.store_faults import group_freeze, group_rollover, group_store

GROUPS: dict[str, Callable[[Path], Awaitable[dict[str, RowResult]]]] = {
    "kills": group_kills,
    "broker": group_broker,
    "disk": group_disk,
    "store": group_store,
    "freeze": group_freeze,
    "rollover": group_rollover,
    "modbus": group_modbus,
    "serial": group_serial,
    "hopper": group_hopper,
    "gnss_time": group_gnss_time,
    "rows": group_rows,
    "commands": group_commands,
    "config": group_config,
    "agopengps": group_agopengps,
    "farm": group_farm,
}


RUN_AFTER_THE_OTHERS = frozenset({"farm"})


async def run_campaign(tmp: Path, wanted: Iterable[str]) -> dict[str, RowResult]:
    """Run the groups the ``wanted`` rows belong to, concurrently; a result for every row."""
    wanted = set(wanted)
    groups = sorted({ROWS_BY_NAME[name].group for name in wanted})

    async def one(group: str) -> dict[str, RowResult]:
        directory = tmp / group
        directory.mkdir(parents=True, exist_ok=True)
        started = time.monotonic()
        try:
            out = await GROUPS[group](directory)
        except Exception as exc:  # a broken harness shows in every row
            import traceback

            text = "".join(traceback.format_exception(exc))
            out = {}
            for row in ROWS:
                if row.group == group:
                    out[row.name] = RowResult(problems=[f"the run of this row failed: {exc!r}"],
                                              notes=[text[-1500:]])
        took = time.monotonic() - started
        for res in out.values():
            res.notes.append(f"group {group}: {took:.0f} s")
        return out

    results: dict[str, RowResult] = {}
    # the farm rows run three cabs' simulated machines, two ingests and a PostgreSQL of their
    # own: side by side with the rest they starve the other groups' simulators in this event
    # loop (rows timed out "waiting for metering" on a quiet 2-core box), so they come after
    alone = [g for g in groups if g in RUN_AFTER_THE_OTHERS]
    for phase in ([g for g in groups if g not in alone], alone):
        for part in await asyncio.gather(*(one(g) for g in phase)):
            results.update(part)
    for name in wanted:
        results.setdefault(name, RowResult(problems=["the row produced no result"]))
    return results
