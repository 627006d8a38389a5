"""The MQTT link over TLS with a client certificate and a password file, against a real
mosquitto that requires all three: the configuration a fleet on a public 4G broker runs."""

from __future__ import annotations

import asyncio
import os
import ssl
import subprocess
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import aiomqtt
import pytest

from gateway.config import Settings, parse_config
from tests.gateway.link.test_mqtt import BASE, MACHINE, drops, running_link
from tests.helpers import eventually
from tests.mosquitto import Mosquitto

USER, PASSWORD = "seeder-t", "correct horse battery staple"


@dataclass(frozen=True)
class Pki:
    dir: Path
    ca: Path
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path
    other_ca: Path  # a CA that signed nothing the broker presents
    passwords: Path  # mosquitto_passwd file with USER
    password_file: Path  # what the box reads: PASSWORD and a newline


def _openssl(*args: str | Path) -> None:
    subprocess.run(["openssl", *map(str, args)], check=True, capture_output=True, timeout=60)


def _ca(d: Path, name: str) -> tuple[Path, Path]:
    key, pem = d / f"{name}.key", d / f"{name}.pem"
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
             "-nodes", "-keyout", key, "-out", pem, "-days", "2", "-subj", f"/CN={name}")
    return pem, key


def _leaf(d: Path, name: str, ca: tuple[Path, Path], ext: str) -> tuple[Path, Path]:
    key, csr, pem, extfile = (d / f"{name}.{s}" for s in ("key", "csr", "pem", "ext"))
    extfile.write_text(ext + "\n")
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", key, "-out", csr, "-subj", f"/CN={name}")
    _openssl("x509", "-req", "-in", csr, "-CA", ca[0], "-CAkey", ca[1], "-CAcreateserial",
             "-out", pem, "-days", "2", "-extfile", extfile)
    return pem, key


@pytest.fixture(scope="module")
def pki() -> Iterator[Pki]:
    with tempfile.TemporaryDirectory(prefix="sowgate-pki-") as tmp:
        d = Path(tmp)
        ca = _ca(d, "fleet-ca")
        other_ca, _ = _ca(d, "other-ca")
        server = _leaf(d, "broker", ca, "subjectAltName=IP:127.0.0.1")
        client = _leaf(d, "seeder-t", ca, "extendedKeyUsage=clientAuth")
        passwords = d / "passwd"
        subprocess.run(["mosquitto_passwd", "-b", "-c", str(passwords), USER, PASSWORD],
                       check=True, capture_output=True, timeout=30)
        password_file = d / "mqtt-password"
        password_file.write_text(PASSWORD + "\n")
        # mosquitto started as root drops to its own user: it must be able to read these
        os.chmod(d, 0o755)
        for f in d.iterdir():
            os.chmod(f, 0o644)
        yield Pki(d, ca[0], *server, *client, other_ca, passwords, password_file)


@pytest.fixture
def tls_broker(pki: Pki) -> Iterator[Mosquitto]:
    options = (
        f"cafile {pki.ca}\ncertfile {pki.server_cert}\nkeyfile {pki.server_key}\n"
        "require_certificate true\n"
    )
    with Mosquitto(listener_options=options, password_file=pki.passwords) as broker:
        yield broker


def tls_settings(port: int, pki: Pki, *, ca: Path, password_file: Path) -> Settings:
    return parse_config({
        "machine": {"id": MACHINE},
        "mqtt": {
            "enabled": True, "host": "127.0.0.1", "port": port, "keepalive": 5,
            "reconnect_max_s": 0.5, "batch_max_records": 200, "batch_max_ms": 100,
            "username": USER, "password_file": str(password_file),
            "tls": {"ca_file": str(ca), "cert_file": str(pki.client_cert),
                    "key_file": str(pki.client_key)},
        },
    })


async def retained_status(port: int, pki: Pki) -> bytes:
    tls = aiomqtt.TLSParameters(ca_certs=str(pki.ca), certfile=str(pki.client_cert),
                                keyfile=str(pki.client_key), cert_reqs=ssl.CERT_REQUIRED)
    async with aiomqtt.Client("127.0.0.1", port, identifier="dashboard-tls", username=USER,
                              password=PASSWORD, tls_params=tls) as client:
        await client.subscribe(f"{BASE}/status", qos=1)
        async with asyncio.timeout(10):
            async for message in client.messages:
                assert isinstance(message.payload, bytes)
                return message.payload
    raise AssertionError("no retained status")


async def test_tls_client_cert_and_password_file_deliver_every_record(
    tls_broker: Mosquitto, pki: Pki, tmp_path: Path
) -> None:
    settings = tls_settings(tls_broker.port, pki, ca=pki.ca, password_file=pki.password_file)
    async with running_link(settings, tmp_path / "r.db") as run:
        run.store.add_seeds(drops(600))
        run.store.flush()  # committed: the backlog counts them from now on
        await eventually(lambda: run.store.backlog() == 0, what="outbox drained over TLS")
        assert run.link.connected and run.link.stats.seeds_published >= 600
        assert await retained_status(tls_broker.port, pki) == b"online"


@pytest.mark.parametrize(
    ("wrong", "reason"),
    [
        ("password", "authori"),  # "Not authorized" / "not authorised", paho's wording varies
        ("ca", "CERTIFICATE_VERIFY_FAILED"),
    ],
)
async def test_wrong_credentials_never_deliver_and_say_why(
    tls_broker: Mosquitto, pki: Pki, tmp_path: Path, wrong: str, reason: str
) -> None:
    bad_password = tmp_path / "bad-password"
    bad_password.write_text("guess\n")
    settings = tls_settings(
        tls_broker.port, pki,
        ca=pki.other_ca if wrong == "ca" else pki.ca,
        password_file=bad_password if wrong == "password" else pki.password_file,
    )
    async with running_link(settings, tmp_path / "r.db") as run:
        run.store.add_seeds(drops(50))
        run.store.flush()
        await eventually(lambda: reason.lower() in run.link.stats.last_error.lower(), 30,
                         f"{reason!r} in last_error")
        assert not run.link.connected and run.link.stats.connects == 0
        assert run.store.backlog() == 50  # kept for when the credentials are fixed


@pytest.mark.parametrize("key", ["tls.ca_file", "tls.cert_file", "tls.key_file", "password_file"])
async def test_a_file_gone_at_run_time_is_named_in_the_error_and_retried(
    tls_broker: Mosquitto, pki: Pki, tmp_path: Path, key: str
) -> None:
    """check-config and the start check the files; one deleted later (a certificate rotation
    gone wrong) must not read as a bare ``[Errno 2] No such file or directory``."""
    gone = tmp_path / "rotated-away.pem"
    settings = tls_settings(tls_broker.port, pki, ca=pki.ca, password_file=pki.password_file)
    section = settings.mqtt.tls if key.startswith("tls.") else settings.mqtt
    assert section is not None
    setattr(section, key.removeprefix("tls."), str(gone))
    async with running_link(settings, tmp_path / "r.db") as run:
        await eventually(lambda: run.link.stats.last_error != "", 30, "a connect error")
        error = run.link.stats.last_error
        assert f"mqtt.{key} {gone}" in error, error
        gone.write_bytes((pki.ca if key == "tls.ca_file" else pki.client_cert).read_bytes())
        if key == "tls.key_file":
            gone.write_bytes(pki.client_key.read_bytes())
        elif key == "password_file":
            gone.write_text(PASSWORD + "\n")
        await eventually(lambda: run.link.connected, 60, "connected once the file is back",
                         detail=lambda: run.link.stats.last_error)
