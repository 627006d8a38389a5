"""What the daemon reports as its state: every device a dashboard must see go missing."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import FrozenInstanceError
from pathlib import Path

import pytest

from gateway.app.daemon import Daemon
from gateway.app.wiring import state_payload
from gateway.config import parse_config


def test_state_reports_the_screen_and_the_seed_sensors_as_devices(tmp_path: Path) -> None:
    """They used to be absent: a dead screen or seed-tube module was invisible in `state`."""
    settings = parse_config({"gnss": {"enabled": True}, "seed_sensors": {"enabled": True},
                             "mqtt": {"enabled": True}})
    daemon = Daemon(settings, tmp_path / "state")
    try:
        devices = state_payload(daemon).devices
        # nothing opened yet: each is listed, and as not answering
        assert devices == {"gnss": False, "hmi": False, "seed_sensors": False}
        daemon.parts.seed_sensors._line.stats.connected = True  # what run() sets once open
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
        sensors, recorder = daemon.parts.seed_sensors, daemon.parts.seeds
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
    assert "hmi" not in daemon.state().devices
    assert "seed_sensors" not in daemon.state().devices


def test_a_state_is_a_frozen_copy_that_later_changes_do_not_reach(tmp_path: Path) -> None:
    """The views draw from one state for a whole screen: it must not change under them (the
    alarm board updates an active alarm's text in place, every control tick)."""
    daemon = Daemon(parse_config({"hmi": {"enabled": False}}), tmp_path / "state")
    daemon.alarms.raise_("speed.lost", "no valid ground speed for 1 s", "critical")
    before = daemon.state()
    daemon.alarms.raise_("speed.lost", "no valid ground speed for 2 s", "critical")
    assert [a.message for a in before.alarms] == ["no valid ground speed for 1 s"]
    assert [a.message for a in daemon.state().alarms] == ["no valid ground speed for 2 s"]
    with pytest.raises(FrozenInstanceError):
        before.crop = "barley"  # type: ignore[misc]


def test_the_service_process_freezes_start_up_and_collects_young_objects_less_often() -> None:
    """``settle_gc`` is process-wide, so it is checked in a child process, as ``sowgate run``
    would call it: what start-up built is out of the collector's sight, and the young
    generation waits for GC_YOUNG_THRESHOLD allocations instead of Python's 700."""
    code = (
        "import gc, json\n"
        "from gateway.app.daemon import GC_YOUNG_THRESHOLD, settle_gc\n"
        "before = gc.get_threshold()\n"
        "settle_gc()\n"
        "print(json.dumps([gc.get_freeze_count(), gc.get_threshold(), before,"
        " GC_YOUNG_THRESHOLD]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60,
        cwd=Path(__file__).resolve().parents[3],
    )
    frozen, after, before, young = json.loads(out.stdout)
    assert frozen > 10_000  # the imported modules' objects at least
    assert after == [young, before[1], before[2]]
    assert young > before[0]


def test_state_carries_rejected_input_per_device_and_reason(tmp_path: Path) -> None:
    """Rejected input was counted inside the drivers only, invisible to the farm."""
    from drivers.seed_sensors import SeedEdgeEvent
    from protocol.hmi import Rejected as HmiRejected

    settings = parse_config({"gnss": {"enabled": True}, "seed_sensors": {"enabled": True},
                             "mqtt": {"enabled": True}})
    daemon = Daemon(settings, tmp_path / "state")
    try:
        gnss, sensors = daemon.parts.gnss, daemon.parts.seed_sensors
        recorder = daemon.parts.seeds
        assert state_payload(daemon).rejected.model_dump() == {
            "gnss": {}, "gnss_discarded_bytes": 0, "hmi": {}, "seed_sensors": {}
        }
        gnss._dispatch(gnss._decoder.feed(b"\xb5\x62" * 1000 + b"$GNRMC,1*00\r\nnoise\n"), 1.0)
        sensors._feed(b"D,9\r\nD,9\r\nX\r\n", 1.0)  # what a read hands over
        assert daemon.hmi is not None
        daemon.hmi.link._dispatch([HmiRejected("noise", b"\x00", "garbage")])
        for k in range(1000):  # far beyond any seed meter, all at once on row 2
            recorder.on_edge(SeedEdgeEvent(2, 10.0 + k * 1e-6))
        recorder.flush()  # what the recorder's tick does
        rejected = state_payload(daemon).rejected
        assert rejected.gnss == {"overlong": 1, "checksum": 1, "garbage": 1}
        assert rejected.gnss_discarded_bytes == 2000
        assert rejected.hmi == {"garbage": 1}
        assert rejected.seed_sensors == {"bad_row": 2, "malformed": 1, "implausible_rate": 1000}
        rows = state_payload(daemon).row_monitor
        assert rows is not None and rows.rows["2"].implausible_edges == 1000  # per row too
        summary = daemon.parts.rejected.summary()
        assert summary is not None and "seed_sensors: bad_row 2, implausible_rate 1000" in summary
        assert daemon.parts.rejected.summary() is None  # nothing new since
    finally:
        for close in daemon.closers:
            close()
