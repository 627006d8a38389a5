"""The checks inside the guest (run by systest.service with the installed sowgate's python).

Talks to the host through the 9p share /out: each result is one JSON line in
/out/results.jsonl; a file /out/flag-<name> tells the host a moment has come (press Start on
the touchscreen, the control loop is frozen now), and the host answers the same way
(/out/host-<name>). Uses only what the bundle installed (paho-mqtt) and the standard library.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import signal
import sqlite3
import subprocess
import threading
import time
from pathlib import Path

OUT = Path("/out")
CONFIG = Path("/etc/sowgate/sowgate.toml")
STATE = Path("/var/lib/private/sowgate")
STORE = STATE / "records.sqlite3"
T0 = time.monotonic()


def result(check: str, ok: bool, detail: str, **extra: object) -> None:
    line = {"check": check, "ok": bool(ok), "detail": detail,
            "t_s": round(time.monotonic() - T0, 1), **extra}
    with (OUT / "results.jsonl").open("a") as f:
        f.write(json.dumps(line) + "\n")
    print(line, flush=True)


def sh(*cmd: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def show(unit: str = "sowgate", *props: str) -> dict[str, str]:
    out = sh("systemctl", "show", unit, *(f"--property={p}" for p in props)).stdout
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


def flag(name: str) -> None:
    (OUT / f"flag-{name}").write_text(str(time.time()))


def wait_host(name: str, timeout: float = 60) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if (OUT / f"host-{name}").exists():
            return True
        time.sleep(0.2)
    return False


def store_ids() -> tuple[int, int, int]:
    """(count, min id, max id) of the seed records, read-only next to the running daemon."""
    db = sqlite3.connect(f"file:{STORE}?mode=ro", uri=True)
    try:
        n, lo, hi = db.execute("SELECT count(*), min(id), max(id) FROM seeds").fetchone()
        return int(n), int(lo or 0), int(hi or 0)
    finally:
        db.close()


# gateway/recording/store/ids.py ID_BLOCK: the store reserves ids a block ahead (the guest runs
# this file with its own python3, without sowgate's packages); after an unclean stop (a
# watchdog kill, a power cut, a stop that outlived TimeoutStopSec) the next run starts past
# the reservation, so an id is never handed out twice: ids then jump, by less than two blocks
ID_BLOCK = 20_000


def id_jumps(since: int) -> list[tuple[int, int]]:
    """The ids missing between stored ids from ``since`` on: (first, last) of each jump."""
    db = sqlite3.connect(f"file:{STORE}?mode=ro", uri=True)
    try:
        ids = [r[0] for r in db.execute(
            "SELECT id FROM seeds WHERE id >= (SELECT coalesce(max(id), 0) FROM seeds "
            "WHERE id <= ?) ORDER BY id", (since,))]
    finally:
        db.close()
    return [(a + 1, b - 1) for a, b in itertools.pairwise(ids) if b > a + 1]


def ids_go_on(since: int, restarts: int) -> tuple[bool, str]:
    """Ids after ``since`` never reused and without holes but for at most one jump per
    restart, each shorter than two reservation blocks: (holds, what was seen)."""
    jumps = id_jumps(since)
    ok = len(jumps) <= restarts and all(hi - lo + 1 < 2 * ID_BLOCK for lo, hi in jumps)
    seen = ("contiguous" if not jumps else "jumps past reserved ids at " + ", ".join(
        f"{lo}..{hi}" for lo, hi in jumps[:4]))
    return ok, f"{seen} (allowed: {restarts} jump{'s' if restarts != 1 else ''} < {2 * ID_BLOCK})"


def integrity() -> str:
    db = sqlite3.connect(f"file:{STORE}?mode=ro", uri=True)
    try:
        return str(db.execute("PRAGMA integrity_check").fetchone()[0])
    finally:
        db.close()


class Mqtt:
    """Everything under sowgate/# on the guest's own mosquitto."""

    def __init__(self) -> None:
        import paho.mqtt.client as mqtt

        self.seeds = 0
        self.seed_ids: list[int] = []  # in arrival order
        self.states: list[dict[str, object]] = []
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        self.client.on_message = self._on_message
        self.client.on_connect = lambda c, *a: c.subscribe("sowgate/#", qos=1)
        self.client.connect("127.0.0.1", 1883)
        self.client.loop_start()

    def _on_message(self, client: object, userdata: object, msg: object) -> None:
        topic: str = msg.topic  # type: ignore[attr-defined]
        with self.lock:
            if topic.endswith("/seeds"):
                payload = json.loads(msg.payload)  # type: ignore[attr-defined]
                self.seeds += len(payload.get("records", []))
                self.seed_ids += [int(r["id"]) for r in payload.get("records", [])]
            elif topic.endswith("/state"):
                self.states.append(json.loads(msg.payload))  # type: ignore[attr-defined]


def check_start(mqtt: Mqtt) -> None:
    # sowgate is enabled and started at boot: `systemctl start` joins that start job and
    # returns when it is done, i.e. at READY=1 (a second start would cost another minute of
    # emulated imports)
    started = time.monotonic()
    done = sh("systemctl", "start", "sowgate", timeout=450)
    took = time.monotonic() - started
    s = show("sowgate", "ActiveState", "SubState", "StatusText", "Type", "MainPID",
             "InactiveExitTimestampMonotonic", "ActiveEnterTimestampMonotonic")
    start_s = (int(s.get("ActiveEnterTimestampMonotonic") or 0)
               - int(s.get("InactiveExitTimestampMonotonic") or 0)) / 1e6
    result("start", done.returncode == 0 and s.get("ActiveState") == "active",
           f"started at boot; active {start_s:.1f} s after its start began (Type={s.get('Type')}, "
           f"at READY=1; `systemctl start` waited {took:.1f} s more): "
           f"{s.get('ActiveState')}/{s.get('SubState')}, STATUS=\"{s.get('StatusText')}\"",
           journal=[] if done.returncode == 0 else sh(
               "journalctl", "-u", "sowgate", "-n", "25", "-o", "cat").stdout.splitlines())
    flag("operate")  # the host presses Start on the touchscreen
    wait_host("started", 30)
    # the simulated drive loops through sowing, turns and a stop: wait for steady sowing
    end = time.monotonic() + 90
    while time.monotonic() < end:
        time.sleep(2)
        with mqtt.lock:
            states = list(mqtt.states)
            seeds = mqtt.seeds
        moving = [st for st in states if (st.get("speed_kmh") or 0) > 1.0
                  and st.get("work_state") == "seeding"
                  and float(st.get("motor_duty_pct") or 0) > 0]
        if len(moving) >= 5 and seeds > 0:
            break
    duty = [float(st.get("motor_duty_pct") or 0) for st in moving]
    speed = [float(st.get("speed_kmh") or 0) for st in moving]
    result("sows", len(moving) >= 5 and seeds > 0,
           f"{len(states)} state messages, {len(moving)} seeding at "
           f"{min(speed, default=0):.1f}..{max(speed, default=0):.1f} km/h with motor duty "
           f"{min(duty, default=0):.1f}..{max(duty, default=0):.1f} %; "
           f"{seeds} seed records on MQTT in the guest's mosquitto",
           work_states=sorted({str(st.get("work_state")) for st in states}))


def check_bad_config() -> None:
    good = CONFIG.read_bytes()
    try:
        # a value out of range: check-config and the daemon name the key, exit 78
        CONFIG.write_text(good.decode().replace("[rs485]\n", "[rs485]\npoll_hz = -3.0\n", 1))
        sh("systemctl", "restart", "sowgate", timeout=450)
        time.sleep(9)  # RestartSec=2s: a loop would have restarted several times by now
        s = show("sowgate", "ActiveState", "Result", "ExecMainStatus", "NRestarts")
        log = sh("journalctl", "-u", "sowgate", "-n", "5", "-o", "cat").stdout.strip()
        result("bad_config", s.get("ExecMainStatus") == "78" and s.get("NRestarts") == "0"
               and s.get("ActiveState") == "failed",
               f"exit {s.get('ExecMainStatus')}, {s.get('ActiveState')} ({s.get('Result')}), "
               f"restarts {s.get('NRestarts')} in 9 s", journal=log[-400:])
    finally:
        # the fitter fixes the config; the upgrade below (install.sh) checks it and restarts
        CONFIG.write_bytes(good)
        sh("systemctl", "reset-failed", "sowgate")


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:12] if path.exists() else "missing"


def opt_links() -> str:
    return " ".join(f"{n} -> {os.readlink(f'/opt/sowgate/{n}')}"
                    for n in ("current", "previous") if os.path.islink(f"/opt/sowgate/{n}"))


def seed_calibration() -> None:
    """A field calibration as `sowgate calibrate tilt` saves it (the inclinometer's zero, the
    config's own value: the machine sows the same), owned by the service's dynamic user."""
    import tomllib

    from gateway.calibration.fits import CalibrationStore, save_tilt, tilt_level_zero

    zero = float(tomllib.loads(CONFIG.read_text()).get("inclinometer", {})
                 .get("zero_offset_deg", 0.0))
    save_tilt(CalibrationStore(STATE), "tilt.inclinometer", tilt_level_zero([zero]))
    owner = STATE.stat()
    os.chown(STATE / "calibration.json", owner.st_uid, owner.st_gid)


def kept_files() -> dict[str, str]:
    return {"config": sha(CONFIG), "calibration": sha(STATE / "calibration.json"),
            "udev rule": sha(Path("/etc/udev/rules.d/99-sowgate.rules"))}


def wait_new_records(hi0: int, timeout: float = 150) -> tuple[int, int, int]:
    end = time.monotonic() + timeout  # the simulated drive may be turning or standing
    n, lo, hi = store_ids()
    while time.monotonic() < end and hi <= hi0:
        time.sleep(2)
        n, lo, hi = store_ids()
    return n, lo, hi


def install_bundle(*args: str) -> tuple[subprocess.CompletedProcess[str], float]:
    bundle = next(Path("/root/upgrade").glob("sowgate-*"))
    started = time.monotonic()
    done = sh(str(bundle / "install.sh"), *args, timeout=900)
    return done, time.monotonic() - started


def check_upgrade() -> None:
    """install.sh of the newer build on the running box (no network: the guest has none)."""
    seed_calibration()
    before = kept_files()
    _, _, hi0 = store_ids()
    links0 = opt_links()
    done, took = install_bundle()
    s = show("sowgate", "ActiveState", "StatusText")
    flag("operate-after-upgrade")
    wait_host("started-after-upgrade", 30)
    _, _, hi = wait_new_records(hi0)
    ids_ok, ids_seen = ids_go_on(hi0, restarts=1)
    after = kept_files()
    devices = Path("/etc/systemd/system/sowgate.service.d/devices.conf")
    allow = [ln for ln in devices.read_text().splitlines() if ln.startswith("DeviceAllow=")] \
        if devices.exists() else []
    current = os.readlink("/opt/sowgate/current")
    result("upgrade", done.returncode == 0 and "+systest.2" in current
           and os.readlink("/opt/sowgate/previous") != current
           and s.get("ActiveState") == "active" and before == after and hi > hi0
           and ids_ok,
           f"install.sh of the newer bundle (offline, {took:.0f} s, exit {done.returncode}): "
           f"{links0} => {opt_links()}; sowgate {s.get('ActiveState')} on it; config, "
           f"calibration.json and udev rule unchanged: {before == after} ({after}); seed ids "
           f"up to {hi0} before, {hi} after: {ids_seen}; "
           f"devices.conf regenerated with udev up: {' '.join(allow)}",
           output=(done.stdout + done.stderr)[-1500:])


def check_rollback() -> None:
    before = kept_files()
    _, _, hi0 = store_ids()
    links0 = opt_links()
    done, took = install_bundle("--rollback")
    s = show("sowgate", "ActiveState")
    flag("operate-after-rollback")
    wait_host("started-after-rollback", 30)
    _, _, hi = wait_new_records(hi0)
    ids_ok, ids_seen = ids_go_on(hi0, restarts=1)
    current = os.readlink("/opt/sowgate/current")
    result("rollback", done.returncode == 0 and "+" not in current
           and s.get("ActiveState") == "active" and kept_files() == before and hi > hi0
           and ids_ok,
           f"install.sh --rollback ({took:.0f} s, exit {done.returncode}): {links0} => "
           f"{opt_links()}; sowgate {s.get('ActiveState')} on the first version; config and "
           f"calibration unchanged: {kept_files() == before}; the store the newer build wrote: "
           f"seed ids up to {hi0} before, {hi} after: {ids_seen}",
           output=(done.stdout + done.stderr)[-1500:])


def set_store_version(version: int) -> None:
    owner = STATE.stat()
    db = sqlite3.connect(STORE)
    try:
        db.execute(f"PRAGMA user_version = {version}")
        db.commit()
    finally:
        db.close()
    for path in STATE.glob("records.sqlite3*"):  # WAL files root may have made
        os.chown(path, owner.st_uid, owner.st_gid)


def check_store_too_new() -> None:
    """A store a newer schema wrote (user_version above this version's): refused, exit 78."""
    sh("systemctl", "stop", "sowgate", timeout=120)
    set_store_version(99)
    cursor = journal_cursor()
    started = sh("systemctl", "start", "sowgate", timeout=450)
    time.sleep(6)  # RestartSec=2s: a loop would have restarted by now
    s = show("sowgate", "ActiveState", "Result", "ExecMainStatus", "NRestarts")
    said = sh("journalctl", "-u", "sowgate", "-o", "cat", "--no-pager",
              f"--after-cursor={cursor}").stdout
    line = next((ln for ln in said.splitlines() if "schema version" in ln), "")
    n, lo, hi = store_ids()
    set_store_version(1)
    sh("systemctl", "reset-failed", "sowgate")
    again = sh("systemctl", "start", "sowgate", timeout=450)
    result("store_too_new", started.returncode != 0 and s.get("ExecMainStatus") == "78"
           and s.get("NRestarts") == "0" and "written by a newer sowgate" in line
           and again.returncode == 0,
           f"store stamped schema 99: sowgate exit {s.get('ExecMainStatus')}, "
           f"{s.get('ActiveState')} ({s.get('Result')}), restarts {s.get('NRestarts')}; "
           f"journal: \"{line[:230]}\"; records untouched ({n}, ids {lo}..{hi}); stamped back "
           f"to 1: started again: {again.returncode == 0}")


def journal_cursor() -> str:
    out = sh("journalctl", "-n", "0", "--show-cursor", "--no-pager").stdout
    return next((ln.split("cursor: ", 1)[1] for ln in out.splitlines() if "cursor: " in ln), "")


class CanPeer(threading.Thread):
    """The fertiliser channel's metering controller (node 1) on vcan0, as little as answers:
    each target-speed frame gets a status frame at that speed (protocol/can_metering.py)."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.commands = 0
        self.enabled = 0
        self.max_rpm = 0.0
        self.statuses = 0
        self.error = ""
        self.started_cursor = journal_cursor()

    def run(self) -> None:
        import socket
        import struct

        from protocol import can_metering as cm

        fmt = "=IB3x8s"
        try:
            sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
            sock.bind(("vcan0",))
            while True:
                can_id, dlc, data = struct.unpack(fmt, sock.recv(16))
                can_id &= socket.CAN_EFF_MASK
                kind = cm.frame_kind(can_id)
                if kind is None or kind[0] != "command":
                    continue
                cmd = cm.decode_command(can_id, data[:dlc])
                self.commands += 1
                if cmd.enable and cmd.target_rpm > 0:
                    self.enabled += 1
                    self.max_rpm = max(self.max_rpm, cmd.target_rpm)
                fid, payload = cm.encode_status(cm.MeterStatus(
                    node_id=cmd.node_id, measured_rpm=cmd.target_rpm if cmd.enable else 0.0,
                    enabled=cmd.enable, at_target=True, stalled=False, fault_active=False,
                    fault=cm.FaultCode.NONE, raw_fault_code=0, sequence_echo=cmd.sequence,
                    valve_pct=30.0 if cmd.enable else 0.0))
                sock.send(struct.pack(fmt, fid, len(payload), payload.ljust(8, b"\0")))
                self.statuses += 1
        except Exception as exc:  # reported by check_can
            self.error = f"{type(exc).__name__}: {exc}"


def check_can(peer: CanPeer) -> None:
    link = sh("ip", "-details", "link", "show", "vcan0").stdout
    log = sh("journalctl", "-u", "sowgate", "-o", "cat", "--no-pager",
             f"--after-cursor={peer.started_cursor}").stdout
    lost = [ln for ln in log.splitlines() if "feedback_lost" in ln or "feedback lost" in ln]
    s = show("sowgate", "RestrictAddressFamilies")
    # what this row proves is AF_CAN under the shipped RestrictAddressFamilies: frames both
    # ways, every command answered. A feedback_lost under emulation (the guest's CPU is ~20x
    # slower, the daemon's CAN poll can miss its deadline once) is reported, not judged: the
    # alarm's logic is proven on python-can's virtual bus
    # (tests/integration/test_can_supervision.py)
    result("can", peer.commands > 0 and peer.enabled > 0 and not peer.error
           and peer.statuses >= peer.commands - 1,
           f"vcan0 {'up' if 'UP' in link else 'DOWN'} (vcan module from the initrd); the daemon "
           f"under RestrictAddressFamilies={s.get('RestrictAddressFamilies')} sent "
           f"{peer.commands} target-speed frames to node 1, {peer.enabled} of them enabled "
           f"(up to {peer.max_rpm:.1f} r/min while sowing); a controller in the guest answered "
           f"{peer.statuses} status frames; feedback_lost in the journal since: {len(lost)}"
           + (f"; peer error {peer.error}" if peer.error else ""))


def check_clock(mqtt: Mqtt) -> None:
    """The system clock moved while sowing (a box without network time, set by hand or by a
    late NTP): records keep the GNSS time, ids stay contiguous, MQTT order holds, no stall."""
    with mqtt.lock:
        k0, states0 = len(mqtt.seed_ids), len(mqtt.states)
    _, _, hi0 = store_ids()
    pid0 = show("sowgate", "MainPID", "NRestarts")
    wall0, mono0 = time.time(), time.monotonic()

    def true_now() -> float:
        return wall0 + time.monotonic() - mono0

    steps = [3 * 3600.0, 0.0, -3 * 3600.0, 0.0]  # +3 h, back, -3 h, back
    seen: list[str] = []
    try:
        for offset in steps:
            sh("date", "-u", "-s", f"@{true_now() + offset:.3f}")
            seen.append(time.strftime("%H:%M", time.gmtime()))
            time.sleep(8)
    finally:
        sh("date", "-u", "-s", f"@{true_now():.3f}")
    wait_new_records(hi0 + 5, 60)
    end = true_now()
    db = sqlite3.connect(f"file:{STORE}?mode=ro", uri=True)
    try:
        utc = [r[0] / 1e6 for r in db.execute("SELECT utc_us FROM seeds WHERE id > ?", (hi0,))]
    finally:
        db.close()
    off = [u - end for u in utc]
    with mqtt.lock:
        ids = mqtt.seed_ids[k0:]
        states = len(mqtt.states) - states0
    unique = list(dict.fromkeys(ids))  # a QoS 1 redelivery may repeat, never reorder
    in_order = all(b > a for a, b in itertools.pairwise(unique))
    pid1 = show("sowgate", "MainPID", "NRestarts")
    worst = max((abs(o) for o in off), default=float("inf"))
    ids_ok, ids_seen = ids_go_on(hi0, restarts=0)
    result("clock", bool(utc) and worst < 120 and ids_ok and in_order and bool(ids)
           and pid1 == pid0 and states > 0,
           f"system clock set to +3 h, back, -3 h, back (guest clock read {', '.join(seen)}) "
           f"over {end - wall0:.0f} s of sowing: {len(utc)} records stored meanwhile, their "
           f"UTC (GNSS) within {worst:.0f} s of the true time (a system-clock stamp would be "
           f"off by 3 h); ids after {hi0}: {ids_seen}; {len(unique)} seed "
           f"ids on MQTT in increasing order: {in_order}; {states} state messages; main PID "
           f"and restarts unchanged: {pid1 == pid0} ({pid1})")


def check_watchdog() -> None:
    before = show("sowgate", "MainPID", "NRestarts", "WatchdogUSec")
    _, _, hi0 = store_ids()
    # the dashboard takes a minute to import under emulation: let it start meanwhile
    sh("systemctl", "start", "--no-block", "sowgate-dashboard")
    pid = before["MainPID"]
    os.kill(int(pid), signal.SIGSTOP)
    frozen = time.monotonic()
    flag("frozen")  # the host watches the PWM module's comm-loss timeout
    killed_after = active_after = None
    while time.monotonic() - frozen < 450 and active_after is None:
        now = show("sowgate", "MainPID", "ActiveState")
        if killed_after is None and now.get("MainPID") != pid:
            killed_after = time.monotonic() - frozen
        if killed_after is not None and now.get("ActiveState") == "active" \
                and now.get("MainPID") not in (pid, "0"):
            active_after = time.monotonic() - frozen
        time.sleep(0.25)
    wait_host("pwm-checked", 20)
    # a restarted daemon starts stopped (safe): the operator presses Start again
    flag("operate-after-restart")
    wait_host("started-after-restart", 30)
    end = time.monotonic() + 120  # the simulated drive may be turning or standing
    _, _, hi1 = store_ids()
    while time.monotonic() < end and hi1 <= hi0:
        time.sleep(2)
        _, _, hi1 = store_ids()
    after = show("sowgate", "NRestarts")
    journal = sh("journalctl", "-u", "sowgate", "-o", "cat", "--since", "-300s").stdout.lower()
    contiguous, ids_seen = ids_go_on(hi0, restarts=1)
    watchdog_s = int(before.get("WatchdogUSec", "10s").rstrip("s") or 10)
    result("watchdog", killed_after is not None and killed_after <= watchdog_s + 5
           and active_after is not None and hi1 > hi0 and contiguous,
           f"SIGSTOP of the main process: systemd's watchdog killed it after "
           f"{killed_after if killed_after is not None else -1:.1f} s (WatchdogSec={watchdog_s}s; "
           f"'watchdog timeout' in the journal: {'watchdog timeout' in journal}), active again "
           f"after {active_after if active_after is not None else -1:.1f} s (restarts "
           f"{before.get('NRestarts')} -> {after.get('NRestarts')}); seed ids up to {hi0} "
           f"before, {hi1} after: {ids_seen}; "
           f"integrity_check: {integrity()}")


def check_hardening() -> None:
    scores = {}
    for unit in ("sowgate", "sowgate-dashboard"):
        out = sh("systemd-analyze", "security", f"{unit}.service", "--no-pager").stdout
        last = [ln for ln in out.splitlines() if "Overall exposure level" in ln]
        scores[unit] = float(last[-1].split(":")[1].split()[0]) if last else 99.0
    result("security", all(v <= 2.5 for v in scores.values()),
           "systemd-analyze security in the guest: " +
           ", ".join(f"{u} {v:.1f}" for u, v in scores.items()))
    # the shipped unit's sandbox around a probe instead of the daemon (ExecStart replaced only)
    unit = Path("/etc/systemd/system/sowgate.service").read_text()
    probe = Path("/run/systemd/system/sowgate-probe.service")
    exec_line = "ExecStart=/opt/sowgate/current/bin/python /usr/local/lib/systest/probe.py"
    probe.write_text("\n".join(exec_line if ln.startswith("ExecStart=") else
                               ("Type=exec" if ln.startswith("Type=") else ln)
                               for ln in unit.splitlines()
                               if not ln.startswith(("WatchdogSec", "NotifyAccess"))) + "\n")
    # with the unit's drop-ins: devices.conf (install.sh: the configured ports only)
    dropins = Path("/run/systemd/system/sowgate-probe.service.d")
    dropins.mkdir(parents=True, exist_ok=True)
    for conf in Path("/etc/systemd/system/sowgate.service.d").glob("*.conf"):
        (dropins / conf.name).write_text(conf.read_text())
    sh("systemctl", "daemon-reload")
    sh("systemctl", "start", "sowgate-probe", timeout=300)
    got: dict[str, str] = {}
    end = time.monotonic() + 30
    while time.monotonic() < end and not got:
        log = sh("journalctl", "-u", "sowgate-probe", "-o", "cat", "--no-pager").stdout
        lines = [ln for ln in log.splitlines() if ln.startswith("probe {")]
        got = json.loads(lines[-1][len("probe "):]) if lines else {}
        time.sleep(0.5)
    # "refused" = any error: file permissions (EACCES) may answer before the device cgroup
    # (EPERM) or the read-only mount (EROFS); the 0666 devices show the cgroup itself
    want = {"open /dev/ttyS2 (configured)": "ok",
            "open /dev/ttyS0 (console, not configured)": "refused",
            "open /dev/net/tun (mode 0666)": "EPERM", "open /dev/fuse (mode 0666)": "EPERM",
            "open /dev/vda (disk)": "refused", "write /var/lib/sowgate": "ok",
            "write /etc/sowgate": "refused", "write /opt/sowgate": "refused",
            "write /usr/bin": "refused", "socket AF_PACKET": "EAFNOSUPPORT"}

    def holds(key: str) -> bool:
        seen = got.get(key)
        return seen not in (None, "ok") if want[key] == "refused" else seen == want[key]

    bad = [k for k in want if not holds(k)]
    result("sandbox", not bad,
           "shipped unit around a probe: " + "; ".join(f"{k}: {got.get(k)}" for k in want)
           + (f" (not as expected: {bad})" if bad else ""))
    check_device_cgroup()


def check_device_cgroup() -> None:
    """The running sowgate.service's own device cgroup (the shipped unit + install.sh's
    devices.conf): a root process moved into that cgroup opens the configured ports, and
    gets EPERM for every other serial port, whatever its file mode (root passes those)."""
    s = show("sowgate", "ControlGroup", "DeviceAllow", "DevicePolicy", "MainPID")
    cgroup = Path("/sys/fs/cgroup") / s.get("ControlGroup", "/").lstrip("/")
    ports = {"/dev/sowgate-rs485": "configured", "/dev/sowgate-gnss": "configured",
             "/dev/sowgate-seeds": "configured", "/dev/sowgate-hmi": "configured",
             "/dev/ttyS0": "console", "/dev/ttyS5": "not configured",
             "/dev/ttyS7": "not configured"}
    code = ("import errno, json, os, sys\n"
            "open(sys.argv[1] + '/cgroup.procs', 'w').write(str(os.getpid()))\n"
            "out = {}\n"
            "for path in sys.argv[2:]:\n"
            "    try:\n"
            "        os.close(os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK))\n"
            "        out[path] = 'ok'\n"
            "    except OSError as exc:\n"
            "        out[path] = errno.errorcode.get(exc.errno, str(exc))\n"
            "print(json.dumps(out))\n")
    done = sh("python3", "-c", code, str(cgroup), *ports, timeout=60)
    outside = {p: "ok" for p in ports}
    for path in ports:  # the same opens from the runner's own cgroup: all allowed
        try:
            os.close(os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK))
        except OSError as exc:
            outside[path] = errno_name(exc)
    try:
        got = json.loads(done.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        got = {}
    # a configured port may be busy (EBUSY: the daemon holds it exclusively) but never EPERM
    ok = all(got.get(p) not in (None, "EPERM") for p, k in ports.items() if k == "configured") \
        and all(got.get(p) == "EPERM" for p, k in ports.items() if k != "configured") \
        and all(v != "EPERM" for v in outside.values())
    allow = s.get("DeviceAllow", "")
    result("other_tty", ok,
           f"a root process in sowgate.service's cgroup ({s.get('ControlGroup')}, "
           f"DevicePolicy={s.get('DevicePolicy')}, DeviceAllow={allow[:200]}): "
           + "; ".join(f"{p} ({ports[p]}): {got.get(p)}" for p in ports)
           + "; the same opens from outside that cgroup: "
           + ", ".join(f"{p.removeprefix('/dev/')} {v}" for p, v in outside.items())
           + (f" [{done.stderr.strip()[-300:]}]" if done.returncode else ""))


def errno_name(exc: OSError) -> str:
    import errno

    return errno.errorcode.get(exc.errno or 0, str(exc))


def get_page(password: str | None) -> tuple[int, str]:
    import base64
    import urllib.error
    import urllib.request

    req = urllib.request.Request("http://127.0.0.1:8080/")
    if password is not None:
        token = base64.b64encode(f"fitter:{password}".encode()).decode()
        req.add_header("Authorization", f"Basic {token}")
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, resp.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, ""


def check_dashboard() -> None:
    password = Path("/etc/sowgate/dashboard-password").read_text().strip()
    sh("systemctl", "start", "sowgate-dashboard", timeout=300)  # started during the watchdog
    started = time.monotonic()
    status, err = 0, ""
    while time.monotonic() - started < 300:  # Type=exec: listening after the imports
        try:
            status, _ = get_page(None)
            break
        except OSError as exc:
            err = str(exc)
            time.sleep(1)
    took = time.monotonic() - started
    if not status:
        result("dashboard", False, f"no page: {err}")
        return
    wrong, _ = get_page("not-the-password")
    right, body = get_page(password)
    s = show("sowgate-dashboard", "ActiveState", "LoadCredential")
    mode = oct(Path("/etc/sowgate/dashboard-password").stat().st_mode & 0o777)
    result("dashboard", s.get("ActiveState") == "active" and status == 401 and wrong == 401
           and right == 200 and "<html" in body.lower(),
           f"sowgate-dashboard {s.get('ActiveState')} (listening {took:.0f} s after the check "
           f"began), its password file /etc/sowgate/dashboard-password ({mode}, root) given as "
           f"LoadCredential={s.get('LoadCredential')} (the README's drop-in): GET / without a "
           f"password {status}, wrong password {wrong}, the password {right} with "
           f"{len(body)} bytes of HTML")


def check_journal() -> None:
    out = sh("journalctl", "-u", "sowgate", "-p", "warning", "-o", "json", "--no-pager").stdout
    entries = [json.loads(ln) for ln in out.splitlines() if ln.strip()]
    by_priority: dict[str, int] = {}
    for e in entries:
        by_priority[e.get("PRIORITY", "?")] = by_priority.get(e.get("PRIORITY", "?"), 0) + 1
    daemon = [e for e in entries if e.get("_COMM", "").startswith("sowgate")
              or e.get("SYSLOG_IDENTIFIER", "").startswith("sowgate")]
    samples = sorted({str(e.get("MESSAGE", ""))[:70] for e in daemon})[:5]
    result("journal", bool(daemon) and all(e.get("PRIORITY") in "01234" for e in entries),
           f"journalctl -u sowgate -p warning: {len(entries)} entries, PRIORITY field "
           f"{dict(sorted(by_priority.items()))}; {len(daemon)} from the daemon itself",
           samples=samples)


def delivered_upto(lo: int) -> int:
    """The highest id such that every seed id from ``lo`` up to it is acknowledged by the
    broker (the store's delivered ranges)."""
    db = sqlite3.connect(f"file:{STORE}?mode=ro", uri=True)
    try:
        ranges = db.execute("SELECT lo, hi FROM delivered WHERE tbl = 'seeds' ORDER BY lo")
        upto = lo - 1
        for a, b in ranges:
            if a <= upto + 1:
                upto = max(upto, int(b))
        return upto
    finally:
        db.close()


def before_power_cut() -> None:
    """Sow with the broker stopped (records pile up in the store's outbox), then have the host
    kill qemu: what a power cut leaves is checked by after_power_cut on the next boot."""
    sh("systemctl", "stop", "mosquitto")
    _, _, hi0 = store_ids()
    flag("operate-before-cut")
    wait_host("started-before-cut", 30)
    end = time.monotonic() + 60
    # the sowing rate, timed over at least 3 s of it from here (timed from the flag alone
    # when 200 records were already in, 428 records in 15 ms read as 27 651 records/s and
    # allowed 41 477 records lost)
    _, lo, hi = store_ids()
    rate_from, rate_id = time.monotonic(), hi
    while time.monotonic() < end and (hi < hi0 + 200 or time.monotonic() - rate_from < 3.0):
        time.sleep(1)
        _, lo, hi = store_ids()
    (OUT / "before-cut.json").write_text(json.dumps(
        {"max_id_read": hi, "before_outage": hi0, "undelivered_from": delivered_upto(lo) + 1,
         "records_per_s": (hi - rate_id) / max(time.monotonic() - rate_from, 1e-3),
         "seen_at": time.time()}))
    flag("cut")  # the host kills qemu now, while sowing
    time.sleep(600)


def after_power_cut() -> None:
    before = json.loads((OUT / "before-cut.json").read_text())
    s = show("sowgate", "ActiveState", "NRestarts", "StatusText")
    ok_integrity = integrity()
    n, _, hi = store_ids()
    contiguous, ids_seen = ids_go_on(before["before_outage"], restarts=1)
    # ids read before the cut were committed then: every one missing now is a record lost
    db = sqlite3.connect(f"file:{STORE}?mode=ro", uri=True)
    try:
        kept = db.execute("SELECT count(*) FROM seeds WHERE id > ? AND id <= ?",
                          (before["before_outage"], before["max_id_read"])).fetchone()[0]
    finally:
        db.close()
    lost = before["max_id_read"] - before["before_outage"] - int(kept)
    # what a power cut may take back: the records of one commit interval and one WAL fsync
    # interval (gateway/recording/store.py: commit_interval_s 0.5 s, SYNC_INTERVAL_S 1 s)
    window = math.ceil(before["records_per_s"] * (0.5 + 1.0))
    written = before["max_id_read"] - before["before_outage"]
    result("power_cut", s.get("ActiveState") == "active" and ok_integrity == "ok"
           and contiguous and lost <= window and written > 0,
           f"qemu killed while sowing ({written} records stored with the broker down), "
           f"booted again: sowgate {s.get('ActiveState')} by itself "
           f"(enabled); integrity_check {ok_integrity}; {n} records, ids after "
           f"{before['before_outage']}: {ids_seen}; last id read before the cut "
           f"{before['max_id_read']}, "
           f"{lost} of them lost (allowed: {window}, the records of the 1.5 s commit + fsync "
           f"window at {before['records_per_s']:.0f} records/s)")
    start = before["undelivered_from"]
    end = time.monotonic() + 90
    upto = delivered_upto(start)
    while time.monotonic() < end and upto < min(hi, before["max_id_read"]):
        time.sleep(2)
        upto = delivered_upto(start)
    result("after_cut_mqtt", upto >= min(hi, before["max_id_read"]),
           f"records {start}..{before['max_id_read']} were unpublished at the cut (broker "
           f"stopped); after the boot the broker has acknowledged ids up to {upto}")
    journal = sh("journalctl", "-b", "-u", "sowgate", "-o", "short-monotonic",
                 "--no-pager").stdout
    (OUT / "journal-after-cut.txt").write_text(journal)


def main() -> None:
    if (OUT / "phase2").exists():
        after_power_cut()
        flag("done")
        return

    result("runner", True, "systemd started the runner after multi-user.target: "
           + sh("systemctl", "is-system-running").stdout.strip())
    mqtt = Mqtt()
    peer = CanPeer()
    peer.start()
    checks = [("start", lambda: check_start(mqtt)), ("can", lambda: check_can(peer)),
              ("bad_config", check_bad_config), ("upgrade", check_upgrade),
              ("watchdog", check_watchdog), ("clock", lambda: check_clock(mqtt)),
              ("security", check_hardening), ("dashboard", check_dashboard),
              ("journal", check_journal), ("rollback", check_rollback),
              ("store_too_new", check_store_too_new)]
    for name, check in checks:
        try:
            check()
        except Exception as exc:  # a failed check is a row, not the end of the run
            result(name, False, f"{type(exc).__name__}: {exc}")
    journal = sh("journalctl", "-b", "-u", "sowgate", "-u", "sowgate-dashboard", "-u",
                 "sowgate-probe", "-o", "short-monotonic", "--no-pager").stdout
    (OUT / "journal.txt").write_text(journal)
    if os.environ.get("SYSTEST_POWER_CUT", "1") == "1":
        before_power_cut()
    flag("done")


if __name__ == "__main__":
    try:
        main()
    finally:
        subprocess.run(["systemctl", "poweroff", "--no-block"])
