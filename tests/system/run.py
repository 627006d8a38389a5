"""``make system-test``: the shipped bundle and units under a real systemd, in qemu.

1. the simulated machine starts on the host (RS485 bus, GNSS, seed line, touchscreen on ptys);
   its config, with the ports the fitter's udev rule gives, is the guest's /etc/sowgate config
2. a throwaway Debian 12 image (build_base.sh, cached) gets the x86_64 bundle from `make dist`
   installed by its install.sh in a chroot without a network namespace's interfaces (offline)
3. qemu (TCG) boots it with systemd as PID 1; the simulator's ports are bridged to the guest's
   ttyS1..ttyS4 (host ptys), results come back through a 9p share
4. guest.py runs the checks in the guest; the host presses Start on the touchscreen when asked
   and watches the PWM module (duty against the radar, comm-loss timeout)
5. the table goes to build/system-test/result.md and into docs/deployment.md

Leaves nothing running and nothing outside build/.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tarfile
import time
import tty
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
BUILD = REPO / "build" / "system-test"
OUT = BUILD / "out"
ROOT = BUILD / "root"
DISK = BUILD / "disk.img"
DOC = REPO / "docs" / "deployment.md"
BEGIN, END = "<!-- system-test:begin -->", "<!-- system-test:end -->"
BOOT_TIMEOUT_S = 1500.0  # one boot of the guest, its checks and poweroff (a loaded host: slow)
# guest port -> which simulated device (the udev rule in the image names them like the
# shipped 99-sowgate.rules does for USB adapters)
PORTS = {"ttyS1": "rs485", "ttyS2": "gnss", "ttyS3": "seeds", "ttyS4": "hmi"}
GUEST_RULES = "".join(
    f'KERNEL=="{tty}", SYMLINK+="sowgate-{name}", GROUP="dialout", MODE="0660"\n'
    for tty, name in PORTS.items())
CREDENTIAL = "/run/credentials/sowgate-dashboard.service/dashboard-password"
DASHBOARD_PASSWORD = "cab-7f3q-seeder"  # the throwaway guest's page
GUEST_FILES = {
    # the README's LoadCredential drop-in for the dashboard's password
    "etc/systemd/system/sowgate-dashboard.service.d/credential.conf":
        "[Service]\nLoadCredential=dashboard-password:/etc/sowgate/dashboard-password\n",
    # the guest's CAN bus, up before sowgate starts at boot (vcan is loaded by the initrd)
    "etc/systemd/system/vcan0.service":
        "[Unit]\nDescription=virtual CAN bus vcan0 (system test)\nBefore=sowgate.service\n"
        "[Service]\nType=oneshot\nRemainAfterExit=yes\n"
        "ExecStart=/sbin/ip link add vcan0 type vcan\nExecStart=/sbin/ip link set vcan0 up\n"
        "[Install]\nWantedBy=multi-user.target\n",
    # The one change to the shipped units, for emulation only: TCG on a busy 2-core host runs
    # Python 20-50x slower than a real cab box, and the daemon's start (imports) took more
    # than the unit's TimeoutStartSec=60s when other jobs loaded the host (load ~20)
    "etc/systemd/system/sowgate.service.d/zz-systest-emulation.conf":
        "[Service]\nTimeoutStartSec=400s\n",
}
RUNNER_UNIT = """[Unit]
Description=system test runner (guest.py: checks, then poweroff)
After=multi-user.target mosquitto.service
[Service]
Type=simple
ExecStart=/opt/sowgate/current/bin/python /usr/local/lib/systest/guest.py
StandardOutput=journal+console
[Install]
WantedBy=multi-user.target
"""


def log(msg: str) -> None:
    print(f"[system-test {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def guest_config(machine: Any) -> dict[str, Any]:
    """The simulated machine's config with the guest's port names and its own broker."""
    data: dict[str, Any] = machine.config()
    data["rs485"].update(port="/dev/sowgate-rs485", timeout_s=0.5)
    data["hmi"]["port"] = "/dev/sowgate-hmi"
    data["gnss"]["port"] = "/dev/sowgate-gnss"
    data["seed_sensors"]["port"] = "/dev/sowgate-seeds"
    data["mqtt"] = {"host": "127.0.0.1", "port": 1883, "topic_prefix": "sowgate"}
    # a second, CAN-driven metering channel (paper B's controller) on the guest's vcan0, next
    # to the RS485 PWM seed meter: AF_CAN under the shipped RestrictAddressFamilies; guest.py
    # answers its target-speed frames as the controller would
    data["can"] = {"enabled": True, "interface": "socketcan", "channel": "vcan0"}
    data["channel"] = [{"name": "fert", "product": "fertiliser", "target_rate_kg_ha": 150.0,
                        "drive": "can_pid", "node_id": 1, "grams_per_rev": 16.97,
                        "outlets": 10}]
    # the page's password as systemd/README.md says: a root-only file handed to the dynamic
    # user by LoadCredential (a drop-in in the image)
    data["dashboard"] = {"listen": "127.0.0.1:8080", "password_file": CREDENTIAL}
    return data


def sh(*cmd: str, **kw: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, check=True, text=True, capture_output=True, **kw)


CACHE_NOTE = ["debootstrap and kernel cached in build/"]


def build_image(bundle: Path, upgrade: Path, config_text: str) -> dict[str, str]:
    """The guest's disk: the cached Debian root, the bundle installed by install.sh."""
    rows: dict[str, str] = {}
    started = time.monotonic()
    if not (BUILD / "base.done").exists() or not (BUILD / "kernel.done").exists():
        CACHE_NOTE[0] = "no build/ cache: debootstrap and kernel included"
    sh("sh", str(REPO / "tests" / "system" / "build_base.sh"), str(BUILD), timeout=900)
    rows["base"] = f"{time.monotonic() - started:.0f} s"
    if ROOT.exists():
        shutil.rmtree(ROOT)
    sh("cp", "-a", str(BUILD / "base"), str(ROOT))
    kv = next((BUILD / "kernel" / "lib" / "modules").iterdir()).name
    (ROOT / "lib" / "modules").mkdir(parents=True, exist_ok=True)
    sh("cp", "-a", str(BUILD / "kernel" / "lib" / "modules" / kv), str(ROOT / "lib" / "modules"))
    (ROOT / "etc" / "fstab").write_text(
        "/dev/vda / ext4 rw 0 1\n"
        "out /out 9p trans=virtio,version=9p2000.L,msize=262144,nofail 0 0\n")
    (ROOT / "out").mkdir(exist_ok=True)
    (ROOT / "etc" / "hostname").write_text("cab-box\n")
    (ROOT / "var" / "log" / "journal").mkdir(parents=True, exist_ok=True)
    (ROOT / "etc" / "udev" / "rules.d" / "98-systest-ports.rules").write_text(GUEST_RULES)
    for rel, text in GUEST_FILES.items():
        (ROOT / rel).parent.mkdir(parents=True, exist_ok=True)
        (ROOT / rel).write_text(text)
    (wants_dir := ROOT / "etc/systemd/system/multi-user.target.wants").mkdir(
        parents=True, exist_ok=True)
    (wants_dir / "vcan0.service").symlink_to("/etc/systemd/system/vcan0.service")
    (ROOT / "etc/sowgate").mkdir(parents=True, exist_ok=True)
    password = ROOT / "etc/sowgate/dashboard-password"
    password.write_text(DASHBOARD_PASSWORD + "\n")
    password.chmod(0o600)  # root only: the dynamic user gets it through LoadCredential
    lib = ROOT / "usr" / "local" / "lib" / "systest"
    lib.mkdir(parents=True, exist_ok=True)
    for name in ("guest.py", "probe.py"):
        shutil.copy(REPO / "tests" / "system" / name, lib / name)
    unit = ROOT / "etc" / "systemd" / "system" / "systest.service"
    unit.write_text(RUNNER_UNIT)
    wants = ROOT / "etc" / "systemd" / "system" / "multi-user.target.wants"
    wants.mkdir(parents=True, exist_ok=True)
    (wants / "systest.service").symlink_to("/etc/systemd/system/systest.service")
    # the fitter's config is there first: install.sh keeps it and checks it
    (ROOT / "etc" / "sowgate").mkdir(parents=True, exist_ok=True)
    (ROOT / "etc" / "sowgate" / "sowgate.toml").write_text(config_text)
    with tarfile.open(bundle) as tar:
        tar.extractall(ROOT / "root", filter="data")
    top = bundle.name.removesuffix(".tar.gz")
    started = time.monotonic()
    # offline: a new network namespace has only a down loopback
    done = subprocess.run(
        ["unshare", "--net", "--mount", "sh", "-c",
         f"mount -t proc proc {ROOT}/proc && exec chroot {ROOT} /root/{top}/install.sh"],
        capture_output=True, text=True, timeout=600)
    (BUILD / "install.log").write_text(done.stdout + done.stderr)
    if done.returncode != 0:
        raise SystemExit(f"install.sh failed in the image:\n{done.stdout}\n{done.stderr}")
    rows["install"] = (f"install.sh in the image, no network: {time.monotonic() - started:.0f} s, "
                       + "; ".join(ln.removeprefix("install.sh: ") for ln in
                                   done.stdout.splitlines() if ln.startswith("install.sh"))[:600])
    shutil.rmtree(ROOT / "root" / top)
    # the newer build, unpacked where the guest's upgrade step finds it
    with tarfile.open(upgrade) as tar:
        tar.extractall(ROOT / "root" / "upgrade", filter="data")
    DISK.unlink(missing_ok=True)
    sh("mkfs.ext4", "-q", "-F", "-d", str(ROOT), str(DISK), "2G", timeout=300)
    return rows


def build_upgrade(bundle: Path) -> Path:
    """A newer build of this checkout for the upgrade step: the same tree with a local version
    suffix (0.1.0 -> 0.1.0+systest.2), its wheel bundled with the first bundle's dependency
    wheels (the same constraints.txt) by systemd/bundle.py's own writer."""
    import importlib.util

    src, wheels = BUILD / "upgrade-src", BUILD / "upgrade-wheels"
    for folder in (src, wheels):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    listed = sh("git", "ls-files", "-z", "--cached", "--others", "--exclude-standard",
                cwd=REPO).stdout.split("\0")
    for rel in filter(None, listed):
        if (REPO / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, src / rel)
    pyproject = (src / "pyproject.toml").read_text()
    old = re.search(r'^version = "([^"]+)"$', pyproject, re.M)
    assert old is not None, "pyproject.toml has no version line"
    version = f"{old.group(1)}+systest.2"
    (src / "pyproject.toml").write_text(pyproject.replace(old.group(0), f'version = "{version}"'))
    sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(wheels), str(src),
       timeout=600)
    with tarfile.open(bundle) as tar:
        deps = [m for m in tar.getmembers() if m.name.endswith(".whl")
                and not Path(m.name).name.startswith("sowgate-")]
        for m in deps:
            m.name = Path(m.name).name
            tar.extract(m, wheels, filter="data")
    spec = importlib.util.spec_from_file_location("bundle", REPO / "systemd" / "bundle.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return Path(mod.write_bundle(BUILD / "upgrade-dist", version, "x86_64",
                                 sorted(wheels.glob("*.whl"))))


class Bridge:
    """A null-modem cable between a simulator's port and a qemu pty (both opened raw)."""

    def __init__(self, a: str, b: str) -> None:
        self.fds = []
        for path in (a, b):
            fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            tty.setraw(fd)
            self.fds.append(fd)
        loop = asyncio.get_running_loop()
        loop.add_reader(self.fds[0], self._pump, self.fds[0], self.fds[1])
        loop.add_reader(self.fds[1], self._pump, self.fds[1], self.fds[0])

    def _pump(self, src: int, dst: int) -> None:
        try:
            data = os.read(src, 4096)
        except (BlockingIOError, OSError):
            return
        # a line nobody reads (the guest's port not open yet, its FIFO full) drops bytes, as
        # a real serial line does; never block the event loop the simulator runs on
        with contextlib.suppress(OSError):
            os.write(dst, data)

    def close(self) -> None:
        loop = asyncio.get_running_loop()
        for fd in self.fds:
            loop.remove_reader(fd)
            with contextlib.suppress(OSError):
                os.close(fd)


def qemu_command() -> list[str]:
    # -cpu max: numpy's wheels need x86-64-v2 (SSE4.2, POPCNT); TCG's default qemu64 CPU
    # lacks them and the daemon dies of SIGILL importing numpy (a real cab box PC has them)
    cmd = ["qemu-system-x86_64", "-accel", "tcg,thread=multi", "-cpu", "max", "-smp", "2",
           "-m", "1024",
           "-nographic", "-no-reboot", "-nic", "none",
           "-kernel", str(BUILD / "vmlinuz"), "-initrd", str(BUILD / "initrd.img"),
           "-append", "root=/dev/vda rw console=ttyS0 quiet panic=-1 8250.nr_uarts=8",
           "-drive", f"file={DISK},format=raw,if=virtio",
           "-virtfs", f"local,path={OUT},mount_tag=out,security_model=none,id=out",
           "-serial", "mon:stdio"]
    for n, tty_name in enumerate(PORTS, start=1):
        cmd += ["-chardev", f"pty,id=s{n}"]
        # the PC has four legacy ports (ttyS0..3): the fourth device is a PCI UART (ttyS4)
        cmd += ["-serial", f"chardev:s{n}"] if n < 4 else ["-device", f"pci-serial,chardev=s{n}"]
        assert tty_name == f"ttyS{n}"
    return cmd


async def operate(machine: Any, settings: Any) -> None:
    code = {"rapeseed": 1, "wheat": 2}[settings.control.crop]
    rate = settings.control.crops[settings.control.crop].default_rate_kg_ha
    machine.hmi.select(code, rate)
    await asyncio.sleep(0.5)
    machine.hmi.press_start()


async def host_side(machine: Any, settings: Any, qemu: asyncio.subprocess.Process,
                    rows: list[dict[str, Any]]) -> None:
    """Answer the guest's flags; sample duty against the radar's speed while it sows."""
    if (OUT / "phase2").exists():  # after the power cut the guest needs nothing from here
        await qemu.wait()
        return
    samples: list[tuple[float, float]] = []
    answered: set[str] = set()
    while qemu.returncode is None:
        await asyncio.sleep(0.25)
        pose = machine.pose()
        duty = machine.rs485.duty_pct["motor"]
        # steady sowing with the motor driven: the same speed for the last 6 s (the speed
        # filter and the motor lag a change by a few seconds)
        steady = abs(machine.pose_at(machine.now() - 6.0).speed_kmh - pose.speed_kmh) < 0.1
        if duty > 0 and pose.tilt_deg < 0 and pose.speed_kmh > 0.5 and steady:
            samples.append((pose.speed_kmh, duty))
        if "cut" not in answered and (OUT / "flag-cut").exists() \
                and not (OUT / "phase2").exists():
            answered.add("cut")
            qemu.kill()  # the power cut: no shutdown, no sync in the guest
            break
        # flag-operate[-X]: press Start on the touchscreen, answer host-started[-X]
        for flag_file in sorted(OUT.glob("flag-operate*")):
            name = flag_file.name.removeprefix("flag-")
            if name not in answered:
                answered.add(name)
                await operate(machine, settings)
                (OUT / f"host-{name.replace('operate', 'started', 1)}").write_text("")
        if "frozen" not in answered and (OUT / "flag-frozen").exists():
            answered.add("frozen")
            t0 = time.monotonic()
            while time.monotonic() - t0 < 15 and any(machine.rs485.duty_pct.values()):  # noqa: ASYNC110
                await asyncio.sleep(0.05)
            off = not any(machine.rs485.duty_pct.values())
            rows.append({"check": "pwm_comm_loss", "ok": off,
                         "detail": f"PWM module set motor and fan to 0 by itself "
                                   f"{time.monotonic() - t0:.1f} s after the freeze "
                                   f"(comm_timeout_s {settings.actuators.comm_timeout_s:g})"
                         if off else "motor/fan still driven 15 s after the freeze"})
            (OUT / "host-pwm-checked").write_text("")
    SAMPLES.extend(samples)


SAMPLES: list[tuple[float, float]] = []  # (true speed km/h, motor duty %) over both boots


def duty_row() -> dict[str, Any]:
    samples = SAMPLES
    speeds = {round(s) for s, _ in samples}
    corr = statistics.correlation([s for s, _ in samples], [d for _, d in samples]) \
        if len(samples) > 3 and len(speeds) > 1 else float("nan")
    return {"check": "duty_follows_radar", "ok": corr > 0.7,
                 "detail": f"{len(samples)} samples of steady sowing at {sorted(speeds)} km/h "
                           f"(host side, the PWM module's duty register): correlation of motor "
                           f"duty with the true speed {corr:.2f}"}


async def boot_once(machine: Any, settings: Any, rows: list[dict[str, Any]],
                    console_name: str) -> None:
    """One qemu boot of the image, its ptys bridged to the simulator, until it powers off
    (or the guest asks for the power cut: then it is killed)."""
    console_path = BUILD / console_name
    console = console_path.open("wb")
    qemu = await asyncio.create_subprocess_exec(
        *qemu_command(), stdin=subprocess.DEVNULL, stdout=console, stderr=console)
    bridges: list[Bridge] = []
    try:
        ptys: dict[str, str] = {}
        waited = time.monotonic()
        while len(ptys) < len(PORTS):  # qemu says where each pty is on its stdout
            if qemu.returncode is not None or time.monotonic() - waited > 60:
                raise SystemExit(f"qemu did not open its ptys ({console_path})")
            await asyncio.sleep(0.1)
            text = console_path.read_text(errors="replace")
            for path, n in re.findall(r"redirected to (/dev/pts/\d+) \(label s(\d)\)", text):
                ptys[f"ttyS{n}"] = path
        devices = {"rs485": machine.rs485, "gnss": machine.gnss,
                   "seeds": machine.seed_tubes, "hmi": machine.hmi}
        for tty_name, name in PORTS.items():
            bridges.append(Bridge(devices[name].device_path, ptys[tty_name]))
        await asyncio.wait_for(
            asyncio.gather(host_side(machine, settings, qemu, rows), qemu.wait()),
            BOOT_TIMEOUT_S)
    except TimeoutError:
        rows.append({"check": "timeout", "ok": False,
                     "detail": f"the guest did not power off within {BOOT_TIMEOUT_S:.0f} s"})
    finally:
        if qemu.returncode is None:
            qemu.kill()
            await qemu.wait()
        for bridge in bridges:
            bridge.close()
        console.close()


async def run(bundle: Path) -> list[dict[str, Any]]:
    sys.path.insert(0, str(REPO))
    from simulator.machine import SimulatedMachine
    from simulator.plant import Drive, demo_drive

    rows: list[dict[str, Any]] = []
    started = time.monotonic()
    # eight rounds of the demo's field work (~40 min): the seed tubes follow the drive without
    # looping, so the whole run must fit in one pass (three rounds ran out during a slow run's
    # clock step: nothing sowed any more)
    drive = Drive(legs=demo_drive().legs * 8)
    async with SimulatedMachine(drive=drive, loop_drive=True, with_gnss=True,
                                with_seed_tubes=True) as machine:
        import tomli_w

        from gateway.config import parse_config

        config = guest_config(machine)
        settings = parse_config(config)
        upgrade = await asyncio.to_thread(build_upgrade, bundle)
        built = await asyncio.to_thread(build_image, bundle, upgrade, tomli_w.dumps(config))
        rows.append({"check": "image", "ok": True,
                     "detail": f"Debian 12 image with the bundle: {time.monotonic() - started:.0f}"
                               f" s (debootstrap and kernel cached: {built['base']})"})
        rows.append({"check": "install", "ok": True, "detail": built["install"]})
        shutil.rmtree(OUT, ignore_errors=True)
        OUT.mkdir(parents=True)
        boot = time.monotonic()
        await boot_once(machine, settings, rows, "console.log")
        if (OUT / "flag-cut").exists():  # the power cut: the same disk boots again
            (OUT / "phase2").write_text("")
            await boot_once(machine, settings, rows, "console-after-cut.log")
        rows.append(duty_row())
        rows.append({"check": "boot", "ok": not any(r["check"] == "timeout" for r in rows),
                     "detail": f"qemu ran {time.monotonic() - boot:.0f} s (boots, checks, "
                               f"power cut, poweroff)"})
    guest = OUT / "results.jsonl"
    if guest.exists():
        rows += [json.loads(line) for line in guest.read_text().splitlines() if line.strip()]
    else:
        rows.append({"check": "guest", "ok": False, "detail": "no results from the guest"})
    rows.append({"check": "total", "ok": True, "seconds": time.monotonic() - started,
                 "detail": f"{time.monotonic() - started:.0f} s for run.py (the bundle's "
                           f"build before it: make's); {CACHE_NOTE[0]}"})
    return rows


ORDER = ["image", "install", "boot", "runner", "start", "sows", "duty_follows_radar", "can",
         "bad_config", "upgrade", "watchdog", "pwm_comm_loss", "clock", "security", "sandbox",
         "other_tty", "dashboard", "journal", "rollback", "store_too_new", "power_cut",
         "after_cut_mqtt", "total"]


def table(rows: list[dict[str, Any]]) -> str:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                           capture_output=True, text=True).stdout.strip()
    rank = {name: n for n, name in enumerate(ORDER)}
    rows = sorted(rows, key=lambda r: rank.get(r["check"], len(ORDER)))
    took = next((r.get("seconds") for r in rows if r["check"] == "total"), None)
    lines = [f"Run {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, commit {commit}"
             f"{' (with uncommitted changes)' if dirty else ''}, `make system-test`"
             + (f" ({int(took) // 60} min {int(took) % 60} s, {CACHE_NOTE[0]})" if took else "")
             + ": "
             f"{sum(r['ok'] and not r.get('limit') for r in rows)} of "
             f"{sum(not r.get('limit') for r in rows)} checks hold.", "",
             "| check | result | what was seen |", "|---|---|---|"]
    for r in rows:
        detail = str(r["detail"]).replace("|", "\\|").replace("\n", " ")
        verdict = "not held (known)" if r.get("limit") else "ok" if r["ok"] else "**FAIL**"
        lines.append(f"| {r['check']} | {verdict} | {detail} |")
    return "\n".join(lines) + "\n"


def write_doc(text: str) -> None:
    if not DOC.exists():
        return
    doc = DOC.read_text()
    if BEGIN in doc and END in doc:
        head, rest = doc.split(BEGIN, 1)
        DOC.write_text(head + BEGIN + "\n" + text + END + rest.split(END, 1)[1])


def main() -> int:
    bundle = Path(sys.argv[1])
    if os.geteuid() != 0:
        raise SystemExit("make system-test needs root (debootstrap, chroot, mkfs -d)")
    rows = asyncio.run(run(bundle))
    text = table(rows)
    (BUILD / "result.md").write_text(text)
    write_doc(text)
    print(text)
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
