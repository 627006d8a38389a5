"""The UM982 emulator: realistic sentences, honest noise, ground truth, faults on demand."""

from __future__ import annotations

import asyncio
import os
import statistics
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pymap3d
import pytest

from protocol.gnss import GnssLineDecoder, Rejected, decode_line
from protocol.nmea import Gga, Rmc
from protocol.unicore import Heading
from simulator.plant import Drive, Leg
from simulator.um982 import Um982Emulator, corrupt_checksum, um982_sentences

T0 = datetime(2024, 6, 1, 8, 0, 0, tzinfo=UTC)


def test_one_epoch_is_rmc_gga_headinga_describing_the_same_instant() -> None:
    rmc_l, gga_l, hdg_l = um982_sentences(T0, 48.1, -11.2, 500.0, 10.0, 45.0, 47.5)
    assert rmc_l.startswith("$GNRMC,") and gga_l.startswith("$GNGGA,")
    assert hdg_l.startswith("#HEADINGA,COM1,")
    rmc, gga, hdg = decode_line(rmc_l), decode_line(gga_l), decode_line(hdg_l)
    assert isinstance(rmc, Rmc) and isinstance(gga, Gga) and isinstance(hdg, Heading)
    assert datetime.combine(rmc.date, rmc.utc, UTC) == T0  # type: ignore[arg-type]
    assert gga.utc == rmc.utc and hdg.utc() == T0
    assert gga.lon == pytest.approx(-11.2) and gga.quality == 4 and rmc.mode == "R"
    assert hdg.heading_deg == 47.5 and hdg.valid


def test_field_widths_are_those_of_the_real_receiver() -> None:
    """ddmm.mmmmmmmm / dddmm.mmmmmmmm, hhmmss.ss, two-digit satellites, 4-decimal height."""
    _, gga, _ = um982_sentences(T0 + timedelta(seconds=0.1), 5.5, 7.25, 12.0, 1.0, 0.0, 0.0)
    fields = gga.split(",")
    assert fields[1] == "080000.10"
    assert fields[2] == "0530.00000000" and fields[4] == "00715.00000000"
    assert fields[7] == "28" and fields[9] == "12.0000"


def test_no_fix_sends_empty_position_and_no_heading_sends_insufficient_obs() -> None:
    rmc_l, gga_l, hdg_l = um982_sentences(
        T0, 48.0, 11.0, 500.0, 0.0, 0.0, 0.0, fix="none", heading_ok=False
    )
    rmc, gga, hdg = decode_line(rmc_l), decode_line(gga_l), decode_line(hdg_l)
    assert isinstance(rmc, Rmc) and not rmc.valid and rmc.lat is None
    assert isinstance(gga, Gga) and gga.quality == 0 and gga.lat is None
    assert isinstance(hdg, Heading) and hdg.sol_status == "INSUFFICIENT_OBS" and not hdg.valid


def test_naive_datetime_is_refused() -> None:
    with pytest.raises(ValueError, match="timezone"):
        um982_sentences(datetime(2024, 1, 1), 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)


def test_corrupt_checksum_makes_every_kind_of_line_fail() -> None:
    for line in um982_sentences(T0, 48.0, 11.0, 500.0, 8.0, 0.0, 0.0):
        decoder = GnssLineDecoder()
        (rej,) = decoder.feed((corrupt_checksum(line) + "\r\n").encode())
        assert isinstance(rej, Rejected) and rej.reason == "checksum"


def test_noise_has_the_configured_sigma_and_truth_is_recorded() -> None:
    """Sampled without the pty: 400 epochs of a parked tractor, scatter ≈ rtk_sigma_m."""
    drive = Drive([Leg(100.0, 0.0)], start_heading_deg=120.0)
    emu = Um982Emulator(
        drive.pose_at, origin_lat=60.0, origin_lon=25.0, rtk_sigma_m=0.02,
        heading_sigma_deg=0.3, seed=3, utc_start=T0, t0_mono=1000.0,
    )
    east, north, hdg = [], [], []
    for k in range(400):
        _, gga, head = (decode_line(ln) for ln in emu.sample_epoch(k))
        assert isinstance(gga, Gga) and isinstance(head, Heading)
        e, n, _ = pymap3d.geodetic2enu(gga.lat, gga.lon, 0.0, 60.0, 25.0, 0.0)
        east.append(e)
        north.append(n)
        hdg.append(head.heading_deg)
    assert statistics.pstdev(east) == pytest.approx(0.02, rel=0.2)
    assert statistics.pstdev(north) == pytest.approx(0.02, rel=0.2)
    assert statistics.fmean(hdg) == pytest.approx(120.0, abs=0.1)
    assert statistics.pstdev(hdg) == pytest.approx(0.3, rel=0.2)
    assert len(emu.truth) == 400
    last = emu.truth[-1]
    assert last.utc == T0 + timedelta(seconds=39.9)
    assert last.t_mono == pytest.approx(1039.9) and last.t_sim == pytest.approx(39.9)
    assert (last.lat, last.lon) == (pytest.approx(60.0), pytest.approx(25.0))


def test_truth_follows_the_trajectory() -> None:
    drive = Drive([Leg(30.0, 9.0)], start_heading_deg=90.0)
    emu = Um982Emulator(drive.pose_at, origin_lat=0.0, origin_lon=0.0, utc_start=T0, t0_mono=0.0)
    emu.sample_epoch(200)
    truth = emu.truth[-1]
    assert truth.pose.east == pytest.approx(drive.pose_at(20.0).east)
    assert truth.pose.east > 30.0 and truth.lon > 0.0  # heading 90: driving east


def test_invalid_settings_are_refused() -> None:
    drive = Drive([Leg(1.0, 1.0)])
    with pytest.raises(ValueError, match="rate_hz"):
        Um982Emulator(drive.pose_at, origin_lat=0, origin_lon=0, rate_hz=0)
    with pytest.raises(ValueError, match="latency"):
        Um982Emulator(drive.pose_at, origin_lat=0, origin_lon=0, output_latency_s=0.2)


async def _read_for(fd: int, seconds: float) -> bytes:
    data = bytearray()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            data += os.read(fd, 4096)
        except BlockingIOError:
            await asyncio.sleep(0.01)
    return bytes(data)


async def test_emulator_writes_ten_epochs_a_second_to_its_pty(tmp_path: Path) -> None:
    drive = Drive([Leg(30.0, 6.0)])
    async with Um982Emulator(
        drive.pose_at, origin_lat=48.0, origin_lon=11.0, link_path=tmp_path / "gnss"
    ) as emu:
        assert emu.device_path == str(tmp_path / "gnss")
        fd = os.open(emu.device_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            data = await _read_for(fd, 1.0)
            emu.drop_heading(True)
            await _read_for(fd, 0.15)  # the epoch in flight may still carry it
            no_heading = await _read_for(fd, 0.5)
        finally:
            os.close(fd)
    decoder = GnssLineDecoder()
    events = decoder.feed(data)
    n_rmc = sum(isinstance(e, Rmc) for e in events)
    assert 6 <= n_rmc <= 12  # 10 Hz, generous for a loaded machine
    assert decoder.counts["ok"] == len(events)  # every line valid
    assert b"HEADINGA" not in no_heading and b"GNRMC" in no_heading
    assert not (tmp_path / "gnss").exists()  # closed cleanly, symlink removed


async def test_faults_reach_the_wire(tmp_path: Path) -> None:
    drive = Drive([Leg(30.0, 6.0)])
    async with Um982Emulator(
        drive.pose_at, origin_lat=48.0, origin_lon=11.0, link_path=tmp_path / "gnss", seed=1
    ) as emu:
        fd = os.open(emu.device_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            await _read_for(fd, 0.15)
            emu.corrupt_next(2)
            emu.garbage(25)
            data = await _read_for(fd, 0.4)
        finally:
            os.close(fd)
    decoder = GnssLineDecoder()
    decoder.feed(data)
    assert decoder.counts["checksum"] == 2 and emu.lines_corrupted == 2
    assert decoder.rejected_total > 2


async def test_unplug_removes_the_port_and_replug_restores_it(tmp_path: Path) -> None:
    drive = Drive([Leg(30.0, 6.0)])
    link = tmp_path / "gnss"
    async with Um982Emulator(drive.pose_at, origin_lat=1, origin_lon=2, link_path=link) as emu:
        emu.unplug()
        assert not link.exists()
        emu.replug()
        assert link.exists()
        fd = os.open(emu.device_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            assert b"GNGGA" in await _read_for(fd, 0.3)
        finally:
            os.close(fd)


async def test_interleaved_binary_precedes_every_line_until_switched_off(tmp_path: Path) -> None:
    """A receiver with binary logs on: the chosen bytes before each sentence, then plain NMEA."""
    drive = Drive([Leg(30.0, 6.0)])
    binary = bytes(range(0x80, 0x80 + 40))
    async with Um982Emulator(
        drive.pose_at, origin_lat=48.0, origin_lon=11.0, link_path=tmp_path / "gnss", seed=1
    ) as emu:
        fd = os.open(emu.device_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            await _read_for(fd, 0.15)
            emu.interleave(binary)
            mixed = await _read_for(fd, 0.35)
            emu.interleave(None)
            await _read_for(fd, 0.15)
            plain = await _read_for(fd, 0.3)
        finally:
            os.close(fd)
    lines = [ln for ln in mixed.split(b"\r\n") if ln]
    assert len(lines) >= 6
    assert all(ln.startswith(binary) and ln[len(binary):][:1] in (b"$", b"#") for ln in lines)
    assert binary not in plain and b"$GNRMC" in plain
