"""What the daemon reports as its state: every device a dashboard must see go missing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from gateway.config import parse_config
from gateway.daemon import Daemon
from gateway.optional_parts import state_payload


def test_state_reports_the_screen_and_the_seed_sensors_as_devices(tmp_path: Path) -> None:
    """They used to be absent: a dead screen or seed-tube module was invisible in `state`."""
    settings = parse_config({"gnss": {"enabled": True}, "seed_sensors": {"enabled": True},
                             "mqtt": {"enabled": True}})
    daemon = Daemon(settings, tmp_path / "state")
    try:
        devices = state_payload(daemon).devices
        # nothing opened yet: each is listed, and as not answering
        assert devices == {"gnss": False, "hmi": False, "seed_sensors": False}
        daemon.components["seed_sensors"]._connected = True  # what run() sets once open
        assert state_payload(daemon).devices["seed_sensors"] is True
    finally:
        for close in daemon.closers:
            close()


def test_gpio_seed_sensors_are_read_ahead_of_each_epoch_reaching_the_recorder(
    tmp_path: Path,
) -> None:
    """The wiring behind the GPIO driver's ``read_pending``: each GNSS epoch first has the
    lines read (the edges before it join the recorder's queue first), then goes on."""
    settings = parse_config({
        "gnss": {"enabled": True},
        "seed_sensors": {"enabled": True, "source": "gpio", "gpio_lines": [5, 6, 13, 19, 26, 21]},
        "machine": {"rows": 6},
    })
    daemon = Daemon(settings, tmp_path / "state")
    calls: list[str] = []
    try:
        sensors, recorder = daemon.components["seed_sensors"], daemon.components["seeds"]
        sensors.read_pending = lambda: calls.append("read lines")
        recorder._queue = lambda event: calls.append(f"queue {event}")
        for listener in daemon.epoch_listeners:
            listener("epoch")
        assert calls == ["read lines", "queue epoch"]
    finally:
        for close in daemon.closers:
            close()


def test_devices_not_configured_are_not_listed(tmp_path: Path) -> None:
    daemon = Daemon(parse_config({"hmi": {"enabled": False}}), tmp_path / "state")
    assert "hmi" not in daemon.snapshot()["devices"]
    assert "seed_sensors" not in daemon.snapshot()["devices"]


def test_the_service_process_freezes_start_up_and_collects_young_objects_less_often() -> None:
    """``settle_gc`` is process-wide, so it is checked in a child process, as ``sowgate run``
    would call it: what start-up built is out of the collector's sight, and the young
    generation waits for GC_YOUNG_THRESHOLD allocations instead of Python's 700."""
    code = (
        "import gc, json\n"
        "from gateway.daemon import GC_YOUNG_THRESHOLD, settle_gc\n"
        "before = gc.get_threshold()\n"
        "settle_gc()\n"
        "print(json.dumps([gc.get_freeze_count(), gc.get_threshold(), before,"
        " GC_YOUNG_THRESHOLD]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60,
        cwd=Path(__file__).resolve().parents[2],
    )
    frozen, after, before, young = json.loads(out.stdout)
    assert frozen > 10_000  # the imported modules' objects at least
    assert after == [young, before[1], before[2]]
    assert young > before[0]
