"""Fixtures shared by the gateway tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.mosquitto import Mosquitto


@pytest.fixture
def mosquitto() -> Iterator[Mosquitto]:
    """A running broker on a free port; ``.stop()``/``.start()`` keep the same port."""
    broker = Mosquitto()
    broker.start()
    try:
        yield broker
    finally:
        broker.close()


@pytest.fixture
def persistent_mosquitto() -> Iterator[Mosquitto]:
    """A broker that keeps subscriber sessions across ``stop()``/``start()`` (like production)."""
    broker = Mosquitto(persistent=True)
    broker.start()
    try:
        yield broker
    finally:
        broker.close()


@pytest.fixture
def stopped_mosquitto() -> Iterator[Mosquitto]:
    """A broker configured on a free port but not started: "unreachable at start" cases."""
    broker = Mosquitto(persistent=True)
    try:
        yield broker
    finally:
        broker.close()
