"""The farm server's real parts: the PostgreSQL on 127.0.0.1:5432 (trust auth, user postgres;
each test makes its own database and drops it) and a mosquitto with the shipped ACL."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import psycopg
import pytest

from gateway.farm_server.db import migrate
from tests.mosquitto import Mosquitto

REPO = Path(__file__).resolve().parents[3]
ACL = REPO / "examples" / "mosquitto-farm.acl"
ADMIN_URL = "postgresql://postgres@127.0.0.1:5432/postgres"


@pytest.fixture
def database() -> Iterator[str]:
    """A fresh database with the sowgate schema (migrated as the owner); its URL."""
    name = f"sowgate_test_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"'.encode())
    url = f"postgresql://postgres@127.0.0.1:5432/{name}"
    try:
        migrate(url)
        yield url
    finally:
        with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'.encode())


@pytest.fixture
def broker() -> Iterator[Mosquitto]:
    """mosquitto with examples/mosquitto-farm.acl: each machine publishes only as itself."""
    with Mosquitto(listener_options=f"acl_file {ACL}\n") as b:
        yield b


def rows(url: str, sql: str) -> list[tuple[object, ...]]:
    with psycopg.connect(url) as conn:
        return conn.execute(sql.encode()).fetchall()


def database_away(url: str, away: bool) -> None:
    """Refuse (and end) every connection to this test database, or allow them again."""
    name = url.rsplit("/", 1)[1]
    with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS {not away}'.encode())
        if away:
            admin.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                          "WHERE datname = %s", (name,))
