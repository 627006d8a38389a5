"""GNSS epochs: assembly from interleaved sentences, and the reader over a real pty."""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import time
from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pymap3d
import pytest

from drivers.backoff import Backoff
from drivers.gnss_reader import (
    EpochAssembler,
    GnssEpoch,
    GnssReader,
    fix_from_gga_quality,
)
from protocol.gnss import GnssEvent, decode_line
from protocol.nmea import Rmc, encode_nmea
from protocol.unicore import encode_headinga, utc_to_gps
from simulator.plant import Drive, Leg
from simulator.um982 import Fix, Um982Emulator, um982_sentences
from tests.helpers import eventually

T0 = datetime(2024, 6, 1, 8, 0, 0, tzinfo=UTC)


def _events(
    utc: datetime, fix: Fix = "rtk_fixed", heading_ok: bool = True, heading: float = 91.0
) -> list[GnssEvent]:
    return [
        decode_line(ln)
        for ln in um982_sentences(utc, 45.0, 7.0, 250.0, 8.0, 90.0, heading, fix, heading_ok)
    ]


def _feed(asm: EpochAssembler, events: list[GnssEvent], t0: float = 100.0) -> list[GnssEpoch]:
    out: list[GnssEpoch] = []
    for i, ev in enumerate(events):
        out += asm.add(ev, t0 + 0.001 * i)
    return out


# -- epoch assembly (pure) -----------------------------------------------------------------


@pytest.mark.parametrize("order", list(itertools.permutations(range(3))))
def test_rmc_gga_heading_in_any_order_make_one_complete_epoch(order: tuple[int, ...]) -> None:
    """The epoch is emitted on the last of its three sentences, whatever the order."""
    events = _events(T0)
    asm = EpochAssembler()
    out: list[GnssEpoch] = []
    for n, i in enumerate(order):
        got = asm.add(events[i], 50.0 + n)
        assert (len(got) == 1) == (n == 2)
        out += got
    (epoch,) = out
    assert epoch.utc == T0 and epoch.t_mono == 50.0  # arrival of the *first* sentence
    assert epoch.lat == pytest.approx(45.0) and epoch.lon == pytest.approx(7.0)
    assert epoch.fix == "rtk_fixed" and epoch.num_sv == 28 and epoch.alt_m == 250.0
    assert epoch.speed_kmh == pytest.approx(8.0, abs=0.002) and epoch.course_deg == 90.0
    assert epoch.heading_deg == pytest.approx(91.0) and epoch.heading_valid


def test_missing_heading_epoch_is_emitted_when_the_next_time_begins() -> None:
    asm = EpochAssembler()
    first = _events(T0)[:2]
    assert _feed(asm, first) == []
    out = asm.add(_events(T0 + timedelta(seconds=0.1))[0], 101.0)
    (epoch,) = out
    assert epoch.utc == T0 and epoch.heading_deg is None and not epoch.heading_valid
    assert epoch.speed_kmh is not None  # what it had is kept


def test_heading_arriving_after_a_newer_epoch_began_is_late_and_dropped() -> None:
    asm = EpochAssembler()
    rmc, gga, hdg = _events(T0)
    _feed(asm, [rmc, gga])
    asm.add(_events(T0 + timedelta(seconds=0.1))[0], 101.0)
    assert asm.add(hdg, 101.01) == []
    assert asm.counts["late"] == 1


def test_float_heading_is_carried_but_not_valid_and_no_solution_means_no_heading() -> None:
    asm = EpochAssembler()
    rmc, gga, _ = _events(T0)
    week, tow = utc_to_gps(T0)
    float_hdg = decode_line(encode_headinga(week, tow, 33.0, pos_type="NARROW_FLOAT"))
    (epoch,) = _feed(asm, [rmc, gga, float_hdg])
    assert epoch.heading_deg == 33.0 and not epoch.heading_valid
    (epoch,) = _feed(asm, _events(T0 + timedelta(seconds=0.1), heading_ok=False))
    assert epoch.heading_deg is None and not epoch.heading_valid


@pytest.mark.parametrize(
    ("quality", "fix"),
    [(4, "rtk_fixed"), (5, "rtk_float"), (2, "dgps"), (1, "single"), (0, "none"), (6, "none")],
)
def test_gga_quality_mapping(quality: int, fix: str) -> None:
    assert fix_from_gga_quality(quality) == fix


@pytest.mark.parametrize("fix", ["rtk_fixed", "rtk_float", "dgps", "single"])
def test_epoch_fix_follows_gga_quality(fix: Fix) -> None:
    (epoch,) = _feed(EpochAssembler(), _events(T0, fix=fix))
    assert epoch.fix == fix


@pytest.mark.parametrize("fix", ["rtk_fixed", "rtk_float", "dgps", "single"])
def test_without_gga_the_rmc_mode_gives_the_fix(fix: Fix) -> None:
    rmc, _, hdg = _events(T0, fix=fix)
    (epoch,) = _feed(EpochAssembler(required={"RMC", "HEADING"}), [rmc, hdg])
    assert epoch.fix == fix and epoch.alt_m is None and epoch.num_sv is None


def test_no_fix_epoch_has_no_position_and_is_not_emitted() -> None:
    asm = EpochAssembler()
    assert _feed(asm, _events(T0, fix="none")) == []
    assert asm.counts["no_position"] == 1


def test_time_rollover_at_midnight_keeps_order_and_advances_the_date() -> None:
    """GGA comes first in the new day, before any RMC carries the new date."""
    asm = EpochAssembler(required={"GGA", "RMC"})
    late = datetime(2024, 6, 1, 23, 59, 59, 900_000, tzinfo=UTC)
    rmc, gga, _ = _events(late)
    out = _feed(asm, [rmc, gga])
    next_gga = _events(late + timedelta(seconds=0.1))[1]
    out += asm.add(next_gga, 200.0)
    out += asm.flush()
    assert [e.utc for e in out] == [late, datetime(2024, 6, 2, tzinfo=UTC)]


def test_hdt_and_ths_attach_to_the_epoch_in_progress() -> None:
    asm = EpochAssembler()
    rmc, gga, _ = _events(T0)
    out = _feed(asm, [rmc, gga, decode_line(encode_nmea("GNTHS,12.5000,A"))])
    (epoch,) = out
    assert epoch.heading_deg == 12.5 and epoch.heading_valid
    rmc2, gga2, _ = _events(T0 + timedelta(seconds=0.1))
    (epoch2,) = _feed(asm, [rmc2, gga2, decode_line(encode_nmea("GPHDT,13.25,T"))])
    assert epoch2.heading_deg == 13.25 and epoch2.heading_valid


def test_untimed_sentence_with_nothing_open_is_counted() -> None:
    asm = EpochAssembler()
    assert asm.add(decode_line(encode_nmea("GPHDT,13.25,T")), 1.0) == []
    assert asm.counts["untimed"] == 1


def test_expire_emits_epochs_whose_first_sentence_is_old_enough() -> None:
    asm = EpochAssembler()
    _feed(asm, _events(T0)[:2], t0=10.0)
    assert asm.expire(older_than_mono=9.0) == []
    (epoch,) = asm.expire(older_than_mono=10.5)
    assert epoch.utc == T0


def test_rmc_without_time_is_counted_untimed() -> None:
    asm = EpochAssembler()
    rmc = decode_line(encode_nmea("GNRMC,,V,,,,,,,,,,N,V"))
    assert isinstance(rmc, Rmc)
    assert asm.add(rmc, 1.0) == []
    assert asm.counts["untimed"] == 1


# -- the reader over a real pty, fed by the emulator ---------------------------------------

ORIGIN = (48.0, 11.0)


def _straight_drive() -> Drive:
    return Drive([Leg(60.0, 8.0)], start_heading_deg=30.0)


@pytest.fixture
async def emulator(tmp_path: Path) -> AsyncIterator[Um982Emulator]:
    drive = _straight_drive()
    async with Um982Emulator(
        drive.pose_at, origin_lat=ORIGIN[0], origin_lon=ORIGIN[1], seed=7,
        link_path=tmp_path / "gnss", output_latency_s=0.02,
    ) as emu:
        yield emu


def _fast_backoff() -> Backoff:
    return Backoff(initial_s=0.05, cap_s=0.2)


async def test_reader_delivers_epochs_matching_ground_truth(emulator: Um982Emulator) -> None:
    """Positions within a few RTK sigmas of the truth; arrival after the epoch instant."""
    epochs: list[GnssEpoch] = []
    async with GnssReader(emulator.device_path, on_epoch=epochs.append) as reader:
        await eventually(lambda: len(epochs) >= 8)
        assert reader.available
        assert reader.speed_kmh() is not None
        stats = reader.stats
    truth = {t.utc: t for t in emulator.truth}
    for e in epochs:
        t = truth[e.utc]
        east, north, _ = pymap3d.geodetic2enu(e.lat, e.lon, 0.0, t.lat, t.lon, 0.0)
        assert math.hypot(east, north) < 0.06  # 1 cm sigma per axis
        assert 0.0 <= e.t_mono - t.t_mono < 0.5  # stamped on arrival, after the epoch instant
        assert e.fix == "rtk_fixed" and e.heading_valid
        heading_err = (e.heading_deg - t.pose.heading_deg + 180.0) % 360.0 - 180.0  # type: ignore[operator]
        assert abs(heading_err) < 0.6
    assert [e.utc for e in epochs] == sorted({e.utc for e in epochs})
    assert stats.rejected == {} and stats.reconnects == 0 and stats.connected


async def test_reader_stamps_with_the_injected_clock(emulator: Um982Emulator) -> None:
    epochs: list[GnssEpoch] = []

    def shifted() -> float:
        return time.monotonic() + 1000.0

    async with GnssReader(emulator.device_path, on_epoch=epochs.append, clock=shifted):
        await eventually(lambda: len(epochs) >= 2)
    assert all(abs(e.t_mono - shifted()) < 10.0 for e in epochs)


async def test_corrupted_lines_and_noise_are_counted_and_skipped(
    emulator: Um982Emulator,
) -> None:
    epochs: list[GnssEpoch] = []
    async with GnssReader(emulator.device_path, on_epoch=epochs.append) as reader:
        await eventually(lambda: len(epochs) >= 2)
        emulator.corrupt_next(3)
        emulator.garbage(40)
        await eventually(lambda: reader.stats.rejected.get("checksum", 0) >= 3)
        n = len(epochs)
        await eventually(lambda: len(epochs) >= n + 3)
        stats = reader.stats
    assert stats.rejected["checksum"] == 3
    assert sum(stats.rejected.values()) > 3  # the noise is counted too
    assert epochs[-1].heading_valid


async def test_dropped_heading_still_gives_epochs_without_heading(
    emulator: Um982Emulator,
) -> None:
    epochs: list[GnssEpoch] = []
    async with GnssReader(emulator.device_path, on_epoch=epochs.append):
        await eventually(lambda: len(epochs) >= 2)
        emulator.drop_heading(True)
        await eventually(lambda: sum(e.heading_deg is None for e in epochs) >= 3)
        emulator.drop_heading(False)
        await eventually(lambda: epochs[-1].heading_valid)


async def test_port_vanishing_is_survived_by_reconnecting(emulator: Um982Emulator) -> None:
    epochs: list[GnssEpoch] = []
    async with GnssReader(
        emulator.device_path, on_epoch=epochs.append, stale_after_s=0.3, backoff=_fast_backoff()
    ) as reader:
        await eventually(lambda: len(epochs) >= 3)
        emulator.unplug()
        await eventually(lambda: not reader.stats.connected)
        await eventually(lambda: not reader.available)
        assert reader.speed_kmh() is None
        before = epochs[-1].utc
        emulator.replug()
        await eventually(lambda: reader.stats.reconnects >= 1 and epochs[-1].utc > before)
        await eventually(lambda: reader.available)
        assert reader.stats.last_error is not None


async def test_missing_port_is_retried_until_it_appears(tmp_path: Path) -> None:
    epochs: list[GnssEpoch] = []
    link = tmp_path / "late-gnss"
    reader = GnssReader(str(link), on_epoch=epochs.append, backoff=_fast_backoff())
    async with reader:
        await asyncio.sleep(0.3)
        assert not reader.stats.connected and "cannot open" in (reader.stats.last_error or "")
        drive = _straight_drive()
        async with Um982Emulator(drive.pose_at, origin_lat=1.0, origin_lon=2.0, link_path=link):
            await eventually(lambda: len(epochs) >= 2)


def test_heading_logged_in_beidou_time_joins_its_rmc_gga_epoch() -> None:
    from protocol.unicore import encode_uniheadinga

    rmc, gga, _ = _events(T0)
    week, tow = utc_to_gps(T0)
    heading = decode_line(encode_uniheadinga(week, tow, 123.0, time_ref="BDS"))
    asm = EpochAssembler()
    (epoch,) = _feed(asm, [rmc, gga, heading])
    assert epoch.utc == T0
    assert epoch.heading_deg == pytest.approx(123.0) and epoch.heading_valid
    assert asm.counts["late"] == 0


@pytest.mark.parametrize(
    ("receiver_deg", "offset_deg", "machine_deg"),
    [(0.0, 90.0, 90.0), (350.0, 20.0, 10.0), (10.0, -90.0, 280.0), (91.0, 180.0, 271.0),
     (91.0, 0.0, 91.0)],
)
def test_heading_offset_turns_the_antenna_baseline_into_the_machine_heading(
    receiver_deg: float, offset_deg: float, machine_deg: float
) -> None:
    """Antennas side by side on the cab roof: the baseline is 90 deg off the direction of travel."""
    asm = EpochAssembler(heading_offset_deg=offset_deg)
    (epoch,) = _feed(asm, _events(T0, heading=receiver_deg))
    assert epoch.heading_deg == pytest.approx(machine_deg)
    assert epoch.heading_valid
    assert epoch.course_deg == 90.0  # the course over ground is not the antennas' business


def test_the_baseline_pitch_of_headinga_rides_on_the_epoch_for_terrain_compensation() -> None:
    """#HEADINGA's pitch (the antenna baseline's elevation) is the machine's roll with the
    antennas side by side: the epoch carries it as received, the positioner turns it."""
    lines = um982_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 1.0, "rtk_fixed", True,
                            pitch_deg=2.75)
    asm = EpochAssembler(heading_offset_deg=90.0)
    (epoch,) = _feed(asm, [decode_line(ln) for ln in lines])
    assert epoch.baseline_pitch_deg == pytest.approx(2.75)
    (no_heading,) = _feed(EpochAssembler(), _events(T0, heading_ok=False))
    assert no_heading.baseline_pitch_deg is None


def test_heading_offset_is_configurable_and_bounded() -> None:
    from gateway.config import ConfigError, parse_config

    assert parse_config({"gnss": {"heading_offset_deg": -90}}).gnss.heading_offset_deg == -90
    with pytest.raises(ConfigError, match=r"gnss\.heading_offset_deg"):
        parse_config({"gnss": {"heading_offset_deg": 270}})


async def test_an_epoch_after_binary_output_is_kept_and_the_binary_bytes_are_counted(
    emulator: Um982Emulator,
) -> None:
    """Binary logs on the same port used to cost the NMEA sentence that followed them."""
    epochs: list[GnssEpoch] = []
    async with GnssReader(emulator.device_path, on_epoch=epochs.append) as reader:
        await eventually(lambda: len(epochs) >= 2)
        written = emulator.epochs_written
        emulator.binary_output(3000)
        await eventually(lambda: reader.stats.discarded_bytes > 0)
        await eventually(lambda: emulator.epochs_written >= written + 3)
        await eventually(lambda: len(epochs) >= emulator.epochs_written - 1)
        stats = reader.stats
    assert stats.discarded_bytes == 3000
    assert stats.rejected == {"overlong": 1}
    utcs = [e.utc for e in epochs]
    assert all(b - a == timedelta(seconds=0.1) for a, b in itertools.pairwise(utcs))  # no gap
    assert all(e.heading_valid for e in epochs)


async def test_rejected_lines_are_warned_about_rate_limited_not_once_per_line(
    emulator: Um982Emulator, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    epochs: list[GnssEpoch] = []
    async with GnssReader(emulator.device_path, on_epoch=epochs.append) as reader:
        await eventually(lambda: len(epochs) >= 2)
        emulator.corrupt_next(30)
        await eventually(lambda: reader.stats.rejected.get("checksum", 0) >= 30)
    checksum_warnings = [
        r for r in caplog.records if r.levelno == logging.WARNING and "checksum" in r.getMessage()
    ]
    assert len(checksum_warnings) == 1  # the first; the rest within the interval held back


# -- time faults: the assembler groups, the position model judges ----------------------------


def _epochs_at(asm: EpochAssembler, stamps: list[tuple[datetime, bool, int]]) -> list[GnssEpoch]:
    """One epoch's three sentences per (stamp, leap second?, GPS−UTC count), 0.1 s apart."""
    out: list[GnssEpoch] = []
    for k, (utc, leap, count) in enumerate(stamps):
        lines = um982_sentences(utc, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0, leap_second=leap,
                                gps_utc_leap_s=count)
        for i, line in enumerate(lines):
            out += asm.add(decode_line(line), 100.0 + 0.1 * k + 0.001 * i)
    return out + asm.flush()


def test_two_epochs_stamped_hours_ahead_do_not_make_the_correct_ones_late() -> None:
    """Before: every later epoch was dropped as "late" until the clock passed the bad stamp."""
    stamps = [T0 + timedelta(seconds=0.1 * k) for k in range(10)]
    stamps[3] += timedelta(hours=2)
    stamps[4] += timedelta(hours=2)
    asm = EpochAssembler()
    out = _epochs_at(asm, [(s, False, 18) for s in stamps])
    assert [e.utc for e in out] == stamps  # all ten, bad ones included (judged downstream)
    assert all(e.heading_valid for e in out)  # every heading found its epoch
    assert asm.counts["late"] == 0


def test_a_straggler_of_an_emitted_epoch_is_still_late() -> None:
    asm = EpochAssembler()
    _feed(asm, _events(T0))
    _feed(asm, _events(T0 + timedelta(seconds=0.1)), t0=100.1)
    assert asm.add(_events(T0)[0], 100.2) == []
    assert asm.counts["late"] == 1


def test_a_leap_second_is_an_epoch_of_its_own_with_its_heading() -> None:
    """23:59:59.x, 23:59:60.x, 00:00:00.x: three seconds, three headings matched; the legacy
    header carries no leap count, so after the leap the assembler counts one more."""
    midnight = datetime(2027, 1, 1, tzinfo=UTC)
    stamps = []
    for k in range(30):  # true time 23:59:59.0 + 0.1 k, continuous
        true = midnight - timedelta(seconds=1) + timedelta(seconds=0.1 * k)
        if true < midnight:
            stamps.append((true, False, 18))
        elif true < midnight + timedelta(seconds=1):
            stamps.append((true - timedelta(seconds=1), True, 18))
        else:
            stamps.append((true - timedelta(seconds=1), False, 19))
    asm = EpochAssembler()
    out = _epochs_at(asm, stamps)
    assert len(out) == 30 and asm.counts["late"] == 0
    assert [e.leap_second for e in out] == [False] * 10 + [True] * 10 + [False] * 10
    assert [e.utc for e in out] == [s for s, _, _ in stamps]
    assert all(e.heading_valid for e in out)
