"""The config file is the fitter's contract: every mistake names its key and the allowed range."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from gateway.config import ConfigError, load_config, parse_config, state_dir

CONTRACT = """
[machine]
id = "seeder-01"
working_width_m = 2.0
rows = 6
[rs485]
port = "/dev/ttyUSB0"
baudrate = 9600
parity = "N"
poll_hz = 3.0
timeout_s = 0.3
[radar]
device_id = 1
register = 0
data_type = "uint16"
scale = 0.01
unit = "km/h"
[inclinometer]
device_id = 0x50
axis = "pitch"
layout = "witmotion16"
zero_offset_deg = 0.0
critical_angle_deg = 0.0
hysteresis_deg = 0.5
[actuators]
device_id = 3
motor_register = 0
fan_register = 1
[hmi]
port = "/dev/ttyS1"
baudrate = 9600
"""


def test_the_documented_contract_loads(tmp_path: Path) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text(CONTRACT)
    s = load_config(f)
    assert s.inclinometer.device_id == 0x50
    assert s.radar.address == 0
    assert s.control.crops["wheat"].meter_b == pytest.approx(132.212)


def test_missing_file_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.toml")


def test_bad_toml_is_an_error(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("[machine\nid=1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(f)


@pytest.mark.parametrize("content", ["", "\n", "# nothing yet\n"])
def test_an_empty_file_is_an_error_that_says_what_it_needs(tmp_path: Path, content: str) -> None:
    """Every table has defaults, so an empty file would pass as a demo seeder: refused."""
    f = tmp_path / "sowgate.toml"
    f.write_text(content)
    with pytest.raises(ConfigError) as err:
        load_config(f)
    (problem,) = err.value.problems
    assert problem.startswith(f"{f}: the config file is empty")
    assert "[machine]" in problem and "[rs485] port" in problem


def test_relative_file_paths_are_from_the_config_files_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A config names its files next to itself; where the daemon is started does not matter."""
    conf = tmp_path / "etc"
    conf.mkdir()
    f = conf / "sowgate.toml"
    f.write_text(
        '[store]\npath = "data/records.sqlite3"\n'
        '[prescription]\npath = "field.geojson"\nas_applied_path = "/abs/applied.csv"\n'
        '[mqtt]\nusername = "seeder"\npassword_file = "../secrets/mqtt"\n'
        '[mqtt.tls]\nca_file = "ca.pem"\ncert_file = "~/client.pem"\n'
        '[dashboard]\npassword_file = "dash"\n'
    )
    monkeypatch.chdir(tmp_path / "..")
    s = load_config(f)
    assert s.store.path == str(conf / "data" / "records.sqlite3")
    assert s.prescription.path == str(conf / "field.geojson")
    assert s.prescription.as_applied_path == "/abs/applied.csv"  # absolute: as written
    assert s.mqtt.password_file == str(conf / ".." / "secrets" / "mqtt")
    assert s.mqtt.tls is not None and s.mqtt.tls.ca_file == str(conf / "ca.pem")
    assert s.mqtt.tls.cert_file == "~/client.pem"  # the home directory is not the file's
    assert s.dashboard.password_file == str(conf / "dash")


def test_a_relative_path_from_the_environment_stays_the_callers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text('[store]\npath = "records.sqlite3"\n')
    monkeypatch.setenv("SOWGATE_STORE__PATH", "here.sqlite3")
    assert load_config(f).store.path == "here.sqlite3"


def test_each_problem_names_its_key_and_value() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"rs485": {"baudrate": 5, "prity": "N"}, "radar": {"unit": "mph"}})
    problems = info.value.problems
    assert any(
        p.startswith("rs485.baudrate: ") and "1200" in p and "(got 5)" in p for p in problems
    )
    assert any(p.startswith("rs485.prity: ") and "Extra inputs" in p for p in problems)
    assert any(p.startswith("radar.unit: ") and "'mph'" in p for p in problems)


def test_rate_outside_crop_range_is_rejected() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"control": {"crop": "wheat", "rate_kg_ha": 300}})
    assert info.value.problems == [
        "control.rate_kg_ha: outside wheat range 120.0..225.0 kg/ha (got 300.0)"
    ]


def test_devices_on_one_bus_need_distinct_ids() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"radar": {"device_id": 3}})
    (line,) = info.value.problems
    assert line.startswith("actuators.device_id: same as radar.device_id;")
    assert line.endswith("(got 3)")


# Checks that span several keys still name the one key to change and the value it has.
@pytest.mark.parametrize(
    ("data", "line"),
    [
        (
            {"actuators": {"motor_register": 1, "fan_register": 1}},
            "actuators.fan_register: must differ from motor_register (got 1)",
        ),
        (
            {"control": {"crop": "maize"}},
            "control.crop: not one of the crops in control.crops: ['rapeseed', 'wheat'] "
            "(got 'maize')",
        ),
        (
            {"machine": {"rows": 4},
             "positioning": {"row_lateral_m": [-1.5, -0.9, -0.3, 0.3, 0.9, 1.5]}},
            "positioning.row_lateral_m: needs one entry per row, machine.rows is 4 but it has 6 "
            "(got [-1.5, -0.9, -0.3, 0.3, 0.9, 1.5])",
        ),
        (
            {"hmi": {"objects": {"speed": "t speed"}}},
            "hmi.objects.speed: not a screen object name (letters, digits, _) (got 't speed')",
        ),
        (
            {"channel": [{"name": "seed", "target_rate_kg_ha": 150, "node_id": 0}]},
            "channel[0].node_id: a can_pid channel needs node_id 1..15 (0 is not addressable) "
            "(got 0)",
        ),
        (
            {"channel": [
                {"name": "seed", "target_rate_kg_ha": 150, "node_id": 2},
                {"name": "shallow", "target_rate_kg_ha": 100, "node_id": 3},
                {"name": "deep", "target_rate_kg_ha": 300, "node_id": 2},
            ]},
            "channel[2].node_id: same as channel[0].node_id (seed); two can_pid channels "
            "cannot share a node_id: each metering controller on the CAN bus needs its own "
            "(1..15) (got 2)",
        ),
    ],
)
def test_cross_key_problems_name_section_key_and_value(data: dict[str, Any], line: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    assert info.value.problems == [line]


def test_refitted_crop_with_inverted_ranges_names_the_key() -> None:
    wheat = parse_config({}).control.crops["wheat"].model_dump()
    wheat["omega_max_rpm"] = 10.0
    with pytest.raises(ConfigError) as info:
        parse_config({"control": {"crops": {"wheat": wheat}, "crop": "wheat"}})
    assert info.value.problems == [
        "control.crops.wheat.omega_max_rpm: must be above omega_min_rpm (20) (got 10.0)"
    ]


def test_a_crop_table_refits_only_the_keys_it_gives(tmp_path: Path) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text(
        "[control]\ncrop = 'wheat'\n"
        "[control.crops.wheat]\nmeter_a = -0.61\nmeter_b = 130.0\nrate_max_kg_ha = 250.0\n"
    )
    s = load_config(f)
    wheat = s.control.crops["wheat"]
    assert (wheat.meter_a, wheat.meter_b, wheat.meter_c) == (-0.61, 130.0, -398.316)
    assert wheat.motor_slope == pytest.approx(0.6671) and wheat.rate_max_kg_ha == 250.0
    assert s.control.crops["rapeseed"].meter_b == pytest.approx(5.468)  # still there


def test_a_new_crop_needs_every_key() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"control": {"crops": {"barley": {"code": 3}}}})
    assert "control.crops.barley.meter_a: Field required" in info.value.problems


def test_unknown_screen_encoding_is_a_config_error_not_a_crash() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"hmi": {"encoding": "gb2321"}})
    (line,) = info.value.problems
    assert line.startswith("hmi.encoding: unknown text encoding")
    assert line.endswith("(got 'gb2321')")
    assert parse_config({"hmi": {"encoding": "gb2312"}}).hmi.encoding == "gb2312"


def test_environment_overrides_the_file(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SOWGATE_RS485__PORT", "/dev/ttyAMA0")
    s = parse_config({"rs485": {"port": "/dev/ttyUSB0", "baudrate": 19200}})
    assert s.rs485.port == "/dev/ttyAMA0"
    assert s.rs485.baudrate == 19200


def test_state_dir_precedence(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SOWGATE_STATE_DIR", raising=False)
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    assert state_dir() == Path("sowgate-state")
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/sowgate")
    assert state_dir() == Path("/var/lib/sowgate")
    monkeypatch.setenv("SOWGATE_STATE_DIR", "/tmp/x")
    assert state_dir() == Path("/tmp/x")


def _pwm(**values: object) -> dict[str, object]:
    return {"name": "seed", "drive": "pwm_modbus", "product": "wheat",
            "target_rate_kg_ha": 200.0, **values}


@pytest.mark.parametrize(
    ("channels", "problem"),
    [
        ([_pwm(), _pwm(name="seed2")], "only one channel may have drive = 'pwm_modbus'"),
        ([_pwm(product="seed")], "channel[0].product = 'seed': a pwm_modbus channel meters"),
        ([_pwm(target_rate_kg_ha=300.0)], "channel[0].target_rate_kg_ha = 300 is outside"),
    ],
)
def test_pwm_modbus_channel_is_checked_against_the_crop_models(
    channels: list[dict[str, object]], problem: str
) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"channel": channels})
    assert any(problem in p for p in info.value.problems), info.value.problems


def test_a_pwm_modbus_channel_may_keep_the_node_id_of_a_can_channel() -> None:
    """node_id addresses a CAN metering controller; the RS485 PWM channel has none."""
    settings = parse_config({"channel": [
        _pwm(node_id=1), {"name": "deep", "target_rate_kg_ha": 300, "node_id": 1},
    ]})
    assert [c.node_id for c in settings.channel] == [1, 1]


def test_a_pwm_modbus_channel_sets_paper_a_crop_and_rate() -> None:
    from gateway.control.controller import Controller
    from gateway.core.alarms import AlarmBoard

    settings = parse_config({"channel": [_pwm()]})
    c = Controller(settings, AlarmBoard())
    assert (c.crop, c.rate_kg_ha) == ("wheat", 200.0)


def test_without_rs485_the_sources_on_it_are_refused_by_name() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"rs485": {"enabled": False}})
    problem = " ".join(info.value.problems)
    assert "speed.source includes radar" in problem
    assert "isobus.work_state_source includes inclinometer" in problem
    ok = parse_config({"rs485": {"enabled": False}, "speed": {"source": "isobus_then_gnss"},
                       "gnss": {}, "isobus": {"work_state_source": "hitch"}})
    assert not ok.rs485.enabled


@pytest.mark.parametrize(
    ("mqtt", "problem"),
    [
        ({"password": "s3cret"}, "needs username"),
        ({"password_file": "/run/credentials/sowgate.service/mqtt"}, "needs username"),
        ({"username": "u", "password": "p", "password_file": "/f"}, "not both"),
        ({"tls": {"key_file": "/etc/sowgate/client.key"}}, "key_file needs cert_file"),
    ],
)
def test_mqtt_credentials_that_would_be_silently_ignored_are_errors(
    mqtt: dict[str, object], problem: str
) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config({"mqtt": mqtt})
    assert any(line.startswith("mqtt") and problem in line for line in err.value.problems), (
        err.value.problems
    )


def test_mqtt_credentials_that_make_sense_load() -> None:
    s = parse_config({"mqtt": {"username": "seeder-01", "password_file": "/f",
                               "tls": {"cert_file": "/c.pem", "key_file": "/c.key"}}})
    assert s.mqtt.username == "seeder-01" and s.mqtt.tls is not None
    assert parse_config({"mqtt": {"tls": {}}}).mqtt.tls is not None  # system CAs, no client cert
# Issue 3's config contract, verbatim: no `enabled` keys, the tables alone describe the devices.
RECORDING_CONTRACT = """
[gnss]
port = "/dev/ttyUSB1"
baudrate = 115200
[seed_sensors]
source = "serial"          # serial | gpio
port = "/dev/ttyUSB2"      # serial: one line "D,<row>\\r\\n" per seed
baudrate = 115200
[positioning]
method = "interpolated"    # interpolated | paper
outlet_behind_antenna_m = 1.2          # longitudinal, outlets behind the main antenna
row_lateral_m = [-1.5, -0.9, -0.3, 0.3, 0.9, 1.5]   # per row, right of the centre line +
"""


def test_the_recording_contract_loads_and_switches_recording_on(tmp_path: Path) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text(RECORDING_CONTRACT)
    s = load_config(f)
    # a fitter who wrote these tables expects seeds to be recorded
    assert s.gnss.enabled and s.seed_sensors.enabled
    assert (s.gnss.port, s.gnss.baudrate) == ("/dev/ttyUSB1", 115200)
    assert (s.seed_sensors.source, s.seed_sensors.port) == ("serial", "/dev/ttyUSB2")
    assert s.seed_sensors.baudrate == 115200
    assert s.positioning.method == "interpolated"
    assert s.positioning.outlet_behind_antenna_m == 1.2
    assert s.positioning.row_lateral_m == [-1.5, -0.9, -0.3, 0.3, 0.9, 1.5]


@pytest.mark.parametrize(
    ("rows", "width_m", "expected"),
    [
        # the default machine: 1/3 m rows, outer outlets 1/6 m in from the 2 m edges
        (6, 2.0, [-5 / 6, -0.5, -1 / 6, 1 / 6, 0.5, 5 / 6]),
        # 48 rows at 0.75 m work 36 m: outer rows at +/-(18 - 0.375)
        (48, 36.0, [-17.625 + 0.75 * i for i in range(48)]),
        (1, 3.0, [0.0]),
    ],
)
def test_row_offsets_follow_the_machine_when_omitted(
    rows: int, width_m: float, expected: list[float]
) -> None:
    """A planter of any size works without listing its outlets: row spacing = width / rows,
    centred, row 1 on the left (negative)."""
    s = parse_config({"machine": {"rows": rows, "working_width_m": width_m}})
    assert s.positioning.row_lateral_m == pytest.approx(expected)


def test_an_explicit_row_offset_list_wins_over_the_derived_one() -> None:
    explicit = [-1.5, -0.9, -0.3, 0.3, 0.9, 1.5]
    s = parse_config({"positioning": {"row_lateral_m": explicit}})
    assert (s.machine.rows, s.machine.working_width_m) == (6, 2.0)
    assert s.positioning.row_lateral_m == explicit


def test_the_example_config_describes_the_machine_it_names() -> None:
    """examples/sowgate.toml is a 6-row, 2 m seeder: its outlets must span 2 m, not 3.6 m."""
    example = Path(__file__).resolve().parents[3] / "examples" / "sowgate.toml"
    s = load_config(example)
    lateral = s.positioning.row_lateral_m
    assert lateral is not None and len(lateral) == s.machine.rows
    spacing = s.machine.working_width_m / s.machine.rows
    assert max(lateral) - min(lateral) == pytest.approx(s.machine.working_width_m - spacing)


def test_absent_or_explicitly_disabled_device_tables_stay_off() -> None:
    s = parse_config({})
    assert not s.gnss.enabled and not s.seed_sensors.enabled
    s = parse_config({"gnss": {"port": "/dev/x", "enabled": False}})
    assert not s.gnss.enabled


def test_seed_sensors_without_gnss_is_an_error_not_a_silent_no_op() -> None:
    with pytest.raises(ConfigError, match=r"seed_sensors is enabled but gnss is not"):
        parse_config({"seed_sensors": {"port": "/dev/ttyUSB2"}})
    with pytest.raises(ConfigError, match=r"seed_sensors is enabled but gnss is not"):
        parse_config({"gnss": {"enabled": False}, "seed_sensors": {"enabled": True}})


@pytest.mark.parametrize("source", ["gnss", "radar_then_gnss"])
def test_a_gnss_speed_source_needs_the_receiver(source: str) -> None:
    with pytest.raises(ConfigError, match=rf"speed.source = '{source}' uses the GNSS speed"):
        parse_config({"speed": {"source": source}})
    assert parse_config({"speed": {"source": source}, "gnss": {}}).speed.source == source.split(
        "_then_"
    )


def test_an_old_loop_hz_still_loads_and_says_rs485_poll_hz_is_the_real_setting(
    tmp_path: Path,
) -> None:
    """control.loop_hz never changed anything (the loop ticks once per RS485 poll); a file
    written for an older version must load, and the fitter must hear what to set instead."""
    f = tmp_path / "sowgate.toml"
    f.write_text(CONTRACT.replace("poll_hz = 3.0", "poll_hz = 5.0") + "[control]\nloop_hz = 20\n")
    s = load_config(f)
    (note,) = s.deprecation_notes()
    assert note.startswith("control.loop_hz = 20 is deprecated and ignored")
    assert "set rs485.poll_hz (now 5 Hz)" in note
    assert not hasattr(s.control, "loop_hz")  # nothing can read it by mistake
    assert parse_config({}).deprecation_notes() == []
    with pytest.raises(ConfigError, match=r"control\.loop_hzz: Extra inputs"):
        parse_config({"control": {"loop_hzz": 20}})  # a typo is still an error


def test_the_daemon_logs_the_ignored_loop_hz_at_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from gateway.app.daemon import Daemon

    settings = parse_config({"hmi": {"enabled": False}, "control": {"loop_hz": 10.0}})
    with caplog.at_level("WARNING", logger="gateway.app.daemon"):
        Daemon(settings, tmp_path / "state")
    (record,) = [r for r in caplog.records if "loop_hz" in r.getMessage()]
    assert record.levelname == "WARNING"
    assert "rs485.poll_hz" in record.getMessage()


@pytest.mark.parametrize("bad", [0, 9.9, 5001, -1])
def test_the_seed_plausibility_limit_is_range_checked_and_named(bad: float) -> None:
    with pytest.raises(ConfigError, match=r"seed_sensors\.max_seeds_per_s_per_row") as err:
        parse_config({"gnss": {}, "seed_sensors": {"max_seeds_per_s_per_row": bad}})
    assert ("5000" if bad > 5000 else "10") in str(err.value)  # the bound it broke


def test_the_seed_plausibility_limit_defaults_to_a_fast_precision_planter_with_margin() -> None:
    settings = parse_config({"gnss": {}, "seed_sensors": {}})
    assert settings.seed_sensors.max_seeds_per_s_per_row == 200.0
    assert parse_config(
        {"gnss": {}, "seed_sensors": {"max_seeds_per_s_per_row": 450}}
    ).seed_sensors.max_seeds_per_s_per_row == 450.0


# ---- [row_monitor] ----------------------------------------------------------------------------


def test_the_row_monitor_is_on_by_default_and_a_table_can_turn_it_off() -> None:
    assert parse_config({}).row_monitor.enabled
    assert parse_config({"row_monitor": {"delay_s": 8}}).row_monitor.enabled
    assert not parse_config({"row_monitor": {"enabled": False}}).row_monitor.enabled


@pytest.mark.parametrize(("table", "problem"), [
    ({"delay_s": 0.5}, "row_monitor.delay_s: Input should be greater than or equal to 1"),
    ({"min_speed_kmh": 40}, "row_monitor.min_speed_kmh: Input should be less than or equal to 30"),
    ({"blocked_pct": 95}, "row_monitor.blocked_pct: Input should be less than or equal to 90"),
    ({"skip_pct": 8}, "row_monitor.skip_pct: must be above blocked_pct (10), in 10..100"),
    ({"min_expected_seeds": 1}, "row_monitor.min_expected_seeds: Input should be greater"),
    ({"delay": 5}, "row_monitor.delay: Extra inputs are not permitted; did you mean delay_s?"),
])
def test_row_monitor_keys_out_of_range_are_named_with_their_range(
    table: dict[str, object], problem: str
) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"row_monitor": table})
    assert info.value.problems[0].startswith(problem), info.value.problems


@pytest.mark.parametrize("value", [0, -1, 0.005, 51, 100])
def test_the_rotation_test_scale_out_of_range_is_a_config_error_naming_key_and_range(
    tmp_path: Path, value: float, capsys: pytest.CaptureFixture[str],
) -> None:
    """``[calibration] scale_g``: a scale of no error, or one coarser than any scale weighs a
    catch with, is a config error (exit 78) that names the key and the range."""
    from gateway.app.cli import main

    path = tmp_path / "sowgate.toml"
    path.write_text(f"[calibration]\nscale_g = {value}\n")
    assert main(["check-config", str(path)]) == 78
    err = capsys.readouterr().err
    assert "calibration.scale_g" in err and "0.01..50 g" in err and f"got {value}" in err


def test_the_rotation_test_scale_is_optional_and_kept() -> None:
    assert parse_config({}).calibration.scale_g is None
    assert parse_config({"calibration": {"scale_g": 5}}).calibration.scale_g == 5.0
