"""The pieces every fault row is built from: the real daemon as a child process, a trace of
the PWM module's motor output, and the simulated machine the daemon is pointed at.

The daemon is ``python -m gateway.app.cli run --config …``, exactly what systemd starts; its
standard error (the journal on the box) goes to a file, which the rows read for uncaught
exceptions (``Traceback``) and for how much it logged. What the daemon did is judged from the
outside only: the simulated devices (what the PWM module was told), the record store on disk
and what reached a real broker.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import statistics
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway.recording.store import RecordStore
from simulator.machine import SimulatedMachine
from simulator.plant import Drive, Leg
from simulator.seed_tubes import SeedTubeEmulator
from tests.helpers import eventually, sowgate_env, spawn_sowgate
from tests.mosquitto import Subscriber, subscriber

MACHINE_ID = "seeder-01"
BASE = f"sowgate/{MACHINE_ID}"
STANDING_S = 3.0  # the daemon opens its ports while the simulated tractor still stands
DUTY_SAMPLE_S = 0.05  # how often the PWM module's motor output is sampled
STOP_TIMEOUT_S = 15.0


def sowing_drive(sow_s: float, kmh: float = 8.0, standing_after_s: float = 120.0) -> Drive:
    """Stand, sow for ``sow_s`` at ``kmh``, stand again (so the seed lines go quiet)."""
    return Drive(
        legs=[Leg(STANDING_S, 0.0), Leg(sow_s, kmh), Leg(standing_after_s, 0.0)], dt=0.02
    )


def steady_drive(kmh: float = 8.0, total_s: float = 900.0) -> Drive:
    return Drive(legs=[Leg(1.0, 0.0), Leg(total_s, kmh)], dt=0.02)


def dashboard(port: int) -> contextlib.AbstractAsyncContextManager[Subscriber]:
    """The rows' dashboard on the broker at ``port``: every message under ``BASE`` and when it
    arrived (``Subscriber.timed``, ``Subscriber.alarms_between``)."""
    return subscriber(port, BASE, "reliability-dashboard")


# "2026-04-20 08:00:00,123 WARNING pymodbus.logging: Repeating...." (cli.setup_logging's form)
PYMODBUS_LINE = re.compile(r"^\S+ \S+ [A-Z]+ pymodbus[.\w]*: ")


def _unit_nice() -> int:
    """``Nice=`` of systemd/sowgate.service: the rows run the daemon as the unit does."""
    unit = Path(__file__).resolve().parents[2] / "systemd" / "sowgate.service"
    for line in unit.read_text().splitlines():
        if line.startswith("Nice="):
            return int(line.removeprefix("Nice="))
    return 0


UNIT_NICE = _unit_nice()


class DaemonProcess:
    """``sowgate run`` in its own process, its log in ``log_path`` (appended across restarts)."""

    def __init__(
        self, config: Path, state_dir: Path, log_path: Path, env: dict[str, str] | None = None
    ) -> None:
        self.config = config
        self.state_dir = state_dir
        self.log_path = log_path
        self.env = sowgate_env(state_dir, env)
        self.proc: asyncio.subprocess.Process | None = None
        self.exit_codes: list[int] = []
        self.starts = 0

    async def start(self) -> None:
        if self.running:
            raise RuntimeError("daemon already running")
        with self.log_path.open("ab") as log:
            self.proc = await spawn_sowgate(
                "run", "--config", str(self.config),
                env=self.env, stdout=asyncio.subprocess.DEVNULL, stderr=log,
            )
        # at the priority the shipped unit gives it (its Nice=), as on the cab box
        with contextlib.suppress(PermissionError, ProcessLookupError):
            os.setpriority(os.PRIO_PROCESS, self.proc.pid, UNIT_NICE)
        self.starts += 1

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.returncode is None

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    async def kill(self) -> int:
        """SIGKILL: what an OOM kill or a watchdog reset looks like to the daemon."""
        assert self.proc is not None
        with contextlib.suppress(ProcessLookupError):  # already ended (and reaped) on its own
            self.proc.send_signal(signal.SIGKILL)
        return await self._reap()

    async def stop(self, timeout: float = STOP_TIMEOUT_S) -> int:
        """SIGTERM, the graceful stop; SIGKILL if it does not end in ``timeout``."""
        assert self.proc is not None
        if self.proc.returncode is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                return await asyncio.wait_for(self._reap(), timeout)
            except TimeoutError:
                return await self.kill()
        return await self._reap()

    async def _reap(self) -> int:
        assert self.proc is not None
        code = await self.proc.wait()
        if len(self.exit_codes) < self.starts:  # one exit code per start
            self.exit_codes.append(code)
        return code

    async def close(self) -> None:
        """Never leave a daemon behind, whatever the row did."""
        if self.running:
            await self.kill()

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def tracebacks(self) -> int:
        return self.log_text().count("Traceback")

    def log_lines(self) -> int:
        return len(self.log_text().splitlines())

    def own_log_lines(self) -> list[str]:
        """The log's lines but pymodbus's own (its "Repeating...." markers and frame notes,
        which come and go with the machine's load): a row's limits read what the daemon
        says, not what the library under it does."""
        return [line for line in self.log_text().splitlines()
                if not PYMODBUS_LINE.match(line)]

    def has_open(self, device_path: str) -> bool:
        """Whether the daemon holds ``device_path`` open (read from /proc, not from its log)."""
        if not self.running:
            return False
        target = os.path.realpath(device_path)
        fd_dir = f"/proc/{self.pid}/fd"
        try:
            names = os.listdir(fd_dir)
        except OSError:
            return False
        for name in names:
            with contextlib.suppress(OSError):
                if os.readlink(f"{fd_dir}/{name}") == target:
                    return True
        return False

    def rss_mb(self) -> float:
        """Resident memory now (MB), from /proc."""
        try:
            for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
        except OSError:
            pass
        return float("nan")

    def describe_exit(self) -> str:
        """'running' or the exit codes it has had, for the table."""
        codes = ", ".join(str(c) for c in self.exit_codes)
        if self.running:
            return f"running (exits so far: {codes})" if codes else "running"
        return f"exited {codes}"


class TracedMachine(SimulatedMachine):
    """The simulated machine, sampling what the PWM module drives the motor with."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self.duty: list[tuple[float, float]] = []  # (monotonic s, motor duty % at the module)
        self._sampler: asyncio.Task[None] | None = None

    async def __aenter__(self) -> TracedMachine:
        await super().__aenter__()
        self._sampler = asyncio.create_task(self._sample(), name="duty-sampler")
        return self

    async def __aexit__(self, *exc: Any) -> None:
        if self._sampler is not None:
            self._sampler.cancel()
            await asyncio.gather(self._sampler, return_exceptions=True)
        await super().__aexit__(*exc)

    async def _sample(self) -> None:
        while True:
            sim = self.rs485
            if sim is not None:
                self.duty.append((time.monotonic(), sim.duty_pct["motor"]))
            await asyncio.sleep(DUTY_SAMPLE_S)

    def motor_pct(self) -> float:
        assert self.rs485 is not None
        return self.rs485.duty_pct["motor"]

    def duty_between(self, t0: float, t1: float) -> list[float]:
        return [d for t, d in self.duty if t0 <= t <= t1]


@dataclass
class Steady:
    """The motor duty at steady speed before any fault: the yardstick for "overshoot"."""

    mean: float
    low: float
    high: float

    @classmethod
    def of(cls, samples: list[float]) -> Steady:
        if not samples:
            raise AssertionError("no steady duty samples")
        return cls(statistics.fmean(samples), min(samples), max(samples))

    def __str__(self) -> str:
        return f"{self.mean:.1f} % ({self.low:.1f}–{self.high:.1f})"


@dataclass
class RowResult:
    """What one fault row measured and which of its invariants did not hold."""

    lost: str = "—"
    recovery: str = "—"
    duty: str = "—"
    daemon: str = "—"
    tracebacks: str = "—"
    notes: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def check(self, ok: bool, problem: str) -> None:
        if not ok:
            self.problems.append(problem)


def seed_ids(db: Path) -> list[int]:
    """Every stored seed id, read as an export would (read-only, the daemon may be running)."""
    if not db.exists():
        return []
    with RecordStore.open_readonly(db, MACHINE_ID) as store:
        return [r.id for r in store.query_seeds()]


def integrity(db: Path) -> str:
    with RecordStore.open_readonly(db, MACHINE_ID) as store:
        return store.integrity_check()


def contiguous(ids: list[int]) -> bool:
    return ids == list(range(1, len(ids) + 1))


@contextlib.contextmanager
def tmpfs(path: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` mounted on ``path`` (root only), always unmounted again."""
    import subprocess

    path.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                   check=True, capture_output=True)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False, capture_output=True)


def fill(directory: Path, name: str = "filler") -> int:
    """Take every free byte of the file system ``directory`` is on; the bytes written."""
    written = 0
    chunk = b"\0" * 65536
    with (directory / name).open("wb", buffering=0) as f:
        while True:
            try:
                written += f.write(chunk)
            except OSError:
                break
        for size in (4096, 512, 1):  # the last partial blocks
            while True:
                try:
                    written += f.write(b"\0" * size)
                except OSError:
                    break
    return written


# ---- shared by the rows ------------------------------------------------------------------


EXCEPTION_LINE = re.compile(r"^[A-Za-z_][\w.]*(?:Error|Exception|Interrupt|Exit)\b.*$", re.M)


def finish_row(res: RowResult, daemon: DaemonProcess, tracebacks_before: int = 0) -> None:
    """Daemon state and uncaught exceptions, common to every row with a daemon."""
    res.daemon = daemon.describe_exit()
    tb = daemon.tracebacks() - tracebacks_before
    res.tracebacks = str(tb)
    if tb > 0:
        log = daemon.log_text()
        at = 0
        for _ in range(tracebacks_before + 1):  # the first Traceback of this row
            at = log.index("Traceback", at) + 1
        kinds = sorted({m.group(0)[:120] for m in EXCEPTION_LINE.finditer(log, at)})
        res.problems.append(
            f"{tb} Traceback(s) (uncaught or logged exceptions) in the daemon's log: "
            + "; ".join(kinds[:3])
        )


def fmt_s(seconds: float | None) -> str:
    return "never" if seconds is None else f"{seconds:.1f} s"


def edges_since(tubes: SeedTubeEmulator, n0: int) -> int:
    return len(tubes.truth) - n0


def late_epochs_note(gnss: Any, window: tuple[float, float]) -> str:
    """The simulated receiver's own lateness in ``window`` (host monotonic), for a row's
    problem text: an epoch the simulator wrote late is not the daemon's doing."""
    late = [s for t, s in gnss.late_epochs if window[0] - 1.0 <= t <= window[1]]
    if not late:
        return " (the simulator wrote every epoch of the window on time)"
    return (f" ({len(late)} epochs of the window written late or skipped by the simulator, "
            f"up to {max(late) * 1000:.0f} ms)")


def edge_mono(tubes: SeedTubeEmulator, t_edge: float) -> float:
    assert tubes.t0_mono is not None
    return tubes.t0_mono + t_edge


def mqtt_overrides(port: int, **extra: Any) -> dict[str, Any]:
    return {
        "mqtt": {"enabled": True, "port": port, "keepalive": 5, "reconnect_max_s": 1.0},
        "control": {"start_working": True},
        **extra,
    }


SAFE_OFF_UNCONFIRMED = "could not set motor and fan to 0 on exit"


def check_graceful_stop(res: RowResult, code: int, daemon: DaemonProcess) -> None:
    """A graceful stop exits 0, or 1 (``EXIT_NOT_SAFE``) when it says it could not confirm
    motor and fan at 0: the simulated PWM module answers from this campaign's own event loop,
    which a busy 2-core host can hold past the daemon's last write. That exit is the daemon
    telling the truth (tests/integration/test_graceful_stop.py proves it); here it is noted, and
    any other code fails the row."""
    if code == 1 and SAFE_OFF_UNCONFIRMED in daemon.log_text()[-4000:]:
        res.notes.append("graceful stop: the simulated PWM module did not confirm 0 in time "
                         "(exit 1, the daemon said so)")
        return
    res.check(code == 0, f"graceful stop exited {code}")


async def records_vs_edges(
    res: RowResult, machine: TracedMachine, daemon: DaemonProcess, db: Path, n_open: int
) -> tuple[int, int]:
    """Stop the daemon once the pass has ended; (edges sensed, records stored)."""
    await eventually(lambda: machine.pose().speed_kmh == 0.0, 120.0, "end of the pass")
    await asyncio.sleep(1.0)  # the last seeds fall
    tubes = machine.seed_tubes
    sent = edges_since(tubes, n_open)
    code = await daemon.stop()
    check_graceful_stop(res, code, daemon)
    ids = seed_ids(db)
    res.check(contiguous(ids), f"ids not contiguous ({len(ids)} rows)")
    check = integrity(db)
    res.check(check == "ok", f"integrity_check says {check!r}")
    return sent, len(ids)


async def steady_duty(machine: TracedMachine, seconds: float) -> Steady:
    t0 = time.monotonic()
    await asyncio.sleep(seconds)
    return Steady.of(machine.duty_between(t0, time.monotonic()))


def recovered_after(
    machine: TracedMachine, t_end: float, steady: Steady, tolerance_pct: float
) -> float | None:
    """Seconds from ``t_end`` until the duty was back in the steady band (± ``tolerance_pct``),
    None if it never was."""
    for t, d in machine.duty:
        if t >= t_end and steady.low - tolerance_pct <= d <= steady.high + tolerance_pct:
            return t - t_end
    return None


