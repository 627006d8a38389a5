"""A taken AgOpenGPS port is an alarm and a retry, never a daemon that stops."""

from __future__ import annotations

import asyncio
import socket

from drivers.agopengps_udp import AgOpenGpsEndpoint
from drivers.tasks import cancel_and_wait
from gateway.app.agopengps import open_until_listening
from gateway.core.alarms import AlarmBoard
from tests.helpers import eventually


async def test_a_taken_port_raises_unavailable_and_is_retried_until_free() -> None:
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("127.0.0.1", 0))
    port = holder.getsockname()[1]
    alarms = AlarmBoard("m1")
    endpoint = AgOpenGpsEndpoint(lambda m, t: None)
    task = asyncio.create_task(
        open_until_listening(endpoint, f"127.0.0.1:{port}", alarms, first_retry_s=0.05)
    )
    try:
        await eventually(lambda: alarms.is_active("agopengps.unavailable"), what="alarm")
        assert not task.done()
        holder.close()  # the other program lets go of the port
        await asyncio.wait_for(task, 15)
        assert endpoint.local_port == port
        assert not alarms.is_active("agopengps.unavailable")
    finally:
        holder.close()
        await cancel_and_wait(task)
        endpoint.close()
