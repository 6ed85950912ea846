"""The userspace link impairment of ``tests/netem.py`` over loopback: what goes through comes out
whole and in order, no sooner than its delay, and exactly the seed's items are lost (dropped
datagrams, retransmitted TCP chunks)."""

import asyncio
import random

import pytest

from tests.mosquitto import free_loopback_port
from tests.netem import Impairment, Route, TcpRelay, UdpRelay

IMPAIRMENT = Impairment(delay_min_s=0.002, delay_max_s=0.006, loss=0.2, retransmit_s=0.02)


def lost_draws(seed: str, items: int) -> list[bool]:
    """Which of ``items`` a line seeded ``seed`` loses (its draws: a delay, then a loss)."""
    rng = random.Random(seed)
    lost = []
    for _ in range(items):
        rng.uniform(IMPAIRMENT.delay_min_s, IMPAIRMENT.delay_max_s)
        lost.append(rng.random() < IMPAIRMENT.loss)
    return lost


async def _echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    while data := await reader.read(4096):
        writer.write(data)
        await writer.drain()
    writer.close()


@pytest.mark.asyncio
async def test_tcp_chunks_come_back_whole_in_order_after_their_delay_and_seeded_retransmissions():
    target = await asyncio.start_server(_echo, "127.0.0.1", 0)
    port = target.sockets[0].getsockname()[1]
    route = Route("echo", ("127.0.0.1", free_loopback_port()), ("127.0.0.1", port))
    loop = asyncio.get_running_loop()
    up, down = lost_draws("7:echo:1:up", 40), lost_draws("7:echo:1:down", 40)
    async with target, TcpRelay(route, IMPAIRMENT, seed=7).serving() as relay:
        reader, writer = await asyncio.open_connection(*route.listen)
        for number in range(40):  # one at a time: each write is one chunk each way
            sent_at = loop.time()
            writer.write(f"message {number:03d};".encode())
            echoed = await asyncio.wait_for(reader.readexactly(12), timeout=10)
            assert echoed == f"message {number:03d};".encode()
            # A lost segment costs its retransmission (lower bounds: a loaded machine is slower).
            retransmits = up[number] + down[number]
            least_s = 2 * IMPAIRMENT.delay_min_s + retransmits * IMPAIRMENT.retransmit_s
            assert loop.time() - sent_at >= least_s - 1e-3
        writer.close()
        await writer.wait_closed()

    assert relay.stats.chunks == 80
    assert relay.stats.retransmitted == up.count(True) + down.count(True) > 0
    assert relay.stats.dropped == 0


class _Collect(asyncio.DatagramProtocol):
    def __init__(self, answer: bool = False) -> None:
        self.answer, self.received = answer, []
        self.arrived = asyncio.Event()

    def connection_made(self, transport):
        self.transport = transport

    def datagram_received(self, data, addr):
        self.received.append(data)
        if self.answer:
            self.transport.sendto(data, addr)
        self.arrived.set()


@pytest.mark.asyncio
async def test_datagrams_that_are_not_lost_come_back_in_order_and_the_lost_ones_are_the_seeds():
    loop = asyncio.get_running_loop()
    echo_transport, _ = await loop.create_datagram_endpoint(
        lambda: _Collect(answer=True), local_addr=("127.0.0.1", 0)
    )
    target = echo_transport.get_extra_info("sockname")
    route = Route("mavlink", ("127.0.0.1", free_loopback_port()), target)
    up, down = lost_draws("3:mavlink:1:up", 100), lost_draws("3:mavlink:1:down", 100)
    # The answers' line draws once per datagram that reached the target.
    through = [n for n in range(100) if not up[n]]
    back = [n for n, lost in zip(through, down, strict=False) if not lost]
    try:
        async with UdpRelay(route, IMPAIRMENT, seed=3).serving() as relay:
            client, collect = await loop.create_datagram_endpoint(
                _Collect, local_addr=("127.0.0.1", 0)
            )
            for number in range(100):
                client.sendto(b"%03d" % number, route.listen)
            while len(collect.received) < len(back):
                collect.arrived.clear()
                await asyncio.wait_for(collect.arrived.wait(), timeout=10)
            client.close()
    finally:
        echo_transport.close()

    assert collect.received == [b"%03d" % n for n in back]
    assert relay.stats.dropped == 100 - len(back) > 0
    assert relay.stats.chunks == 100 + len(through)


@pytest.mark.asyncio
async def test_no_impairment_relays_as_is():
    target = await asyncio.start_server(_echo, "127.0.0.1", 0)
    port = target.sockets[0].getsockname()[1]
    route = Route("plain", ("127.0.0.1", free_loopback_port()), ("127.0.0.1", port))
    async with target, TcpRelay(route, Impairment.none(), seed=1).serving() as relay:
        reader, writer = await asyncio.open_connection(*route.listen)
        writer.write(b"x" * 100_000)
        assert await asyncio.wait_for(reader.readexactly(100_000), timeout=10) == b"x" * 100_000
        writer.close()
        await writer.wait_closed()
    assert relay.stats.bytes == 200_000
    assert relay.stats.retransmitted == relay.stats.dropped == 0
