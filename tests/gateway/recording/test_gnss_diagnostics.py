"""decode-gnss: one JSON object per input line, decoded fields or the precise reason."""

from __future__ import annotations

import io
import json
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from gateway.recording.gnss_diagnostics import (
    EXIT_ALL_DECODED,
    EXIT_NO_INPUT,
    EXIT_SOME_REJECTED,
    decode_stream,
    main_decode_gnss,
)
from protocol.nmea import encode_nmea, nmea_checksum
from simulator.um982 import corrupt_checksum, um982_sentences

T0 = datetime(2024, 6, 1, 8, 0, 0, 500_000, tzinfo=UTC)
RMC, GGA, HDG = um982_sentences(T0, 48.0, 11.0, 500.0, 8.0, 90.0, 91.5, fix="rtk_float")


def test_valid_lines_give_their_type_and_fields() -> None:
    rmc, gga, hdg = decode_stream([RMC, GGA, HDG])
    assert rmc["line"] == 1 and rmc["ok"] is True and rmc["type"] == "RMC"
    assert rmc["utc"] == "08:00:00.500000" and rmc["date"] == "2024-06-01" and rmc["mode"] == "F"
    assert gga["type"] == "GGA" and gga["quality"] == 5 and gga["lat"] == pytest.approx(48.0)
    assert hdg["type"] == "HEADINGA" and hdg["heading_deg"] == 91.5
    assert hdg["valid"] is True and hdg["utc"] == T0.isoformat()
    for record in (rmc, gga, hdg):
        json.dumps(record)  # JSON-able as is


def test_checksum_error_reports_expected_and_received() -> None:
    body = "GPHDT,274.07,T"
    expected = nmea_checksum(body)
    wrong = f"{int(expected, 16) ^ 0x01:02X}"
    (record,) = decode_stream([f"${body}*{wrong}"])
    assert record == {
        "line": 1, "ok": False, "reason": "checksum",
        "error": f"checksum mismatch: expected {expected}, got {wrong}",
    }


def test_line_numbers_count_blank_lines_which_produce_no_output() -> None:
    records = list(decode_stream([RMC, "", "\r", corrupt_checksum(GGA), "just noise"]))
    assert [(r["line"], r["ok"]) for r in records] == [(1, True), (4, False), (5, False)]
    assert records[1]["reason"] == "checksum" and "CRC" not in records[1]["error"]
    assert records[2]["reason"] == "garbage"


def test_noise_before_a_sentence_is_a_warning_not_a_failure() -> None:
    (record,) = decode_stream(["\x07~~" + HDG])
    assert record["ok"] is True and "garbage" in record["warning"]


def test_unknown_and_truncated_lines_say_so() -> None:
    unknown, cut = decode_stream([encode_nmea("GNGSV,1,1,00"), HDG[:50]])
    assert unknown["reason"] == "unknown_sentence" and "GNGSV" in unknown["error"]
    assert cut["reason"] == "truncated"


def test_main_writes_json_lines_and_exit_code_tells_if_anything_was_rejected(
    tmp_path: Path,
) -> None:
    good = tmp_path / "good.txt"
    good.write_bytes(f"{RMC}\r\n{GGA}\r\n{HDG}\r\n".encode())
    out = io.StringIO()
    assert main_decode_gnss(str(good), out) == EXIT_ALL_DECODED
    assert [json.loads(x)["type"] for x in out.getvalue().splitlines()] == [
        "RMC", "GGA", "HEADINGA",
    ]
    bad = tmp_path / "bad.txt"
    bad.write_bytes(f"{RMC}\n\xff\xfe{corrupt_checksum(HDG)}\n".encode("latin-1"))
    out = io.StringIO()
    assert main_decode_gnss(str(bad), out) == EXIT_SOME_REJECTED
    lines = [json.loads(x) for x in out.getvalue().splitlines()]
    assert lines[1]["ok"] is False and lines[1]["reason"] == "checksum"


def test_main_reports_an_unreadable_file(tmp_path: Path) -> None:
    out = io.StringIO()
    assert main_decode_gnss(str(tmp_path / "missing.txt"), out) == EXIT_NO_INPUT
    assert "cannot read" in json.loads(out.getvalue())["error"]


def test_dash_reads_stdin(monkeypatch: pytest.MonkeyPatch) -> None:
    stdin = io.TextIOWrapper(io.BytesIO(f"{GGA}\n".encode()))
    monkeypatch.setattr(sys, "stdin", stdin)
    out = io.StringIO()
    assert main_decode_gnss("-", out) == EXIT_ALL_DECODED
    assert json.loads(out.getvalue())["type"] == "GGA"


def test_two_sentences_on_one_line_are_both_shown_with_a_warning() -> None:
    (record,) = decode_stream([RMC + GGA])
    assert record["ok"] is True and record["type"] == "RMC"
    assert "2 sentences on one line" in record["warning"]
    assert [m["type"] for m in record["more"]] == ["GGA"]


def test_a_date_1024_weeks_early_is_shown_with_the_date_it_is_corrected_to() -> None:
    rolled = T0 - timedelta(weeks=1024)
    rmc, _gga, hdg = decode_stream(um982_sentences(rolled, 48.0, 11.0, 500.0, 8.0, 90.0, 91.5))
    for record in (rmc, hdg):
        assert record["week_rollover_weeks"] == 1024
        assert record["corrected_utc"] == T0.isoformat()
    assert "week_rollover_weeks" not in next(decode_stream([RMC]))  # a plausible date


def test_a_leap_second_decodes_as_second_60() -> None:
    midnight = datetime(2027, 1, 1, tzinfo=UTC)
    lines = um982_sentences(midnight - timedelta(seconds=0.5), 48.0, 11.0, 500.0, 8.0, 90.0,
                            91.5, leap_second=True)
    rmc, gga, _hdg = decode_stream(lines)
    assert rmc["ok"] and gga["ok"]
    assert rmc["leap_second"] is True and rmc["utc"] == "23:59:59.500000"
