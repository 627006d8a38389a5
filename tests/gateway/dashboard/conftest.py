"""The fleet view's tests use the farm server's fresh PostgreSQL database per test."""

from tests.gateway.farm_server.conftest import database

__all__ = ["database"]
