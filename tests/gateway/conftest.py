"""Fixtures shared by the gateway tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.mosquitto import Mosquitto


def _broker(*, persistent: bool, started: bool = True) -> Iterator[Mosquitto]:
    broker = Mosquitto(persistent=persistent)
    try:
        if started:
            broker.start()
        yield broker
    finally:
        broker.close()


@pytest.fixture
def mosquitto() -> Iterator[Mosquitto]:
    """A running broker on a free port; ``.stop()``/``.start()`` keep the same port."""
    yield from _broker(persistent=False)


@pytest.fixture
def persistent_mosquitto() -> Iterator[Mosquitto]:
    """A broker that keeps subscriber sessions across ``stop()``/``start()`` (like production)."""
    yield from _broker(persistent=True)


@pytest.fixture
def stopped_mosquitto() -> Iterator[Mosquitto]:
    """A broker configured on a free port but not started: "unreachable at start" cases."""
    yield from _broker(persistent=True, started=False)
