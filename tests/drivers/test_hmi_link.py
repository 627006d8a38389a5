"""HmiLink over a real pty, with the simulated screen (HmiPeer) on the other end."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from drivers.backoff import Backoff
from drivers.hmi_link import MAX_WRITE_BACKLOG, HmiLink
from protocol.hmi import (
    EmptySeed,
    HmiEvent,
    Rejected,
    SeedLevelMonitoring,
    SelectCrop,
    StartWork,
    StopWork,
    ZeroTilt,
)
from simulator.hmi_peer import HmiPeer
from simulator.pty_link import PtyPair
from tests.drivers.helpers import running
from tests.helpers import eventually


def fast_backoff() -> Backoff:
    return Backoff(initial_s=0.02, cap_s=0.1)


@pytest.fixture
async def peer(tmp_path: Path) -> AsyncIterator[HmiPeer]:
    screen = HmiPeer(link_path=tmp_path / "ttyHMI")
    yield screen
    await screen.close()


@pytest.fixture
def events() -> list[HmiEvent]:
    return []


@pytest.fixture
async def link(peer: HmiPeer, events: list[HmiEvent]) -> AsyncIterator[HmiLink]:
    hmi = HmiLink(peer.device_path, 9600, "ascii", on_event=events.append, backoff=fast_backoff())
    async with running(hmi):
        await eventually(lambda: hmi.available, what="the HMI port to open")
        yield hmi


async def test_button_presses_arrive_as_typed_events(
    peer: HmiPeer, link: HmiLink, events: list[HmiEvent]
) -> None:
    """Every screen button reaches the gateway as one command, in order."""
    peer.press_start()
    peer.select(2, 225.0)
    peer.seed_level(True)
    peer.empty()
    peer.zero_tilt()
    peer.press_stop()
    await eventually(lambda: len(events) >= 6, what="six events")
    assert events == [
        StartWork(),
        SelectCrop(2, 225.0),
        SeedLevelMonitoring(True),
        EmptySeed(),
        ZeroTilt(),
        StopWork(),
    ]
    assert link.stats.frames_ok == 6 and link.stats.rejected == 0


async def test_text_written_by_the_daemon_appears_on_the_screen(
    peer: HmiPeer, link: HmiLink
) -> None:
    assert await link.show("t_speed", "4.8 km/h")
    assert await link.show_many({"t_state": "seeding", "t_msg": 'rate "too" high'})
    assert await link.set_number("n_duty", 873)
    assert await peer.wait_text("t_speed") == "4.8 km/h"
    assert await peer.wait_text("t_msg") == 'rate "too" high'
    assert peer.texts["t_state"] == "seeding"
    await eventually(lambda: peer.values.get("n_duty") == 873, what="the number object")
    assert link.stats.writes == 4 and link.stats.dropped_writes == 0


async def test_text_uses_the_configured_encoding(tmp_path: Path) -> None:
    """A GB2312 screen shows the Chinese labels the operator configured."""
    async with HmiPeer(encoding="gb2312") as screen:
        hmi = HmiLink(screen.device_path, 9600, "gb2312", on_event=lambda e: None)
        async with running(hmi):
            await eventually(lambda: hmi.available, what="the HMI port to open")
            await hmi.show("t_state", "播种中")
            assert await screen.wait_text("t_state") == "播种中"


async def test_garbage_is_rejected_and_the_link_keeps_working(
    peer: HmiPeer, link: HmiLink, events: list[HmiEvent]
) -> None:
    """Noise between frames becomes one Rejected; the frames around it still arrive."""
    peer.press_start()
    peer.send_raw(b"\x00\x13noise\xfe")
    peer.select(1, 6.0)
    peer.send_raw(b"\x55\x55\x0a\x00\x00\x00\x0d\x0a")  # unknown function code
    peer.press_stop()
    await eventually(lambda: len(events) >= 5, what="five events")
    assert events[0] == StartWork()
    assert isinstance(events[1], Rejected) and events[1].raw == b"\x00\x13noise\xfe"
    assert events[2] == SelectCrop(1, 6.0)
    assert events[3] == Rejected("unknown function code 0x0A", b"UU\x0a\x00\x00\x00\r\n")
    assert events[4] == StopWork()
    assert link.stats.rejected == 2 and link.stats.frames_ok == 3
    assert link.available


async def test_trailing_garbage_is_reported_once_the_line_goes_quiet(
    peer: HmiPeer, link: HmiLink, events: list[HmiEvent]
) -> None:
    """Nothing follows the noise, so the idle gap (not the next frame) ends the run."""
    peer.send_raw(b"\x55\x55\x03\x02")  # a frame cut off mid-way
    await eventually(lambda: len(events) == 1, what="the idle flush")
    assert events == [Rejected("incomplete frame", b"\x55\x55\x03\x02")]
    peer.press_start()
    await eventually(lambda: len(events) == 2, what="the next frame")
    assert events[1] == StartWork()


async def test_frame_split_across_writes_decodes(
    peer: HmiPeer, link: HmiLink, events: list[HmiEvent]
) -> None:
    peer.send_raw(b"\x55\x55\x03")
    await asyncio.sleep(0.05)
    peer.send_raw(b"\x02\x08\xca\x0d\x0a")
    await eventually(lambda: len(events) == 1, what="the frame")
    assert events == [SelectCrop(2, 225.0)]


async def test_screen_error_replies_are_counted_not_forwarded(
    tmp_path: Path, events: list[HmiEvent]
) -> None:
    """Writing to an object the page lacks makes the screen answer 1A FF FF FF; that must not
    come back to the gateway as a rejected frame (it would show it, provoking another)."""
    async with HmiPeer(known_objects={"t_speed"}) as screen:
        hmi = HmiLink(screen.device_path, 9600, "ascii", on_event=events.append)
        async with running(hmi):
            await eventually(lambda: hmi.available, what="the HMI port to open")
            await hmi.show("t_missing", "x")
            await hmi.show("t_speed", "1.0")
            await eventually(lambda: hmi.stats.screen_errors == 1, what="the screen error")
            assert hmi.last_screen_error is not None and hmi.last_screen_error.code == 0x1A
            assert await screen.wait_text("t_speed") == "1.0"
    assert events == [] and hmi.stats.rejected == 0


async def test_failing_event_handler_does_not_stop_the_link(peer: HmiPeer) -> None:
    seen: list[HmiEvent] = []

    def handler(event: HmiEvent) -> None:
        seen.append(event)
        if isinstance(event, StartWork):
            raise RuntimeError("bug in the gateway")

    hmi = HmiLink(peer.device_path, 9600, "ascii", on_event=handler)
    async with running(hmi) as task:
        await eventually(lambda: hmi.available, what="the HMI port to open")
        peer.press_start()
        peer.press_stop()
        await eventually(lambda: len(seen) == 2, what="both events")
        assert not task.done() and hmi.stats.callback_errors == 1


async def test_vanished_screen_is_reported_then_reconnected(tmp_path: Path) -> None:
    """Unplugging the adapter makes the link unavailable (no exception); plugging a screen
    back in on the same device name brings it back."""
    events: list[HmiEvent] = []
    path = tmp_path / "ttyHMI"
    first = HmiPeer(link_path=path)
    hmi = HmiLink(str(path), 9600, "ascii", on_event=events.append, backoff=fast_backoff())
    try:
        async with running(hmi) as task:
            await eventually(lambda: hmi.available, what="the HMI port to open")
            first.vanish()
            await eventually(lambda: not hmi.available, what="the link to notice the loss")
            assert hmi.stats.disconnects == 1
            assert await hmi.show("t_speed", "lost") is False
            assert hmi.stats.dropped_writes == 1
            await eventually(lambda: hmi.stats.open_failures >= 2, what="retries while unplugged")
            assert not task.done()

            async with HmiPeer(link_path=path) as second:
                await eventually(lambda: hmi.available, what="the link to reopen")
                second.press_start()
                await eventually(
                    lambda: events == [StartWork()], what="an event after reconnecting"
                )
                assert await hmi.show("t_speed", "back")
                assert await second.wait_text("t_speed") == "back"
            assert hmi.stats.connects == 2 and hmi.stats.reconnects >= 2
    finally:
        await first.close()


async def test_missing_port_retries_without_raising(tmp_path: Path) -> None:
    """A port that does not exist (adapter not plugged at boot) is retried forever, quietly."""
    hmi = HmiLink(
        str(tmp_path / "no-such-tty"),
        9600,
        "ascii",
        on_event=lambda e: None,
        backoff=fast_backoff(),
    )
    async with running(hmi) as task:
        await eventually(lambda: hmi.stats.open_failures >= 3, what="several open attempts")
        assert not hmi.available and not task.done()
        assert await hmi.show("t_speed", "x") is False
        assert await hmi.show_many({"t_a": "1", "t_b": "2"}) is False
        assert hmi.stats.dropped_writes == 3 and hmi.stats.reconnects >= 3


async def test_screen_that_stops_reading_never_blocks_the_caller_long() -> None:
    """If the screen's UART hangs while the port stays open, updates time out and are then
    dropped instead of piling up without bound."""
    with PtyPair() as pair:  # nobody reads the master end
        hmi = HmiLink(pair.device_path, 9600, "ascii", on_event=lambda e: None, write_timeout_s=0.2)
        async with running(hmi):
            await eventually(lambda: hmi.available, what="the HMI port to open")
            page = {f"t{i}": "x" * 250 for i in range(400)}  # ~100 kB: more than a pty holds
            started = time.monotonic()
            await hmi.show_many(page)
            assert time.monotonic() - started < 3.0
            assert hmi.write_backlog > MAX_WRITE_BACKLOG
            started = time.monotonic()
            assert await hmi.show("t_speed", "1.0") is False
            assert time.monotonic() - started < 1.0
            assert hmi.stats.dropped_writes == 1


def test_unknown_encoding_fails_at_construction() -> None:
    with pytest.raises(LookupError):
        HmiLink("/dev/null", 9600, "klingon-8", on_event=lambda e: None)
