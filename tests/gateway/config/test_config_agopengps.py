"""``[agopengps]``: on when present, its keys checked with the key and range named (exit 78)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from gateway.app.cli import main
from gateway.config import ConfigError, parse_config

CHANNEL = {"name": "left", "product": "wheat", "target_rate_kg_ha": 100.0, "node_id": 1}


def test_defaults_and_switched_on_when_present() -> None:
    assert parse_config({}).agopengps.enabled is False
    aog = parse_config({"agopengps": {}}).agopengps
    assert aog.enabled and aog.listen == "0.0.0.0:8888" and aog.agio is None
    assert aog.stale_after_s == 4.0
    assert parse_config({"agopengps": {"enabled": False}}).agopengps.enabled is False


def test_sources_and_section_map() -> None:
    s = parse_config({
        "speed": {"source": "agopengps_then_radar"},
        "isobus": {"enabled": False, "work_state_source": "agopengps_then_inclinometer"},
        "channel": [CHANNEL],
        "agopengps": {"agio": "192.168.5.10:9999",
                      "sections": [{"channel": "left", "rows": [1, 2]}, {"rows": [3]}]},
    })
    assert s.speed.source == ["agopengps", "radar"]
    assert s.isobus.work_state_source == ["agopengps", "inclinometer"]
    assert s.agopengps.sections[0].channel == "left" and s.agopengps.sections[1].rows == [3]


@pytest.mark.parametrize(
    ("data", "line"),
    [
        ({"agopengps": {"listen": "8888"}},
         "agopengps.listen: must be HOST:PORT, e.g. 0.0.0.0:8888 (got '8888')"),
        ({"agopengps": {"agio": "192.168.5.10:70000"}},
         "agopengps.agio: the port must be 1-65535, not 70000 (got '192.168.5.10:70000')"),
        ({"agopengps": {"stale_after_s": 0}},
         "agopengps.stale_after_s: Input should be greater than 0 (got 0)"),
        ({"speed": {"source": "agopengps"}},
         "speed.source: uses agopengps but [agopengps] is not enabled (got 'agopengps')"),
        ({"agopengps": {"sections": [{"channel": "nope"}]}},
         "agopengps.sections[0].channel: no such channel (channels: none) (got 'nope')"),
        ({"agopengps": {"sections": [{"rows": [99]}]}},
         "agopengps.sections[0].rows: rows are 1..6 (machine.rows) (got [99])"),
    ],
)
def test_bad_values_name_key_and_range(data: dict[str, Any], line: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    assert info.value.problems == [line]


def test_check_config_exits_78(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "s.toml"
    f.write_text('[agopengps]\nstale_after_s = 99\n')
    assert main(["check-config", str(f)]) == 78
    assert "agopengps.stale_after_s" in capsys.readouterr().err
