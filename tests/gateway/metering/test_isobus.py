"""The tractor's ISOBUS readings as the machine acts on them: speed-source priority, the
300 ms staleness and the hitch's work state (the listener only decodes)."""

from __future__ import annotations

import pytest

from drivers.can_bus import IsobusListener
from gateway.metering.isobus import TractorInputs
from protocol import isobus as ib
from tests.drivers.test_can_bus import hitch_msg, speed_msg


def test_isobus_speed_goes_stale_after_300_ms() -> None:
    lis = IsobusListener()
    tractor = TractorInputs(lis)
    lis.feed(speed_msg(65097, 1389), now=10.0)
    s = tractor.speed(now=10.25)
    assert s is not None and s.source == "ground" and s.speed_kmh == pytest.approx(5.0, abs=0.01)
    assert s.age_s == pytest.approx(0.25)
    assert tractor.speed(now=10.31) is None


def test_staleness_is_the_configured_one() -> None:
    lis = IsobusListener()
    tractor = TractorInputs(lis, stale_after_s=1.0)
    lis.feed(speed_msg(65097, 1389), now=10.0)
    assert tractor.speed(now=10.9) is not None
    assert tractor.speed(now=11.1) is None


def test_isobus_speed_falls_back_by_priority() -> None:
    """Machine-selected first; when it stops, ground-based; invalid raw values are skipped."""
    lis = IsobusListener()
    tractor = TractorInputs(lis, speed_priority=("machine_selected", "ground", "wheel"))
    lis.feed(speed_msg(61474, 2000), now=0.0)
    lis.feed(speed_msg(65097, 0xFE00), now=0.0)  # radar error
    lis.feed(speed_msg(65096, 1000), now=0.2)
    s = tractor.speed(now=0.1)
    assert s is not None and s.source == "machine_selected"
    s = tractor.speed(now=0.4)
    assert s is not None and s.source == "wheel" and s.speed_kmh == pytest.approx(3.6)


def test_a_source_not_in_the_priority_list_is_never_used() -> None:
    lis = IsobusListener()
    tractor = TractorInputs(lis, speed_priority=("wheel", "ground"))
    lis.feed(speed_msg(61474, 2000), now=0.0)  # machine-selected: not configured
    assert tractor.speed(now=0.1) is None
    lis.feed(speed_msg(65097, 1000), now=0.1)
    s = tractor.speed(now=0.1)
    assert s is not None and s.source == "ground"


def test_isobus_reverse_counts_as_zero_speed() -> None:
    lis = IsobusListener()
    tractor = TractorInputs(lis)
    lis.feed(speed_msg(61474, 1500, direction=0), now=0.0)
    s = tractor.speed(now=0.0)
    assert s is not None and s.speed_kmh == 0.0 and s.direction is ib.Direction.REVERSE


def test_isobus_hitch_gives_work_state() -> None:
    lis = IsobusListener()
    tractor = TractorInputs(lis, hitch_in_work_below_pct=30.0)
    assert tractor.working(now=0.0) is None and tractor.hitch_received_at() is None
    lis.feed(hitch_msg(20, 0b01), now=0.0)
    assert tractor.working(now=0.1) is True
    lis.feed(hitch_msg(200, 0b00), now=0.2)
    assert tractor.working(now=0.3) is False
    lis.feed(hitch_msg(50, 0b11), now=0.4)  # in-work n/a: position 20 % < 30 % threshold
    assert tractor.working(now=0.5) is True
    assert tractor.working(now=1.0) is None  # stale
    assert tractor.hitch_received_at() == 0.4  # however old: the pump stamps with it


def test_hitch_without_in_work_bits_or_threshold_says_nothing() -> None:
    lis = IsobusListener()
    tractor = TractorInputs(lis)  # no hitch_in_work_below_pct
    lis.feed(hitch_msg(50, 0b11), now=0.0)
    assert tractor.hitch(now=0.1) is not None
    assert tractor.working(now=0.1) is None


def test_isobus_unknown_priority_source_is_rejected() -> None:
    with pytest.raises(ValueError, match=r"isobus\.speed_priority.*radar"):
        TractorInputs(IsobusListener(), speed_priority=("radar",))
    with pytest.raises(ValueError, match=r"isobus\.speed_priority"):
        TractorInputs(IsobusListener(), speed_priority=())
