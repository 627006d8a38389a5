"""The simulator's own GNSS sentence encoder, checked against real receivers, not against protocol/.

Two independent references:

* the layout of real receivers' lines (``NMEA_LAYOUT``, ``HEADINGA_LAYOUT``: field count and
  each field's shape), written down from published captures of UM98x receivers. When the
  captures are on this machine (``SOWGATE_RECEIVER_CAPTURES``, by default the shared reference
  directory; third-party data, so not copied into the project) the layouts and the
  checksums/CRCs are checked against them, and the encoder re-encodes each captured line from
  the values an independent parser (pynmeagps) read out of it;
* checksums by other means: pynmeagps validates the NMEA checksum, and the Unicore CRC is
  checked by the CRC-32 affine identity with zlib (init 0 / no final XOR vs zlib's inverted
  init and output).

The decoders under ``protocol/`` are not used here: they are what the encoder's output judges.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import zlib
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pynmeagps import VALCKSUM, NMEAReader

from simulator.gnss_sentences import (
    epoch_sentences,
    gga,
    gps_week_tow,
    headinga,
    rmc,
    unicore_crc,
    xor_checksum,
)

CAPTURES = Path(os.environ.get("SOWGATE_RECEIVER_CAPTURES", "/work/shared/reference/captures"))
T0 = datetime(2026, 5, 2, 6, 0, 0, 300_000, tzinfo=UTC)

# Shapes of the fields real receivers print (from the captures; see the module docstring).
# A shape: "d" digits, "." a decimal point, "A" letters; e.g. 4020.17401738 -> "dddd.dddddddd".
TIME = "dddddd.dd"
LAT, LON = "dddd.dddddddd", "ddddd.dddddddd"
NMEA_LAYOUT = {
    # number of fields (the address included), field index -> shape
    "GGA": (15, {1: TIME, 2: LAT, 3: "A", 4: LON, 5: "A", 6: "d", 7: "dd", 10: "A", 12: "A"}),
    "RMC": (14, {1: TIME, 2: "A", 3: LAT, 4: "A", 5: LON, 6: "A", 7: "d.ddd", 8: "d.d",
                 9: "dddddd", 12: "A"}),
}
FOUR_DECIMALS = "d.dddd"
HEADINGA_LAYOUT = (10, 17, {  # header fields (with the name), body fields, body shapes
    2: FOUR_DECIMALS, 3: FOUR_DECIMALS, 4: FOUR_DECIMALS, 5: FOUR_DECIMALS, 6: FOUR_DECIMALS,
    7: FOUR_DECIMALS,
})


def shape(field: str) -> str:
    """Digits -> d (runs of digits before the point collapse to their length kept), letters
    -> A; a leading minus dropped; used to compare layouts, not values."""
    s = re.sub(r"[A-Za-z]+", "A", field.lstrip("-"))
    return re.sub(r"[0-9]", "d", s)


def loose(field: str) -> str:
    """The shape with the integer part collapsed (heights, speeds vary in magnitude)."""
    return re.sub(r"d+(?=\.)|^d+$", "d", shape(field))


def nmea_fields(line: str) -> tuple[str, list[str], str]:
    body, cs = line[1:].split("*")
    fields = body.split(",")
    return fields[0][2:], fields, cs


def check_nmea_layout(line: str, *, count: bool = True) -> None:
    """``count`` False: the shapes only (a receiver on NMEA 4.0 has no RMC nav status)."""
    kind, fields, cs = nmea_fields(line)
    n, shapes = NMEA_LAYOUT[kind]
    assert len(fields) == n or not count, (kind, fields)
    for i, want in shapes.items():
        got = shape(fields[i]) if want in (TIME, LAT, LON, "dddddd", "dd") else loose(fields[i])
        assert got == want, (kind, i, fields[i], want)
    assert re.fullmatch(r"[0-9A-F]{2}", cs)


def check_headinga_layout(line: str) -> None:
    content, crc = line[1:].split("*")
    header, body = content.split(";")
    n_header, n_body, shapes = HEADINGA_LAYOUT
    h, b = header.split(","), body.split(",")
    assert (len(h), len(b)) == (n_header, n_body)
    assert h[0] == "HEADINGA" and h[4] == "FINE"
    assert re.fullmatch(r"\d+\.\d", h[3]) and re.fullmatch(r"\d{4}", h[5])
    assert re.fullmatch(r"\d+\.\d{3}", h[6])
    for i, want in shapes.items():
        assert loose(b[i]) == want, (i, b[i])
    assert re.fullmatch(r'"\d*"', b[8])
    assert re.fullmatch(r"[0-9a-f]{8}", crc)


# ------------------------------------------------------------------ against the real captures


def _captured(name: str) -> list[str]:
    path = CAPTURES / name
    if not path.is_file():
        pytest.skip(f"receiver captures not on this machine ({path}); set "
                    "SOWGATE_RECEIVER_CAPTURES to a directory holding nmea.txt/unicore.txt")
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]


def test_captured_gga_rmc_have_the_layout_and_checksums_the_encoder_follows() -> None:
    lines = [ln for ln in _captured("nmea.txt") if ln[3:6] in ("GGA", "RMC")]
    assert len(lines) >= 4
    for line in lines:
        msg = NMEAReader.parse(line, validate=VALCKSUM)  # an independent parser and checksum
        _kind, fields, cs = nmea_fields(line)
        assert xor_checksum(line[1:].split("*")[0]) == cs
        if fields[6 if line[3:6] == "GGA" else 2] in ("4", "5", "R", "F", "A") and (
            len(fields[2 if line[3:6] == "GGA" else 3]) == len(LAT)
        ):
            check_nmea_layout(line, count=line[3:6] == "GGA" or fields[-1] == "V")
        # the encoder, given the values pynmeagps read, prints the same fields
        day = datetime(2026, 1, 1, tzinfo=UTC)
        if line[3:6] == "RMC":
            day = datetime.combine(msg.date, datetime.min.time(), UTC)
        utc = day.replace(hour=msg.time.hour, minute=msg.time.minute, second=msg.time.second,
                          microsecond=msg.time.microsecond)
        if line[3:6] == "GGA":
            ours = gga(utc, msg.lat, msg.lon, msg.alt, {1: "single", 4: "rtk_fixed"}[
                msg.quality], num_sv=msg.numSV, hdop=msg.HDOP, geoid_sep_m=msg.sep,
                talker=line[1:3])
            same = range(1, 12)
        else:
            ours = rmc(utc, msg.lat, msg.lon, msg.spd * 1.852, msg.cog,
                       {"A": "single", "D": "dgps"}[msg.posMode], talker=line[1:3])
            same = (1, 2, 4, 6, 7, 8, 9, 12)
        _k, our_fields, _cs = nmea_fields(ours)
        assert len(our_fields) == len(fields) or fields[-1] != "V"
        for i in same:
            if (i in (2, 4) and line[3:6] == "GGA") or (i in (3, 5) and line[3:6] == "RMC"):
                # pynmeagps keeps 10 decimals of degrees: the last digit of minutes may differ
                assert shape(our_fields[i]) == shape(fields[i])
                assert float(our_fields[i]) == pytest.approx(float(fields[i]), abs=2e-8)
            else:
                assert our_fields[i] == fields[i], (line, i)


def test_captured_headinga_has_the_layout_and_crc_the_encoder_follows() -> None:
    lines = [ln for ln in _captured("unicore.txt") if ln.startswith("#HEADINGA,")]
    assert lines
    for line in lines:
        content, crc = line[1:].split("*")
        assert unicore_crc(content.encode()) == int(crc, 16)  # the receiver's own CRC
        check_headinga_layout(line)
        header, body = content.split(";")
        h, b = header.split(","), body.split(",")
        ours = headinga(int(h[5]), float(h[6]), float(b[3]), float(b[4]), float(b[2]),
                        pos_type=b[1], hdg_std=float(b[6]), ptch_std=float(b[7]),
                        num_sv_tracked=int(b[9]), num_sv_used=int(b[10]), port=h[1],
                        sequence=int(h[2]), idle_pct=float(h[3]))
        check_headinga_layout(ours)
        oh, ob = ours[1:].split("*")[0].split(";")
        assert oh.split(",")[:7] == h[:7]
        assert ob.split(",")[:8] == b[:8]


def test_captured_negative_lines_fail_the_encoders_checks() -> None:
    for line in _captured("negative.txt"):
        if line.startswith("#") and "\t" in line:
            text = line.split("\t")[0]
            content, crc = text[1:].split("*")
            if text.startswith(("#HEADINGA", "#UNIHEADINGA")):
                assert unicore_crc(content.encode()) != int(crc, 16)
            elif text.startswith("$"):
                assert xor_checksum(content) != crc


# ------------------------------------------------------------------ the encoder's own output


def test_an_epoch_is_rmc_gga_headinga_in_the_real_layout() -> None:
    rmc_l, gga_l, hdg_l = epoch_sentences(T0, 45.75, 126.63, 150.0, 8.0, 91.0, 1.0,
                                          pitch_deg=-1.6)
    check_nmea_layout(rmc_l)
    check_nmea_layout(gga_l)
    check_headinga_layout(hdg_l)


fixes = st.sampled_from(["rtk_fixed", "rtk_float", "dgps", "single"])


@given(lat=st.floats(-89.9, 89.9), lon=st.floats(-179.9, 179.9), alt=st.floats(-400, 8000),
       kmh=st.floats(0, 60), course=st.floats(0, 359.9), fix=fixes,
       ms=st.integers(0, 86_399_900).map(lambda x: x - x % 100))
def test_pynmeagps_reads_back_what_was_encoded(lat: float, lon: float, alt: float, kmh: float,
                                               course: float, fix: str, ms: int) -> None:
    utc = datetime(2026, 5, 2, tzinfo=UTC) + timedelta(milliseconds=ms)
    rmc_l, gga_l, _h = epoch_sentences(utc, lat, lon, alt, kmh, course, 0.0, fix)  # type: ignore[arg-type]
    g = NMEAReader.parse(gga_l, validate=VALCKSUM)
    r = NMEAReader.parse(rmc_l, validate=VALCKSUM)
    assert g.lat == pytest.approx(lat, abs=1e-9) and g.lon == pytest.approx(lon, abs=1e-9)
    assert r.lat == pytest.approx(lat, abs=1e-9) and r.lon == pytest.approx(lon, abs=1e-9)
    assert g.alt == pytest.approx(alt, abs=5e-5)
    assert g.quality == {"rtk_fixed": 4, "rtk_float": 5, "dgps": 2, "single": 1}[fix]
    assert r.spd * 1.852 == pytest.approx(kmh, abs=1e-3)
    assert r.date == utc.date()
    check_nmea_layout(rmc_l)
    check_nmea_layout(gga_l)


@given(st.binary(max_size=300))
def test_unicore_crc_is_zlib_crc_with_init_and_output_inversion_undone(data: bytes) -> None:
    assert unicore_crc(data) == zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF


def test_headinga_carries_gps_time_and_its_crc_covers_the_content() -> None:
    week, tow = gps_week_tow(T0)
    line = epoch_sentences(T0, 45.0, 7.0, 250.0, 8.0, 90.0, 91.0)[2]
    content, crc = line[1:].split("*")
    assert content.split(",")[5:7] == [str(week), f"{tow:.3f}"]
    assert int(crc, 16) == zlib.crc32(content.encode(), 0xFFFFFFFF) ^ 0xFFFFFFFF
    # 2026-05-02 is the Saturday of GPS week 2416: 6 days + 6 h + 18 leap seconds into it
    assert (week, tow) == (2416, 6 * 86400 + 6 * 3600 + 18 + 0.3)


TRUTHS = {  # module -> top-level packages it must not load
    "simulator.gnss_sentences": ("gateway", "protocol", "drivers"),
    "simulator.field_truth": ("gateway", "protocol", "drivers"),
    # the emulator uses drivers' asyncio helpers (drivers.tasks) for its pty, not a decoder
    "simulator.um982": ("gateway", "protocol", "drivers.gnss_reader"),
}


@pytest.mark.parametrize("module", sorted(TRUTHS))
def test_the_encoder_and_the_field_truth_load_nothing_they_would_judge(module: str) -> None:
    code = f"import sys, {module}; print('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    loaded = out.stdout.split()
    bad = [m for m in loaded for p in TRUTHS[module] if m == p or m.startswith(p + ".")]
    assert bad == []
