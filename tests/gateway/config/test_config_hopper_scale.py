"""``[hopper_scale]``: the weight transmitter on the RS485 bus, its format and its estimator's
knobs. Every bad value names its key and the allowed range (exit 78)."""

from __future__ import annotations

import pytest

from gateway.config import ConfigError, parse_config


def test_the_defaults_are_the_documented_ones() -> None:
    h = parse_config({"hopper_scale": {}}).hopper_scale
    assert h.enabled
    assert (h.device_id, h.address, h.data_type, h.word_order) == (4, 0, "int32", "big")
    assert (h.window_s, h.max_correction_pct) == (120.0, 20.0)
    assert h.warn_below_kg == 50.0


@pytest.mark.parametrize(
    ("key", "value", "says"),
    [
        ("device_id", 0, "greater than or equal to 1"),
        ("register", 70000, "less than or equal to 65535"),
        ("data_type", "uint32", "'int32', 'uint16', 'int16' or 'float32'"),
        ("word_order", "middle", "'big' or 'little'"),
        ("scale", 0, "greater than 0"),
        ("window_s", 1, "greater than or equal to 5"),
        ("max_correction_pct", 80, "less than or equal to 50"),
        ("warn_below_kg", -1, "greater than or equal to 0"),
    ],
)
def test_a_bad_value_names_its_key_and_range(key: str, value: object, says: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"hopper_scale": {key: value}})
    problems = info.value.problems
    assert any(p.startswith(f"hopper_scale.{key}: ") and says in p and "(got " in p
               for p in problems), problems


def test_its_device_id_must_differ_from_the_other_devices_on_the_bus() -> None:
    with pytest.raises(ConfigError, match=r"hopper_scale.device_id: same as actuators"):
        parse_config({"hopper_scale": {"device_id": 3}})
    # off, its id does not matter
    parse_config({"hopper_scale": {"device_id": 3, "enabled": False}})


def test_it_needs_the_rs485_bus() -> None:
    with pytest.raises(ConfigError, match="hopper_scale is enabled"):
        parse_config({"rs485": {"enabled": False}, "speed": {"source": "isobus"},
                      "isobus": {"work_state_source": "hitch"}, "hopper_scale": {}})
