"""Nothing off without a word: a table in the file switches its part on, the daemon and
``check-config`` say which parts are on, and a file or directory the config names but that is
not there is a config error (exit 78) that names the key and the path."""

from __future__ import annotations

import logging
import subprocess
from pathlib import Path
from typing import Any

import pytest

from gateway.app.cli import main
from gateway.config import ConfigError, load_config, parse_config, parts_summary
from tests.helpers import run_sowgate, sowgate_env

ROOT = Path(__file__).resolve().parents[3]

# a table with its part's ordinary keys but no `enabled`, for every optional part
PRESENT_WITHOUT_ENABLED: dict[str, dict[str, Any]] = {
    "mqtt": {"host": "broker.example", "port": 8883},
    "can": {"channel": "can0"},
    "isobus": {"channel": "can1"},
    "gnss": {"port": "/dev/ttyUSB1"},
    "prescription": {"path": "/srv/map.geojson"},
    "hopper_scale": {"device_id": 5},
    "agopengps": {"listen": "0.0.0.0:8888"},
}


@pytest.mark.parametrize("part", sorted(PRESENT_WITHOUT_ENABLED))
def test_a_table_present_switches_its_part_on(part: str) -> None:
    s = parse_config({part: PRESENT_WITHOUT_ENABLED[part]})
    assert getattr(s, part).enabled is True


@pytest.mark.parametrize("part", sorted(PRESENT_WITHOUT_ENABLED))
def test_enabled_false_keeps_a_present_table_off(part: str) -> None:
    s = parse_config({part: {**PRESENT_WITHOUT_ENABLED[part], "enabled": False}})
    assert getattr(s, part).enabled is False


def test_absent_tables_are_off_except_the_bus_and_the_screen() -> None:
    """rs485 and hmi are paper A's machine and on by default, as documented; every other part
    is off until its table is written."""
    s = parse_config({})
    assert s.rs485.enabled and s.hmi.enabled
    for part in ("mqtt", "can", "isobus", "gnss", "seed_sensors", "prescription",
                 "hopper_scale"):
        assert getattr(s, part).enabled is False, part


def test_a_nested_table_alone_counts_as_present() -> None:
    assert parse_config({"mqtt": {"tls": {}}}).mqtt.enabled


def test_the_mqtt_table_from_the_issue_switches_mqtt_on(tmp_path: Path) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text('[mqtt]\nhost = "broker.example"\nport = 1883\n')
    assert load_config(f).mqtt.enabled


def test_an_environment_override_makes_a_table_present(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("SOWGATE_MQTT__HOST", "broker.example")
    s = parse_config({})
    assert s.mqtt.enabled and s.mqtt.host == "broker.example"


def test_an_environment_override_can_switch_a_present_table_off(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("SOWGATE_MQTT__ENABLED", "false")
    assert not parse_config({"mqtt": {"host": "broker.example"}}).mqtt.enabled


# ---- which parts are on -----------------------------------------------------------------------


def test_the_parts_summary_names_every_part_and_how_it_is_reached() -> None:
    s = parse_config({
        "rs485": {"port": "/dev/ttyUSB0"},
        "hmi": {"enabled": False},
        "gnss": {"port": "/dev/ttyUSB1"},
        "mqtt": {"host": "broker.example", "port": 8883, "tls": {}},
        "channel": [{"name": "seed", "target_rate_kg_ha": 150, "node_id": 2}],
    })
    assert parts_summary(s) == (
        "parts: rs485 on (/dev/ttyUSB0), hmi off, gnss on (/dev/ttyUSB1), seed_sensors off, "
        "row_monitor off (no seed_sensors), mqtt on (broker.example:8883 TLS), can off, "
        "isobus off, prescription off, hopper_scale off, agopengps off, "
        "channel seed off (can_pid, but can is off)"
    )


def test_check_config_prints_the_parts_after_ok(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = tmp_path / "sowgate.toml"
    f.write_text('[mqtt]\nhost = "broker.example"\nport = 1883\n[can]\n')
    assert main(["check-config", str(f)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith("ok (machine seeder-01, 6 rows)")
    assert out[1] == parts_summary(load_config(f))
    assert "mqtt on (broker.example:1883)" in out[1] and "can on (socketcan can0)" in out[1]


def test_the_daemon_logs_the_parts_once_at_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from gateway.app.daemon import Daemon

    settings = parse_config({"hmi": {"enabled": False}, "isobus": {"channel": "vcan9"}})
    with caplog.at_level(logging.INFO, logger="gateway.app.daemon"):
        Daemon(settings, tmp_path / "state")
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("parts: ")]
    assert lines == [parts_summary(settings)]
    assert "isobus on (socketcan vcan9)" in lines[0] and "mqtt off" in lines[0]


# ---- files the config names --------------------------------------------------------------------


def _tls_config(tmp_path: Path, **tls: str) -> dict[str, Any]:
    password = tmp_path / "mqtt-password"
    password.write_text("secret\n")
    cert, key, ca = tmp_path / "client.pem", tmp_path / "client.key", tmp_path / "ca.pem"
    for f in (cert, key, ca):
        f.write_text("-----BEGIN-----\n")
    files = {"ca_file": str(ca), "cert_file": str(cert), "key_file": str(key)}
    return {
        "mqtt": {"host": "broker.example", "port": 8883, "username": "u",
                 "password_file": tls.pop("password_file", str(password)),
                 "tls": {**files, **tls}},
    }


def _toml(data: dict[str, Any], path: Path) -> Path:
    import tomli_w

    path.write_text(tomli_w.dumps(data))
    return path


@pytest.mark.parametrize(
    "key", ["tls.ca_file", "tls.cert_file", "tls.key_file", "password_file"]
)
def test_check_config_names_a_missing_mqtt_file(
    key: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = str(tmp_path / "nowhere" / "file.pem")
    data = _tls_config(tmp_path, **{key.removeprefix("tls."): missing})
    assert main(["check-config", str(_toml(data, tmp_path / "s.toml"))]) == 78
    err = capsys.readouterr().err
    assert f"mqtt.{key}: file not found (got {missing!r})" in err.splitlines()


def test_check_config_accepts_mqtt_files_that_are_there(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check-config", str(_toml(_tls_config(tmp_path), tmp_path / "s.toml"))]) == 0


def test_files_of_a_part_that_is_off_are_not_needed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _tls_config(tmp_path, ca_file=str(tmp_path / "gone.pem"))
    data["mqtt"]["enabled"] = False
    assert main(["check-config", str(_toml(data, tmp_path / "s.toml"))]) == 0


def test_a_directory_where_a_file_belongs_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _tls_config(tmp_path, ca_file=str(tmp_path))
    assert main(["check-config", str(_toml(data, tmp_path / "s.toml"))]) == 78
    assert f"mqtt.tls.ca_file: a directory, not a file (got {str(tmp_path)!r})" in (
        capsys.readouterr().err
    )


def test_a_missing_prescription_map_is_a_config_error_at_start(tmp_path: Path) -> None:
    from gateway.app.daemon import Daemon

    missing = str(tmp_path / "field-7.geojson")
    settings = parse_config({
        "hmi": {"enabled": False}, "can": {"interface": "virtual"},
        "prescription": {"path": missing},
        "channel": [{"name": "seed", "target_rate_kg_ha": 150, "node_id": 2,
                     "prescription_attribute": "rate"}],
    })
    with pytest.raises(ConfigError) as caught:
        Daemon(settings, tmp_path / "state")
    assert caught.value.problems == [f"prescription.path: file not found (got {missing!r})"]


def _run(
    config: Path, env: dict[str, str], cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """The real console script, as systemd starts it; it must stop by itself with 78."""
    return run_sowgate(
        "run", "--config", str(config),
        env=sowgate_env(env=env, clean=True), cwd=cwd, timeout=30, console_script=True,
    )


def test_run_with_a_missing_ca_file_exits_78_naming_key_and_path(tmp_path: Path) -> None:
    missing = str(tmp_path / "ca.pem.old")
    data = {"hmi": {"enabled": False}, **_tls_config(tmp_path, ca_file=missing)}
    proc = _run(_toml(data, tmp_path / "s.toml"), {"SOWGATE_STATE_DIR": str(tmp_path / "st")})
    assert proc.returncode == 78, proc.stderr
    assert f"mqtt.tls.ca_file: file not found (got {missing!r})" in proc.stderr
    assert "Traceback" not in proc.stderr


# ---- the state directory ------------------------------------------------------------------------


def test_run_with_a_state_dir_that_is_a_file_exits_78(tmp_path: Path) -> None:
    in_the_way = tmp_path / "state"
    in_the_way.write_text("not a directory\n")
    cfg = _toml({"hmi": {"enabled": False}}, tmp_path / "s.toml")
    proc = _run(cfg, {"SOWGATE_STATE_DIR": str(in_the_way)})
    assert proc.returncode == 78, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        f"$SOWGATE_STATE_DIR: a file, not a directory (got {str(in_the_way)!r})"
    )
    assert "Traceback" not in proc.stderr


def test_run_with_a_systemd_state_dir_that_cannot_be_created_exits_78(tmp_path: Path) -> None:
    blocker = tmp_path / "var-lib"
    blocker.write_text("")
    wanted = blocker / "sowgate"
    cfg = _toml({"hmi": {"enabled": False}}, tmp_path / "s.toml")
    proc = _run(cfg, {"STATE_DIRECTORY": str(wanted)})
    assert proc.returncode == 78, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("$STATE_DIRECTORY: cannot create the directory")
    assert last.endswith(f"(got {str(wanted)!r})")
    assert "Traceback" not in proc.stderr


def test_run_with_the_default_state_dir_blocked_names_the_variables(tmp_path: Path) -> None:
    (tmp_path / "sowgate-state").write_text("")
    cfg = _toml({"hmi": {"enabled": False}}, tmp_path / "s.toml")
    proc = _run(cfg, {}, cwd=tmp_path)
    assert proc.returncode == 78, proc.stderr
    assert (
        "state directory (default; set $SOWGATE_STATE_DIR): a file, not a directory "
        "(got 'sowgate-state')"
    ) in proc.stderr


def test_run_with_a_store_path_under_a_file_exits_78(tmp_path: Path) -> None:
    blocker = tmp_path / "data"
    blocker.write_text("")
    store = blocker / "records.sqlite3"
    cfg = _toml({"hmi": {"enabled": False}, "mqtt": {"port": 1},
                 "store": {"path": str(store)}}, tmp_path / "s.toml")
    proc = _run(cfg, {"SOWGATE_STATE_DIR": str(tmp_path / "st")})
    assert proc.returncode == 78, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("store.path: cannot create the directory")
    assert last.endswith(f"(got {str(store)!r})")
    assert "Traceback" not in proc.stderr


def test_every_table_with_an_enabled_switch_follows_the_one_rule() -> None:
    """A later table (a hopper, say) with ``enabled: bool`` must be an ``OptionalPart``, or a
    fitter's ``[hopper]`` table would again be silently off."""
    from gateway.config import OptionalPart, Settings, optional_parts

    for name, field in Settings.model_fields.items():
        kind = field.annotation
        switch = getattr(kind, "model_fields", {}).get("enabled")
        if isinstance(kind, type) and switch is not None and switch.annotation is bool:
            assert issubclass(kind, OptionalPart), name
            assert name in optional_parts()
