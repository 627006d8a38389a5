"""Config errors point at where the bad value came from, and suggest the key that was meant."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.app.cli import main
from gateway.config import ConfigError, load_config, parse_config


def _problems(data: dict[str, object]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    return info.value.problems


def test_a_bad_value_from_the_environment_names_the_variable(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("SOWGATE_RS485__POLL_HZ", "abc")
    [problem] = _problems({})
    assert problem.startswith("rs485.poll_hz (from $SOWGATE_RS485__POLL_HZ): ")
    assert problem.endswith("(got 'abc')")


def test_a_bad_value_in_the_file_names_no_variable() -> None:
    [problem] = _problems({"rs485": {"poll_hz": "abc"}})
    assert problem.startswith("rs485.poll_hz: ") and "$" not in problem


def test_the_environment_is_named_even_when_the_file_sets_the_key_too(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Environment beats the file, so the bad value is the variable's."""
    monkeypatch.setenv("SOWGATE_RS485__BAUDRATE", "5")
    [problem] = _problems({"rs485": {"baudrate": 9600}})
    assert problem.startswith("rs485.baudrate (from $SOWGATE_RS485__BAUDRATE): ")


def test_a_misspelt_key_gets_the_closest_valid_key() -> None:
    [problem] = _problems({"rs485": {"baudrat": 9600}})
    assert problem.startswith("rs485.baudrat: ") and "did you mean baudrate?" in problem


def test_a_misspelt_table_gets_the_closest_table() -> None:
    [problem] = _problems({"rs458": {"port": "/dev/ttyUSB0"}})
    assert problem.startswith("rs458: ") and "did you mean rs485?" in problem


def test_a_misspelt_key_in_a_channel_or_crop_gets_a_hint_too() -> None:
    problems = _problems(
        {"channel": [{"name": "deep", "drive": "can_pid", "node_id": 3, "rate_kg_hha": 1}]}
    )
    assert any(p.startswith("channel[0].rate_kg_hha: ") and "did you mean" in p
               for p in problems), problems


def test_a_key_like_nothing_gets_no_guess() -> None:
    [problem] = _problems({"rs485": {"zzzzzz": 1}})
    assert problem.startswith("rs485.zzzzzz: ") and "did you mean" not in problem


def test_a_misspelt_key_from_the_environment_names_the_variable_and_the_key(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("SOWGATE_RS485__PORTT", "/dev/ttyS0")
    [problem] = _problems({})
    assert problem.startswith("rs485.portt (from $SOWGATE_RS485__PORTT): ")
    assert "did you mean port?" in problem


def test_check_config_prints_the_hints_and_exits_78(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text('[rs485]\nport = "/dev/ttyUSB0"\nbaudrat = 9600\n')
    monkeypatch.setenv("SOWGATE_RS485__POLL_HZ", "abc")
    assert main(["check-config", str(f)]) == 78
    err = capsys.readouterr().err
    assert "rs485.baudrat: " in err and "did you mean baudrate?" in err
    assert "rs485.poll_hz (from $SOWGATE_RS485__POLL_HZ): " in err and "(got 'abc')" in err
    with pytest.raises(ConfigError):
        load_config(f)
