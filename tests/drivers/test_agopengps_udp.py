"""The AgOpenGPS UDP endpoint over real sockets on loopback: what it obeys, answers and drops.

127.0.0.1 plays AgIO and 127.0.0.2 a stranger on the tractor LAN (both are loopback on Linux).
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator

import pytest

from drivers.agopengps_udp import AgOpenGpsEndpoint
from protocol import agopengps as aog
from tests.helpers import eventually

ON4 = (True,) * 4 + (False,) * 12


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def udp(host: str, port: int = 0) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((host, port))
    s.setblocking(False)
    return s


@pytest.fixture
async def agio_socket() -> AsyncIterator[socket.socket]:
    s = udp("127.0.0.1")
    yield s
    s.close()


async def started(endpoint: AgOpenGpsEndpoint) -> int:
    await endpoint.open("127.0.0.1", 0)
    port = endpoint.local_port
    assert port is not None
    return port


async def recv(sock: socket.socket) -> bytes:
    loop = asyncio.get_running_loop()
    return await asyncio.wait_for(loop.sock_recv(sock, 1024), 15)


async def test_obeys_agio_answers_its_hello_and_sends_texts(agio_socket: socket.socket) -> None:
    got: list[aog.Message] = []
    agio_port = agio_socket.getsockname()[1]
    endpoint = AgOpenGpsEndpoint(lambda m, t: got.append(m), agio=("127.0.0.1", agio_port),
                                 hello_sections=lambda: ON4)
    port = await started(endpoint)
    try:
        agio_socket.sendto(aog.encode_steer_data(7.5, ON4), ("127.0.0.1", port))
        agio_socket.sendto(aog.hello_from_agio(), ("127.0.0.1", port))
        reply = await recv(agio_socket)
        assert reply == aog.hello_reply(ON4) and len(reply) == 11
        await eventually(lambda: len(got) == 2, what="both frames handed on")
        assert got[0] == aog.SteerData(7.5, ON4)
        assert endpoint.send_text("Row 7 blocked")
        text = aog.decode_frame(await recv(agio_socket))
        assert text.pgn == 221 and text.data[2:] == b"Row 7 blocked"
    finally:
        endpoint.close()


async def test_bad_frames_are_counted_by_reason(agio_socket: socket.socket) -> None:
    got: list[aog.Message] = []
    endpoint = AgOpenGpsEndpoint(lambda m, t: got.append(m))
    port = await started(endpoint)
    to = ("127.0.0.1", port)
    try:
        good = aog.encode_steer_data(5.0, ON4)
        agio_socket.sendto(good[:-1] + bytes([good[-1] ^ 1]), to)
        agio_socket.sendto(b"\x80\x81\x7f", to)
        agio_socket.sendto(aog.encode(0x7F, 254, (2000).to_bytes(2, "little") + bytes(6)), to)
        agio_socket.sendto(aog.encode(0x7E, 254, bytes(8)), to)
        agio_socket.sendto(good, to)
        await eventually(lambda: endpoint.accepted == 1, what="the good frame")
        assert dict(endpoint.rejected) == {
            "bad_checksum": 1, "bad_frame": 1, "out_of_range": 1, "not_from_agio": 1,
        }
        assert got == [aog.SteerData(5.0, ON4)]
        assert endpoint.trusted_host == "127.0.0.1"
    finally:
        endpoint.close()


async def test_a_strangers_flood_cannot_move_the_machine(agio_socket: socket.socket) -> None:
    """AgIO is adopted first; 2000 well-formed frames from another host change nothing and
    are not answered; AgIO's own flood is cut to the rate limit."""
    clock = Clock()
    got: list[aog.Message] = []
    endpoint = AgOpenGpsEndpoint(lambda m, t: got.append(m), max_frames_per_s=50, clock=clock)
    port = await started(endpoint)
    to = ("127.0.0.1", port)
    stranger = udp("127.0.0.2")
    try:
        agio_socket.sendto(aog.encode_steer_data(6.0, ON4), to)
        await eventually(lambda: endpoint.accepted == 1, what="AgIO adopted")
        for burst in range(1, 21):  # in bursts of 100, so the socket buffer drops none
            for _ in range(100):
                stranger.sendto(aog.encode_steer_data(30.0, (True,) * 16), to)
            await eventually(lambda n=burst: endpoint.rejected["untrusted_sender"] == n * 100,
                             what=f"burst {burst} dropped")
        stranger.sendto(aog.hello_from_agio(), to)
        await eventually(lambda: endpoint.rejected["untrusted_sender"] == 2001,
                         what="every stranger frame dropped",
                         detail=lambda: dict(endpoint.rejected))
        assert got == [aog.SteerData(6.0, ON4)]
        with pytest.raises(BlockingIOError):
            stranger.recv(64)  # the stranger's hello was not answered
        # AgIO itself flooding: at most the bucket (50) gets through while the clock stands
        for _ in range(200):
            agio_socket.sendto(aog.encode_steer_data(6.0, ON4), to)
        await eventually(lambda: endpoint.accepted + endpoint.rejected["over_rate"] == 201,
                         what="the flood handled")
        assert endpoint.accepted <= 50
        # after AgIO has been silent for stale_after_s, a new AgIO address may take over
        clock.t += endpoint.stale_after_s + 0.1
        stranger.sendto(aog.encode_steer_data(4.0, ON4), to)
        await eventually(lambda: endpoint.trusted_host == "127.0.0.2", what="re-adoption")
    finally:
        stranger.close()
        endpoint.close()


async def test_a_configured_agio_is_the_only_sender_ever_obeyed() -> None:
    clock = Clock()
    got: list[aog.Message] = []
    endpoint = AgOpenGpsEndpoint(lambda m, t: got.append(m), agio=("127.0.0.1", 9999),
                                 clock=clock)
    port = await started(endpoint)
    stranger = udp("127.0.0.2")
    try:
        clock.t += 100.0  # however long AgIO has been silent
        stranger.sendto(aog.encode_steer_data(9.0, ON4), ("127.0.0.1", port))
        await eventually(lambda: endpoint.rejected["untrusted_sender"] == 1, what="dropped")
        assert got == [] and endpoint.trusted_host == "127.0.0.1"
    finally:
        stranger.close()
        endpoint.close()
