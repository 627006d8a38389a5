"""Rows about the store's medium: what a power cut or a bad SD card leaves of the store (the
WAL lost, the last seconds of writes lost, a zero-length, truncated or overwritten file), and
a card that freezes for seconds while the drill sows.

The damage is done to the real files between a SIGKILL and the next start of the same daemon;
the freeze is ``fsfreeze`` on a loop-mounted ext4 image holding the state directory. What is
judged comes from outside: what the dashboard received on a real broker (no id may come with
two different seeds), the PWM module's motor output, the daemon's log.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

from tests.helpers import eventually
from tests.mosquitto import Mosquitto, Subscriber
from tests.reliability.harness import (
    DaemonProcess,
    RowResult,
    Steady,
    TracedMachine,
    check_graceful_stop,
    dashboard,
    finish_row,
    mqtt_overrides,
    records_vs_edges,
    recovered_after,
    seed_ids,
    sowing_drive,
    steady_duty,
)
from tests.reliability.rows import (
    DUTY_TOLERANCE_PCT,
    FREEZE_S,
    FREEZE_SETTLE_S,
    LAST_WRITES_LOST_S,
    RECOVERY_MAX_S,
    ROLLOVER_WEEKS,
    STORE_DAMAGE_ROWS,
)

STORE = "records.sqlite3"


def reused_ids(dash: Subscriber) -> list[int]:
    """Ids the dashboard received with two different seeds (a resend repeats the same one)."""
    seen: dict[int, tuple[object, ...]] = {}
    reused: set[int] = set()
    for payload in dash.on("seeds"):
        for r in json.loads(payload)["records"]:
            key = (r["utc"], r["row"], r["lat"], r["lon"])
            if seen.setdefault(r["id"], key) != key:
                reused.add(r["id"])
    return sorted(reused)


def _side_files(db: Path) -> list[Path]:
    return [db.with_name(db.name + s) for s in ("-wal", "-shm")]


def _remove_side_files(db: Path) -> None:
    for p in _side_files(db):
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def _overwrite_a_page(db: Path) -> None:
    size = db.stat().st_size
    page = max(2, (size // 4096) // 2)
    with db.open("r+b") as f:
        f.seek(page * 4096)
        f.write(bytes(range(256)) * 16)


DAMAGE: dict[str, tuple[str, Callable[[Path], None]]] = {
    # row name: (the alarm that must say so, what is done to the store after the SIGKILL)
    "store_wal_lost": ("store.unclean_stop", _remove_side_files),
    "store_zero_length": ("store.replaced", lambda db: (db.write_bytes(b""),
                                                        _remove_side_files(db))[0]),
    "store_truncated": ("store.replaced", lambda db: os.truncate(db, db.stat().st_size // 2)),
    "store_page_overwritten": ("store.replaced", _overwrite_a_page),
}


async def group_store(tmp: Path) -> dict[str, RowResult]:
    """One daemon, killed once per row, its store damaged, started again on the same state."""
    machine = TracedMachine(drive=sowing_drive(len(STORE_DAMAGE_ROWS) * 25.0 + 30.0),
                            with_gnss=True, with_seed_tubes=True)
    results: dict[str, RowResult] = {}
    with Mosquitto() as broker:
        async with dashboard(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            state = tmp / "state"
            db = state / STORE
            daemon = DaemonProcess(cfg, state, tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                await eventually(lambda: len(dash.seed_ids()) > 100, 30.0, "seeds on the broker")
                steady = await steady_duty(machine, 3.0)
                for name in STORE_DAMAGE_ROWS:
                    results[name] = await _damage_row(name, machine, dash, daemon, db, steady)
            finally:
                await daemon.close()
    return results


async def _damage_row(
    name: str, machine: TracedMachine, dash: Subscriber, daemon: DaemonProcess, db: Path,
    steady: Steady,
) -> RowResult:
    res = RowResult()
    tubes = machine.seed_tubes
    tb0 = daemon.tracebacks()
    before = set(seed_ids(db))
    snapshot: Path | None = None
    if name == "store_last_writes_lost":
        # the card's cache lied: every file of the state directory as it was LAST_WRITES_LOST_S
        # before the cut (the id reservation included)
        snapshot = db.parent.with_name("snapshot")
        shutil.rmtree(snapshot, ignore_errors=True)
        shutil.copytree(db.parent, snapshot)
        await asyncio.sleep(LAST_WRITES_LOST_S)
    published = set(dash.seed_ids())
    stored = set(seed_ids(db))
    code = await daemon.kill()
    res.check(code == -9, f"exit code {code}, not -9 (SIGKILL)")
    if snapshot is not None:
        # the copy of a store being written may itself be damaged: then it is replaced
        alarms = {"store.unclean_stop", "store.replaced"}
        shutil.rmtree(db.parent)
        shutil.copytree(snapshot, db.parent)
    else:
        alarm, damage = DAMAGE[name]
        alarms = {alarm}
        damage(db)
    t_start = time.monotonic()
    await daemon.start()
    try:
        await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
        t_open = time.monotonic()
        await eventually(lambda: len(set(dash.seed_ids()) - published) > 100, 30.0,
                         "new seeds on the broker")
        await eventually(lambda: alarms & dash.alarms_between(t_start, time.monotonic()),
                         15.0, f"{' or '.join(sorted(alarms))} on MQTT")
    except AssertionError as exc:
        res.problems.append(str(exc))
        t_open = time.monotonic()
    await asyncio.sleep(3.0)
    res.check(daemon.running, "the daemon exited after the restart")
    reused = reused_ids(dash)
    res.check(not reused, f"{len(reused)} ids published for two different seeds "
                          f"(first: {reused[:5]})")
    back = recovered_after(machine, t_open, steady, DUTY_TOLERANCE_PCT)
    res.check(back is not None and back <= RECOVERY_MAX_S,
              f"the motor duty not back at steady within {RECOVERY_MAX_S:g} s of the restart "
              f"({back})")
    after = set(seed_ids(db))
    new = after - stored
    res.check(not new or min(new) > max(stored | published, default=0),
              "a new id is not above every id stored or published before the cut")
    gone = stored - after
    undelivered = gone - set(dash.seed_ids())
    moved = sorted(p.name for p in db.parent.iterdir()
                   if ".bad-" in p.name and not p.name.endswith(("-wal", "-shm")))
    seen = alarms & dash.alarms_between(t_start, time.monotonic())
    if seen == {"store.replaced"}:
        res.check(bool(moved), "no store moved aside (records.sqlite3.bad-…) in the state dir")
    res.lost = (f"{len(gone)} of {len(stored)} stored records gone from the store with the "
                f"damage; {len(undelivered)} of them never delivered")
    res.recovery = (f"seed port open {t_open - t_start:.1f} s after the start; duty at steady "
                    f"{back:.1f} s later" if back is not None else "duty never back at steady")
    res.notes.append(f"{len(before)} stored before; ids after the restart from "
                     f"{min(new) if new else '—'}; alarm seen: {', '.join(sorted(seen))}"
                     + (f"; kept: {', '.join(moved)}" if moved else ""))
    finish_row(res, daemon, tb0)
    res.daemon = "running after the restart" if daemon.running else res.daemon
    return res


# ---- the state directory frozen --------------------------------------------------------------


@contextlib.contextmanager
def loop_ext4(image: Path, mountpoint: Path, size_mb: int = 64) -> Iterator[Path]:
    """A small ext4 file system in ``image``, loop-mounted on ``mountpoint`` (root only): one
    that ``fsfreeze`` can freeze (tmpfs cannot be)."""
    with image.open("wb") as f:
        f.truncate(size_mb * 1024 * 1024)
    subprocess.run(["mkfs.ext4", "-q", "-F", str(image)], check=True, capture_output=True)
    mountpoint.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-o", "loop", str(image), str(mountpoint)], check=True,
                   capture_output=True)
    try:
        yield mountpoint
    finally:
        subprocess.run(["fsfreeze", "--unfreeze", str(mountpoint)], check=False,
                       capture_output=True)
        subprocess.run(["umount", "-l", str(mountpoint)], check=False, capture_output=True)


async def group_freeze(tmp: Path) -> dict[str, RowResult]:
    res = RowResult()
    # long enough that a slow start on a loaded box cannot end the pass during the freeze (the
    # tractor slowing down read as the duty falling); the group waits for the end of the pass
    machine = TracedMachine(drive=sowing_drive(FREEZE_S + 50.0), with_gnss=True,
                            with_seed_tubes=True)
    with loop_ext4(tmp / "card.img", tmp / "card") as card, Mosquitto() as broker:
        async with dashboard(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            state = card / "state"
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(broker.port))
            db = state / STORE
            daemon = DaemonProcess(cfg, state, tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                n_open = len(tubes.truth)
                await eventually(lambda: len(dash.seed_ids()) > 100, 30.0, "seeds on the broker")
                await asyncio.sleep(FREEZE_SETTLE_S)  # the rate controller settles first
                steady = await steady_duty(machine, 4.0)
                # nothing in this process may touch the card while it is frozen (it would
                # sleep uninterruptibly like the daemon once did)
                freeze = await asyncio.create_subprocess_exec("fsfreeze", "--freeze", str(card))
                res.check(await freeze.wait() == 0, "fsfreeze --freeze failed")
                t_frozen = time.monotonic()
                await asyncio.sleep(FREEZE_S)
                thaw = await asyncio.create_subprocess_exec("fsfreeze", "--unfreeze", str(card))
                res.check(await thaw.wait() == 0, "fsfreeze --unfreeze failed")
                t_thawed = time.monotonic()
                res.check(machine.pose().speed_kmh > 0.0,
                          "the pass ended before the thaw (the daemon started too slowly for "
                          "this drive): the duty judged includes the tractor stopping")
                during = machine.duty_between(t_frozen, t_thawed)
                low = min(during, default=0.0)
                res.check(bool(during) and low >= steady.low - DUTY_TOLERANCE_PCT,
                          f"the motor duty fell to {low:.1f} % while the card was frozen "
                          f"(steady {steady})")
                res.duty = (f"steady {steady}; while frozen {low:.1f}–"
                            f"{max(during, default=0.0):.1f} %")
                res.notes.append("duty each second while frozen: " + ", ".join(
                    f"{d:.1f}" for d in during[::max(1, int(1.0 / 0.05))]))
                alarms = dash.alarms_between(t_frozen, t_thawed + 1.0)
                res.check("store.stalled" in alarms,
                          "store.stalled never published on MQTT while the card was frozen "
                          f"(seen: {', '.join(sorted(alarms)) or 'none'})")
                res.check(daemon.running, "daemon exited while the card was frozen")
                sent, stored = await records_vs_edges(res, machine, daemon, db, n_open)
                res.lost = f"{max(0, sent - stored)} of {sent} edges not stored"
                res.check(stored >= sent, f"{sent - stored} of {sent} seed edges lost to the "
                                          "freeze")
                reused = reused_ids(dash)
                res.check(not reused, f"{len(reused)} ids published for two different seeds")
                res.recovery = f"card frozen {FREEZE_S:g} s; alarms seen: " + (
                    ", ".join(sorted(alarms)) or "none")
            finally:  # never leave the card frozen, whatever the row did
                unfreeze = await asyncio.create_subprocess_exec(
                    "fsfreeze", "--unfreeze", str(card), stderr=asyncio.subprocess.DEVNULL)
                await unfreeze.wait()
                await daemon.close()
            finish_row(res, daemon)
    return {"store_frozen_8s": res}


# ---- GNSS dates 1024 weeks early, then the pruning a start runs ---------------------------


async def group_rollover(tmp: Path) -> dict[str, RowResult]:
    """A receiver past a GPS week rollover stamps every seed 1024 weeks early; the store's
    pruning (at every start, and hourly) must not take that for age."""
    res = RowResult()
    early = datetime.now(UTC).replace(microsecond=0) - timedelta(weeks=ROLLOVER_WEEKS)
    machine = TracedMachine(drive=sowing_drive(30.0), with_gnss=True, with_seed_tubes=True,
                            gnss_utc_start=early)
    with Mosquitto() as broker:
        async with dashboard(broker.port) as dash, machine:
            tubes = machine.seed_tubes
            cfg = machine.write_config(tmp / "sowgate.toml", **mqtt_overrides(
                broker.port, store={"retention_days": 30}))
            db = tmp / "state" / STORE
            daemon = DaemonProcess(cfg, tmp / "state", tmp / "daemon.log")
            try:
                await daemon.start()
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                await eventually(lambda: len(seed_ids(db)) > 300, 60.0, "seeds stored")
                stored = seed_ids(db)
                await eventually(lambda: set(stored) <= set(dash.seed_ids()), 30.0,
                                 "the stored seeds delivered")
                years = sorted({json.loads(p)["records"][0]["utc"][:4] for p in dash.on("seeds")})
                code = await daemon.stop()
                check_graceful_stop(res, code, daemon)
                kept_at_stop = seed_ids(db)
                await daemon.start()  # the start prunes
                await eventually(lambda: daemon.has_open(tubes.device_path), 30.0, "seed port")
                await asyncio.sleep(5.0)
                res.check(daemon.running, "daemon exited after the restart")
                code = await daemon.stop()
                check_graceful_stop(res, code, daemon)
                after = seed_ids(db)
                deleted = sorted(set(kept_at_stop) - set(after))
                res.check(not deleted, f"{len(deleted)} of {len(kept_at_stop)} delivered "
                                       "records deleted by the pruning at start")
                res.lost = f"{len(deleted)} of {len(kept_at_stop)} delivered records deleted"
                res.notes.append(f"seeds stamped {', '.join(years)}; retention 30 days; "
                                 f"{len(after)} records after the restart")
            finally:
                await daemon.close()
            finish_row(res, daemon)
    return {"store_prune_gps_rollover": res}
