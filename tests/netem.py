"""A Wi-Fi-like link in userspace: TCP and UDP relays that delay, and lose, what they carry.

For kernels without ``tc netem`` (no ``sch_netem`` module, no iptables either): put a relay where
a process would connect, and point it at the real endpoint. Every direction of every connection is
a :class:`DelayLine`: each chunk (TCP) or datagram (UDP) leaves a seeded random delay after it
came in, in order (802.11 delivers in order per traffic class), and a lost one:

- UDP (MAVLink): the datagram is dropped;
- TCP (MQTT): nothing is lost above TCP, a lost segment costs a retransmission. It is modelled
  as one RTO (``retransmit_s``, 200 ms: Linux's minimum RTO) added to that chunk's delay, and,
  since the line keeps order, to every chunk queued behind it (head-of-line blocking, as TCP).

The defaults are a Wi-Fi mesh's: 20 ms +- 10 ms (uniform 10-30 ms) each way and 2 % loss, i.e.
what ``tc qdisc add dev X root netem delay 20ms 10ms loss 2%`` on both ends of a link gives,
without its reordering. Seeds are per line (``seed``, link name, connection number, direction),
so a run's draws do not depend on what other connections carried (a route is named by its kind
and place on the command line: ``tcp1``, ``udp2``).

As a tool (runs until SIGINT or SIGTERM, then prints what it did)::

    python -m tests.netem --seed 1 --tcp 10.0.0.1:1884=127.0.0.1:1883 \
        --udp 127.0.0.1:14540=10.0.1.2:14540

prints ``netem: ready`` once every listener is bound. ``--delay-ms 0 0 --loss 0`` relays as is.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import random
import signal
import socket
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import cast


@dataclass(frozen=True)
class Impairment:
    """What a link does to what it carries, each way."""

    delay_min_s: float = 0.010
    delay_max_s: float = 0.030
    loss: float = 0.02
    retransmit_s: float = 0.200

    @classmethod
    def none(cls) -> Impairment:
        return cls(0.0, 0.0, 0.0, 0.0)

    def describe(self) -> str:
        return (
            f"{1e3 * self.delay_min_s:.0f}-{1e3 * self.delay_max_s:.0f} ms each way, "
            f"{100 * self.loss:g} % lost (TCP: +{1e3 * self.retransmit_s:.0f} ms)"
        )


@dataclass
class LineStats:
    """What the lines of one link carried, both directions, every connection."""

    chunks: int = 0
    bytes: int = 0
    dropped: int = 0
    retransmitted: int = 0


class DelayLine:
    """Bytes in through :meth:`put`, out through ``send`` in the same order, each after its
    delay (never before the one ahead of it). ``drop_lost``: a lost item is dropped (datagrams),
    else delayed by ``retransmit_s`` more (a TCP stream). :meth:`close` ends :meth:`run` once
    everything queued before it went out."""

    def __init__(
        self,
        impairment: Impairment,
        seed: str,
        send: Callable[[bytes], Awaitable[None]],
        stats: LineStats,
        *,
        drop_lost: bool,
    ) -> None:
        self.impairment = impairment
        self._rng = random.Random(seed)
        self._send = send
        self._stats = stats
        self._drop_lost = drop_lost
        self._queue: asyncio.Queue[tuple[float, bytes | None]] = asyncio.Queue()
        self._last_due = 0.0

    def put(self, data: bytes) -> None:
        imp = self.impairment
        # Two draws per item whatever happens, so the sequence of delays is the seed's alone.
        delay_s = self._rng.uniform(imp.delay_min_s, imp.delay_max_s)
        lost = self._rng.random() < imp.loss
        self._stats.chunks += 1
        self._stats.bytes += len(data)
        if lost and self._drop_lost:
            self._stats.dropped += 1
            return
        if lost:
            self._stats.retransmitted += 1
            delay_s += imp.retransmit_s
        now = asyncio.get_running_loop().time()
        self._last_due = max(self._last_due, now + delay_s)
        self._queue.put_nowait((self._last_due, data))

    def close(self) -> None:
        self._queue.put_nowait((self._last_due, None))

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            due, data = await self._queue.get()
            if data is None:
                return
            if (wait_s := due - loop.time()) > 0:
                await asyncio.sleep(wait_s)  # the link's delay itself
            await self._send(data)


@dataclass(frozen=True)
class Route:
    """A relay: listen on ``listen``, forward to ``target`` (host, port); ``name`` seeds it."""

    name: str
    listen: tuple[str, int]
    target: tuple[str, int]

    @classmethod
    def parse(cls, text: str, name: str) -> Route:
        """``HOST:PORT=HOST:PORT`` (listen = target)."""
        listen, target = (part.rsplit(":", 1) for part in text.split("=", 1))
        return cls(name, (listen[0], int(listen[1])), (target[0], int(target[1])))


@dataclass
class TcpRelay:
    """Accepts on ``route.listen``; each connection gets its own to ``route.target`` and a
    :class:`DelayLine` each way. Use :meth:`serving` (owns its connections)."""

    route: Route
    impairment: Impairment
    seed: int
    stats: LineStats = field(default_factory=LineStats)
    _connections: int = 0
    _group: asyncio.TaskGroup | None = None
    _tasks: set[asyncio.Task[None]] = field(default_factory=set)

    @contextlib.asynccontextmanager
    async def serving(self) -> AsyncIterator[TcpRelay]:
        async with asyncio.TaskGroup() as group:
            self._group = group
            server = await asyncio.start_server(self._accept, *self.route.listen)
            try:
                yield self
            finally:
                server.close()
                for task in self._tasks:
                    task.cancel()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._connections += 1
        number = self._connections
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.route.target)
        except OSError:
            writer.close()
            return
        sock = up_writer.get_extra_info("socket")
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        writer.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        assert self._group is not None
        for direction, source, sink in (("up", reader, up_writer), ("down", up_reader, writer)):
            task = self._group.create_task(
                self._pump(f"{number}:{direction}", source, sink),
                name=f"netem {self.route.name} {number} {direction}",
            )
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _pump(
        self, key: str, source: asyncio.StreamReader, sink: asyncio.StreamWriter
    ) -> None:
        async def send(data: bytes) -> None:
            sink.write(data)
            await sink.drain()

        seed = f"{self.seed}:{self.route.name}:{key}"
        line = DelayLine(self.impairment, seed, send, self.stats, drop_lost=False)
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(line.run(), name=f"netem {self.route.name} {key} line")
                while data := await source.read(65536):
                    line.put(data)
                line.close()
        except* OSError:  # either end went away (ConnectionError is one): close the other
            pass
        finally:
            sink.close()


class _UdpEnd(asyncio.DatagramProtocol):
    """One socket of a UDP relay; what it receives goes to ``received(data, address)``."""

    def __init__(self, received: Callable[[bytes, tuple[str, int]], None]) -> None:
        self.received = received
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.received(data, addr)


@dataclass
class UdpRelay:
    """Datagrams to ``route.listen`` from a client go to ``route.target`` from a socket of the
    relay's own (one per client), and the target's answers back to that client from
    ``route.listen``, each through a :class:`DelayLine` that drops what is lost. Use
    :meth:`serving` (owns its sockets and lines)."""

    route: Route
    impairment: Impairment
    seed: int
    stats: LineStats = field(default_factory=LineStats)
    _listen: _UdpEnd | None = None
    _clients: dict[tuple[str, int], DelayLine] = field(default_factory=dict)
    _ends: list[_UdpEnd] = field(default_factory=list)
    _group: asyncio.TaskGroup | None = None
    _tasks: list[asyncio.Task[None]] = field(default_factory=list)

    @contextlib.asynccontextmanager
    async def serving(self) -> AsyncIterator[UdpRelay]:
        loop = asyncio.get_running_loop()
        async with asyncio.TaskGroup() as group:
            self._group = group
            self._listen = _UdpEnd(self._from_client)
            await loop.create_datagram_endpoint(lambda: self._listen, local_addr=self.route.listen)
            try:
                yield self
            finally:
                for task in self._tasks:
                    task.cancel()
                for end in [self._listen, *self._ends]:
                    if end.transport is not None:
                        end.transport.close()

    def _from_client(self, data: bytes, client: tuple[str, int]) -> None:
        if client not in self._clients:
            self._clients[client] = self._open(client)
        self._clients[client].put(data)

    def _open(self, client: tuple[str, int]) -> DelayLine:
        """The lines and the target-side socket of a client heard for the first time."""
        assert self._group is not None and self._listen is not None
        listen, number = self._listen, len(self._clients) + 1
        upstream = _UdpEnd(lambda data, _address: answers.put(data))
        self._ends.append(upstream)

        async def to_target(data: bytes) -> None:
            if upstream.transport is None:
                loop = asyncio.get_running_loop()
                await loop.create_datagram_endpoint(lambda: upstream, remote_addr=self.route.target)
            assert upstream.transport is not None
            upstream.transport.sendto(data)

        async def to_client(data: bytes) -> None:
            assert listen.transport is not None
            listen.transport.sendto(data, client)

        key = f"{self.seed}:{self.route.name}:{number}"
        line = DelayLine(self.impairment, f"{key}:up", to_target, self.stats, drop_lost=True)
        answers = DelayLine(self.impairment, f"{key}:down", to_client, self.stats, drop_lost=True)
        for way, each in (("up", line), ("down", answers)):
            name = f"netem {self.route.name} {number} {way}"
            self._tasks.append(self._group.create_task(each.run(), name=name))
        return line


@contextlib.asynccontextmanager
async def relays(
    tcp: list[Route], udp: list[Route], impairment: Impairment, seed: int
) -> AsyncIterator[list[TcpRelay | UdpRelay]]:
    """Every route's relay, serving; stopped on exit."""
    async with contextlib.AsyncExitStack() as stack:
        serving: list[TcpRelay | UdpRelay] = []
        for route in tcp:
            serving.append(
                await stack.enter_async_context(TcpRelay(route, impairment, seed).serving())
            )
        for route in udp:
            serving.append(
                await stack.enter_async_context(UdpRelay(route, impairment, seed).serving())
            )
        yield serving


def stats_line(relay: TcpRelay | UdpRelay) -> str:
    """``netem: tcp1 LISTEN=TARGET: N chunks, N B, N retransmitted`` (UDP: ``dropped``)."""
    s, route = relay.stats, relay.route
    lost = (
        f"{s.retransmitted} retransmitted"
        if isinstance(relay, TcpRelay)
        else f"{s.dropped} dropped"
    )
    addresses = "=".join(f"{host}:{port}" for host, port in (route.listen, route.target))
    return f"netem: {route.name} {addresses}: {s.chunks} chunks, {s.bytes} B, {lost}"


async def _serve(arguments: argparse.Namespace) -> None:
    low_ms, high_ms = arguments.delay_ms
    impairment = Impairment(low_ms / 1e3, high_ms / 1e3, arguments.loss, arguments.rto_ms / 1e3)
    # Named by kind and place on the command line, not by address: free ports change from run
    # to run, the draws must not.
    tcp = [Route.parse(text, f"tcp{i}") for i, text in enumerate(arguments.tcp, start=1)]
    udp = [Route.parse(text, f"udp{i}") for i, text in enumerate(arguments.udp, start=1)]
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for number in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(number, stop.set)
    async with relays(tcp, udp, impairment, arguments.seed) as serving:
        _say(f"netem: ready ({impairment.describe()}, seed {arguments.seed})")
        await stop.wait()
    for relay in serving:
        _say(stats_line(relay))


def _say(text: str) -> None:
    """A line on stdout, at once (whoever started the relay waits for its ready line)."""
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tcp", action="append", default=[], metavar="LISTEN=TARGET")
    parser.add_argument("--udp", action="append", default=[], metavar="LISTEN=TARGET")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--delay-ms", type=float, nargs=2, default=(10.0, 30.0))
    parser.add_argument("--loss", type=float, default=0.02, help="fraction lost (0.02)")
    parser.add_argument("--rto-ms", type=float, default=200.0, help="TCP: what a loss costs")
    asyncio.run(_serve(parser.parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
