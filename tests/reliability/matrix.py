"""The campaign: the groups of the selected rows, run concurrently, each in its own process.

Rows that need their own daemon run beside each other (the broker outage alone takes a
minute); rows whose faults do not interfere share one daemon inside their group. Every group
returns a ``RowResult`` per row.

Each group runs in a process of its own (its own event loop and GIL): the simulated machine,
its broker client and the judge's sampling are Python code on an event loop, and with every
group in one loop they shared one core. On a loaded 2-core machine that loop fell behind by
more than the daemon's own timeouts (GNSS epochs written > 0.5 s late, a radar answering late
after a gap), and rows failed on the harness's lateness, not the daemon's.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import time
from collections.abc import Awaitable, Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
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


def _run_group(group: str, directory: Path) -> dict[str, RowResult]:
    """One group in this (child) process: its own event loop; a harness failure shows in every
    row of the group."""
    directory.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    try:
        out = asyncio.run(GROUPS[group](directory))
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


async def run_campaign(tmp: Path, wanted: Iterable[str]) -> dict[str, RowResult]:
    """Run the groups the ``wanted`` rows belong to, concurrently; a result for every row."""
    wanted = set(wanted)
    groups = sorted({ROWS_BY_NAME[name].group for name in wanted})
    results: dict[str, RowResult] = {}
    # the farm rows run three cabs' simulated machines, two ingests and a PostgreSQL of their
    # own: side by side with the rest they starve the other groups (rows timed out "waiting
    # for metering" on a quiet 2-core box), so they come after
    alone = [g for g in groups if g in RUN_AFTER_THE_OTHERS]
    loop = asyncio.get_running_loop()
    # spawn, not fork: the parent may hold threads (pytest plugins, executors) and a fork of
    # a process with threads can deadlock in the child
    context = multiprocessing.get_context("spawn")
    for phase in ([g for g in groups if g not in alone], alone):
        if not phase:
            continue
        with ProcessPoolExecutor(max_workers=len(phase), mp_context=context) as pool:
            parts = await asyncio.gather(
                *(loop.run_in_executor(pool, _run_group, g, tmp / g) for g in phase)
            )
        for part in parts:
            results.update(part)
    for name in wanted:
        results.setdefault(name, RowResult(problems=["the row produced no result"]))
    return results
