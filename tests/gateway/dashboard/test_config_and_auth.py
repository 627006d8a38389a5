"""``[dashboard]``: where it listens, when it needs a password, and that the password holds."""

from __future__ import annotations

import asyncio
import base64
import socket
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from gateway.app.cli import main
from gateway.config import EXIT_CONFIG, ConfigError, dashboard_problems, parse_config
from gateway.dashboard.server import check_password, page_config
from tests.browser import DashboardProcess
from tests.helpers import run_sowgate, sowgate_env


def basic(user: str, password: str) -> str:
    return "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()


def test_defaults_listen_on_localhost_without_a_password() -> None:
    settings = parse_config({})
    d = settings.dashboard
    assert (d.listen, d.host, d.port, d.local_only) == ("127.0.0.1:8080", "127.0.0.1", 8080, True)
    assert d.tile_url is None and d.password_file is None
    assert dashboard_problems(settings) == []
    assert page_config(settings)["commands"] == []  # commands off: the page has no controls
    crops = page_config(settings)["crops"]  # the rate form's choices, with their ranges
    assert list(crops) == sorted(settings.control.crops) and "wheat" in crops
    wheat = settings.control.crops["wheat"]
    assert crops["wheat"] == [wheat.rate_min_kg_ha, wheat.rate_max_kg_ha]


@pytest.mark.parametrize("listen", ["8080", "host:", ":8080", "a b:1", "0.0.0.0:0",
                                    "0.0.0.0:70000", "[::1:8080"])
def test_a_bad_listen_address_is_a_config_error_naming_the_key_and_the_form(listen: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config({"dashboard": {"listen": listen}})
    (problem,) = [p for p in err.value.problems if p.startswith("dashboard.listen")]
    assert "HOST:PORT" in problem or "the port must be 1-65535" in problem, problem


@pytest.mark.parametrize("listen", ["127.0.0.1:8080", "0.0.0.0:80", "[::1]:8080",
                                    "cab-box.local:65535"])
def test_good_listen_addresses_are_taken(listen: str) -> None:
    assert parse_config({"dashboard": {"listen": listen}}).dashboard.listen == listen


def test_a_tile_url_needs_the_xyz_placeholders() -> None:
    with pytest.raises(ConfigError):
        parse_config({"dashboard": {"tile_url": "https://tiles.example/map.png"}})
    ok = parse_config({"dashboard": {"tile_url": "https://t.example/{z}/{x}/{y}.png"}})
    assert ok.dashboard.tile_url == "https://t.example/{z}/{x}/{y}.png"


def test_controls_beyond_localhost_need_a_password_file(tmp_path: Path) -> None:
    open_to_all = {"dashboard": {"listen": "0.0.0.0:8080"},
                   "commands": {"enabled": ["start", "stop"]}}
    (problem,) = dashboard_problems(parse_config(open_to_all))
    assert problem.startswith("dashboard.password_file: needed when dashboard.listen "
                              "(0.0.0.0:8080) is not localhost")
    # read-only page (no command the page offers): no password needed
    read_only = {"dashboard": {"listen": "0.0.0.0:8080"}, "commands": {"enabled": ["zero_tilt"]}}
    assert dashboard_problems(parse_config(read_only)) == []
    secret = tmp_path / "dashboard-password"
    secret.write_text("s3cret\n")
    with_password = {**open_to_all, "dashboard": {"listen": "0.0.0.0:8080",
                                                  "password_file": str(secret)}}
    assert dashboard_problems(parse_config(with_password)) == []
    missing = {"dashboard": {"password_file": str(tmp_path / "nope")}}
    (problem,) = dashboard_problems(parse_config(missing))
    assert problem == f"dashboard.password_file: file not found (got {str(tmp_path / 'nope')!r})"
    empty = tmp_path / "empty"
    empty.write_text("\n")
    (problem,) = dashboard_problems(parse_config({"dashboard": {"password_file": str(empty)}}))
    assert problem.startswith("dashboard.password_file: the file is empty")
    (problem,) = dashboard_problems(parse_config({"dashboard": {"password_file": str(tmp_path)}}))
    assert problem.startswith("dashboard.password_file: a directory, not a file")


def test_check_config_reports_dashboard_problems_with_exit_78(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The fitter hears it from check-config, not from a dashboard unit failing at boot."""
    f = tmp_path / "sowgate.toml"
    f.write_text('[commands]\nenabled = ["start", "stop"]\n[dashboard]\nlisten = "0.0.0.0:8080"\n')
    assert main(["check-config", str(f)]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "dashboard.password_file: needed when dashboard.listen (0.0.0.0:8080)" in err
    f.write_text(f'[dashboard]\npassword_file = "{tmp_path / "missing"}"\n')
    assert main(["check-config", str(f)]) == EXIT_CONFIG
    assert "dashboard.password_file: file not found" in capsys.readouterr().err
    f.write_text('[dashboard]\nlisten = "0.0.0.0:99999"\n')
    assert main(["check-config", str(f)]) == EXIT_CONFIG
    assert "dashboard.listen: the port must be 1-65535, not 99999" in capsys.readouterr().err
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n")
    f.write_text(f'[commands]\nenabled = ["start"]\n[dashboard]\nlisten = "0.0.0.0:8080"\n'
                 f'password_file = "{secret}"\n')
    assert main(["check-config", str(f)]) == 0, capsys.readouterr().err


def test_the_command_refuses_to_start_open_controls_with_exit_78(tmp_path: Path) -> None:
    config = tmp_path / "sowgate.toml"
    config.write_text('[commands]\nenabled = ["start", "stop", "rate"]\n')
    got = run_sowgate("dashboard", "--config", str(config), "--listen", "0.0.0.0:18080",
                      env=sowgate_env(tmp_path, clean=True))
    assert got.returncode == EXIT_CONFIG, got.stderr
    assert "dashboard.password_file: needed" in got.stderr
    got = run_sowgate("dashboard", "--config", str(config), "--listen", "nonsense",
                      env=sowgate_env(tmp_path, clean=True))
    assert got.returncode == EXIT_CONFIG and "--listen" in got.stderr, got.stderr


def test_basic_auth_takes_the_password_with_any_user_name() -> None:
    assert check_password(basic("farmer", "s3cret"), "s3cret")
    assert check_password(basic("", "s3cret"), "s3cret")
    assert not check_password(basic("farmer", "wrong"), "s3cret")
    assert not check_password(None, "s3cret")
    assert not check_password("Basic !!!notbase64", "s3cret")
    assert not check_password("Bearer s3cret", "s3cret")
    assert not check_password("Basic " + base64.b64encode(b"no-colon").decode(), "no-colon")


async def test_with_a_password_file_every_request_needs_the_password(tmp_path: Path) -> None:
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n")
    config = tmp_path / "sowgate.toml"
    # the broker port is closed: the page still loads (and says the broker is away)
    config.write_text(f'[mqtt]\nport = 9\n[dashboard]\npassword_file = "{secret}"\n')
    dash = DashboardProcess(config, tmp_path / "dashboard.log")
    await dash.start()
    try:
        status, headers, _ = await asyncio.to_thread(get, dash.url)
        assert status == 401 and "Basic" in headers["WWW-Authenticate"]
        status, _, body = await asyncio.to_thread(get, dash.url, basic("x", "s3cret"))
        assert status == 200 and b"sowgate dashboard" in body
        for path in ("static/dashboard.js", "api/health"):
            assert (await asyncio.to_thread(get, dash.url + path))[0] == 401
            status, _, _ = await asyncio.to_thread(get, dash.url + path, basic("x", "wrong"))
            assert status == 401
    finally:
        await dash.stop()


def get(url: str, authorization: str | None = None) -> tuple[int, Any, bytes]:
    """(status, headers, body) of a GET, errors included."""
    headers = {"Authorization": authorization} if authorization else {}
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers),
                                    timeout=10) as resp:
            return resp.status, resp.headers, resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers, b""


def test_the_allowed_hosts_default_to_the_listen_address_and_localhost_names() -> None:
    local = parse_config({}).dashboard
    assert local.trusted_hosts() == {"localhost", "127.0.0.1", "::1"}
    named = parse_config({"dashboard": {"listen": "cab-box.lan:8080"}}).dashboard
    assert "cab-box.lan" in named.trusted_hosts()
    wide = parse_config({"dashboard": {"listen": "0.0.0.0:8080"}}).dashboard
    own = socket.gethostname().lower()
    assert {"localhost", own, own.split(".")[0] + ".local"} <= wide.trusted_hosts()
    assert "0.0.0.0" not in wide.trusted_hosts()
    chosen = parse_config({"dashboard": {"allowed_hosts": ["Cab-Box.local", "[fd00::1]",
                                                           "*.farm.lan"]}}).dashboard
    assert chosen.trusted_hosts() == {"cab-box.local", "fd00::1", "*.farm.lan"}


@pytest.mark.parametrize("hosts", [[], ["http://cab-box.local"], ["cab-box.local:8080"],
                                   ["cab box"]])
def test_allowed_hosts_must_be_bare_names(hosts: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config({"dashboard": {"allowed_hosts": hosts}})
    assert any(p.startswith("dashboard.allowed_hosts") for p in err.value.problems)
