"""Rows about what is recorded: SIGKILL ×10, the broker down a minute, the disk full."""

from __future__ import annotations

import asyncio
import contextlib
import random
import time
from pathlib import Path

from tests.helpers import eventually
from tests.mosquitto import Mosquitto
from tests.reliability.harness import (
    DaemonProcess,
    RowResult,
    TracedMachine,
    dashboard,
    edge_mono,
    edges_since,
    fill,
    finish_row,
    integrity,
    mqtt_overrides,
    records_vs_edges,
    seed_ids,
    sowing_drive,
    tmpfs,
)
from tests.reliability.rows import (
    BROKER_DOWN_S,
    COMMIT_WINDOW_S,
    DISK_FULL_S,
    KILLS,
)

# ---- SIGKILL ×10 ----------------------------------------------------------------------------


async def group_kills(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    rng = random.Random(11)
    machine = TracedMachine(drive=sowing_drive(KILLS * 6.0 + 10.0), with_gnss=True,
                            with_seed_tubes=True)
    async with machine:
        tubes = machine.seed_tubes
        cfg = machine.write_config(tmp / "sowgate.toml", control={"start_working": True})
        db = tmp / "state" / "records.sqlite3"
        daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
        try:
            prev = 0
            before: list[int] = []
            losses: list[tuple[int, int]] = []  # (lost, allowed) per kill
            restarts: list[float] = []
            t_killed: float | None = None
            for k in range(KILLS):
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0,
                                 f"seed port open (start {k + 1})")
                if t_killed is not None:
                    restarts.append(time.monotonic() - t_killed)
                n_open = len(tubes.truth)

                def falling(n0: int = n_open) -> bool:
                    return edges_since(tubes, n0) >= 10

                await eventually(falling, 30.0, "seeds falling")
                await asyncio.sleep(1.5 + rng.uniform(0.0, 1.0))  # any phase of the commit
                n_kill, t_killed = len(tubes.truth), time.monotonic()
                code = await daemon.kill()
                res.check(code == -9, f"kill {k + 1}: exit code {code}, not -9 (SIGKILL)")
                check = integrity(db)
                res.check(check == "ok", f"kill {k + 1}: integrity_check says {check!r}")
                ids = seed_ids(db)
                # each run's ids are contiguous and above every id of the runs before (a run
                # killed skips the rest of its id reservation: gateway.recording.store.ids)
                res.check(run_after(before, ids),
                          f"kill {k + 1}: ids not kept and increasing ({len(ids)} rows, "
                          f"max {ids[-1] if ids else 0})")
                stored = len(ids) - prev
                prev = len(ids)
                before = ids
                sent = n_kill - n_open
                window = sum(
                    1 for s in tubes.truth[n_open:n_kill]
                    if edge_mono(tubes, s.t_edge) >= t_killed - COMMIT_WINDOW_S
                )
                lost = max(0, sent - stored)
                losses.append((lost, window))
                res.check(lost <= window, f"kill {k + 1}: {lost} records lost of {sent} sensed, "
                                          f"more than the {window} of the commit window")
            total_lost = sum(lost for lost, _ in losses)
            total_allowed = sum(window for _, window in losses)
            res.lost = (f"{total_lost} in {KILLS} kills, at most {max(x for x, _ in losses)} a "
                        f"kill (the seeds of the kills' commit windows: {total_allowed})")
            median = sorted(restarts)[len(restarts) // 2]
            res.recovery = (f"restart → seed port open: median {median:.1f} s, "
                            f"max {max(restarts):.1f} s")
            res.notes.append(f"{prev} records, ids contiguous within each run and never "
                             f"reused; integrity ok after each kill" if not res.problems
                             else f"{prev} records")
        finally:
            await daemon.close()
        finish_row(res, daemon)
        res.daemon = f"{KILLS} × exit −9, restarted each time"
    return {"sigkill_during_seeding_x10": res}


def run_after(before: list[int], ids: list[int]) -> bool:
    """``ids`` keeps ``before`` and adds one contiguous run above all of it."""
    new = ids[len(before):]
    return (ids[:len(before)] == before and (not new or (
        new == list(range(new[0], new[0] + len(new))) and (not before or new[0] > before[-1])
    )))


# ---- broker down 60 s -----------------------------------------------------------------------


async def group_broker(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    machine = TracedMachine(drive=sowing_drive(BROKER_DOWN_S + 20.0), with_gnss=True,
                            with_seed_tubes=True)
    with Mosquitto(persistent=True) as broker:
        async with dashboard(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            db = tmp / "state" / "records.sqlite3"
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)
                await eventually(
                    lambda: len(set(dash.seed_ids())) > 100, 30.0, "seeds on the broker"
                )
                broker.stop()
                at_down = len(seed_ids(db))
                await asyncio.sleep(BROKER_DOWN_S)
                res.check(daemon.running, "daemon exited while the broker was down")
                during = len(seed_ids(db)) - at_down
                res.check(during > 0, "the store recorded nothing while the broker was down")
                broker.start()
                backlog = seed_ids(db)
                try:
                    took = await eventually(lambda: set(backlog) <= set(dash.seed_ids()), 60.0,
                                            "the outage's backlog delivered")
                    res.recovery = f"backlog of {len(backlog) - at_down} delivered {took:.1f} s " \
                                   "after the broker came back"
                except AssertionError as exc:
                    res.problems.append(str(exc))
                    res.recovery = "backlog never delivered"
                sent, stored = await records_vs_edges(res, machine, daemon, db, n_open)
                ids = seed_ids(db)
                with contextlib.suppress(AssertionError):
                    await eventually(
                        lambda: set(ids) <= set(dash.seed_ids()), 10.0, "all delivered"
                    )
                undelivered = len(set(ids) - set(dash.seed_ids()))
                res.lost = (f"{max(0, sent - stored)} of {sent} edges not stored; "
                            f"{undelivered} of {len(ids)} stored not delivered")
                res.check(stored >= sent, f"{sent - stored} of {sent} seed edges not stored")
                res.check(undelivered == 0, f"{undelivered} stored records never delivered")
                res.notes.append(f"{during} records stored during the outage")
            finally:
                await daemon.close()
            finish_row(res, daemon)
    return {"broker_down_60s": res}


# ---- disk full 20 s -------------------------------------------------------------------------


async def group_disk(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    machine = TracedMachine(drive=sowing_drive(DISK_FULL_S + 20.0), with_gnss=True,
                            with_seed_tubes=True)
    with tmpfs(tmp / "disk", "2m") as disk, Mosquitto() as broker:
        async with dashboard(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            state = disk / "state"
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            db = state / "records.sqlite3"
            daemon = DaemonProcess(cfg, state, tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)
                await eventually(lambda: len(seed_ids(db)) > 100, 30.0, "seeds stored")
                t_full = time.monotonic()
                filled = fill(disk)
                await asyncio.sleep(DISK_FULL_S)
                res.check(daemon.running, "daemon exited while the disk was full")
                remount = await asyncio.create_subprocess_exec(
                    "mount", "-o", "remount,size=64m", str(disk))
                res.check(await remount.wait() == 0, "could not remount the tmpfs larger")
                (disk / "filler").unlink()
                t_free = time.monotonic()
                alarms = dash.alarms_between(t_full, t_free + 1.0)
                res.check("records.store_failed" in alarms,
                          "records.store_failed never published on MQTT while the disk was full "
                          f"(seen: {', '.join(sorted(alarms)) or 'none'})")
                sent_by_free = edges_since(tubes, n_open)
                try:
                    took = await eventually(lambda: len(seed_ids(db)) >= sent_by_free, 30.0,
                                            "the store caught up with the seeds of the outage")
                    res.recovery = f"store caught up {took:.1f} s after space came back"
                except AssertionError:
                    res.recovery = "store never caught up"
                sent, stored = await records_vs_edges(res, machine, daemon, db, n_open)
                res.lost = f"{max(0, sent - stored)} of {sent} edges not stored"
                res.check(stored >= sent, f"{sent - stored} of {sent} seed edges lost to the "
                                          "full disk")
                res.notes.append(f"{filled // 1024} KiB filled; alarms seen while full: "
                                 f"{', '.join(sorted(alarms)) or 'none'}")
            finally:
                await daemon.close()
                with contextlib.suppress(OSError):
                    (disk / "filler").unlink()
            finish_row(res, daemon)
    return {"disk_full_20s": res}


