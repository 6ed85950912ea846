"""Test doubles and helpers for the emulator tests.

- :class:`FakeLink` collects what an autopilot sends (no sockets).
- :class:`Bench` steps physics + autopilots synchronously, the way the emulator's loop does,
  so state-machine tests need neither asyncio nor time.
- :class:`RawClient` is a minimal MAVLink client over real UDP (pymavlink) with
  ``expect(predicate, timeout)`` matchers instead of polling.
- :func:`free_port_config` picks port bases that are free right now for every range a test needs;
  :func:`free_truth_stream` does the same for the ground-truth link.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import random
from collections.abc import Callable, Iterator
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import Px4Autopilot, Snapshot
from sitl.config import (
    FlightLogConfig,
    PortsConfig,
    StreamRates,
    TruthStreamConfig,
    udp_port_free,
)
from sitl.geo import MapProjection
from sitl.gnss import GnssError
from sitl.modes import FlightMode
from sitl.odometry import Odometry
from sitl.physics import MulticopterPhysics
from sitl.telemetry import StreamScheduler

Message = mavlink.MAVLink_message


class FakeLink:
    """Collects messages; ``name`` and ``streams`` like a real link."""

    def __init__(self, name: str = "api", rates: StreamRates | None = None) -> None:
        self.name = name
        self.streams = StreamScheduler(rates or StreamRates())
        self.sent: list[Message] = []

    def send(self, msg: Message) -> None:
        self.sent.append(msg)

    def of_type(self, kind: str) -> list[Message]:
        return [m for m in self.sent if m.get_type() == kind]

    def clear(self) -> None:
        self.sent.clear()


def roundtrip(msg: Message, src_system: int = 255, src_component: int = 190) -> Message:
    """Encode ``msg`` as a client would and decode it again (so src ids and types are real)."""
    encoder = mavlink.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
    decoder = mavlink.MAVLink(None)
    decoded = decoder.parse_buffer(msg.pack(encoder))
    assert decoded is not None and len(decoded) == 1
    return decoded[0]


class Bench:
    """``n`` autopilots over shared physics, stepped synchronously at ``dt`` seconds."""

    def __init__(
        self,
        n: int = 1,
        *,
        params: dict[str, float] | None = None,
        ready_after_s: float = 0.0,
        dt: float = 0.02,
        odometry: dict[str, float] | None = None,
        spacing_m: float = 5.0,
        boot_offsets_s: list[float] | None = None,
        unix_time_us: Callable[[float], int] | None = None,
        gnss: GnssError | None = None,
        flight_logs: FlightLogConfig | None = None,
    ) -> None:
        start = [[0.0, spacing_m * i, 0.0] for i in range(n)]
        self.physics = MulticopterPhysics(start)
        self.odometry = Odometry(start, **(odometry or {}))
        self.gnss = gnss
        self.snapshot = Snapshot()
        self.snapshot.refresh(self.physics, self.odometry, gnss)
        self.projection = MapProjection(47.397742, 8.545594)
        self.autopilots = [
            Px4Autopilot(
                i,
                physics=self.physics,
                odometry=self.odometry,
                snapshot=self.snapshot,
                projection=self.projection,
                ground_amsl_m=488.0,
                param_overrides=params,
                preflight_ready_after_s=ready_after_s,
                unix_time_us=unix_time_us,
                boot_offset_s=boot_offsets_s[i] if boot_offsets_s else 0.0,
                flight_logs=flight_logs,
            )
            for i in range(n)
        ]
        self.links = [FakeLink() for _ in range(n)]
        for ap, link in zip(self.autopilots, self.links, strict=True):
            ap.links = [link]
        self.dt = dt
        self.t = 0.0
        self.steps = 0

    @property
    def ap(self) -> Px4Autopilot:
        return self.autopilots[0]

    @property
    def link(self) -> FakeLink:
        return self.links[0]

    def step(self, count: int = 1) -> None:
        for _ in range(count):
            for ap in self.autopilots:
                ap.update(self.t)
            self.physics.step(self.dt)
            self.odometry.step(self.dt)
            if self.gnss is not None:
                self.gnss.step(self.dt)
            self.steps += 1
            self.t = self.steps * self.dt
            self.snapshot.refresh(self.physics, self.odometry, self.gnss)

    def run(self, seconds: float) -> None:
        self.step(round(seconds / self.dt))

    def run_until(self, predicate: Callable[[], bool], max_s: float, what: str) -> float:
        """Step until ``predicate()``; returns the time it took; fails after ``max_s``."""
        start = self.t
        while not predicate():
            if self.t - start > max_s:
                raise AssertionError(f"not {what} within {max_s} s simulated")
            self.step()
        return self.t - start

    def deliver(self, msg: Message, vehicle: int = 0, src: tuple[int, int] = (255, 190)) -> None:
        self.autopilots[vehicle].handle_message(roundtrip(msg, *src), self.links[vehicle], self.t)

    def command(
        self,
        command: int,
        *params: float,
        vehicle: int = 0,
        target: int | None = None,
        target_component: int = 1,
        src: tuple[int, int] = (255, 190),
    ) -> int | None:
        """Send COMMAND_LONG; return the ACK result (None if there was no ACK)."""
        p = [*params, *([0.0] * (7 - len(params)))]
        sysid = vehicle + 1 if target is None else target
        link = self.links[vehicle]
        before = len(link.sent)
        self.deliver(
            mavlink.MAVLink_command_long_message(sysid, target_component, command, 0, *p),
            vehicle,
            src,
        )
        acks = [m for m in link.sent[before:] if m.get_type() == "COMMAND_ACK"]
        assert len(acks) <= 1
        return acks[0].result if acks else None

    def set_mode(self, main: int, sub: int = 0, vehicle: int = 0) -> int | None:
        return self.command(176, 1, main, sub, vehicle=vehicle)

    def velocity_setpoint(
        self,
        vn: float,
        ve: float,
        vd: float,
        *,
        yaw: float = 0.0,
        vehicle: int = 0,
        target: int | None = None,
    ) -> None:
        self.deliver(
            mavlink.MAVLink_set_position_target_local_ned_message(
                0,
                vehicle + 1 if target is None else target,
                1,
                1,
                2503,
                0,
                0,
                0,
                vn,
                ve,
                vd,
                0,
                0,
                0,
                yaw,
                0,
            ),
            vehicle,
        )

    def sticks(self, seconds: float, *, x: int = 0, y: int = 0, z: int = 500, r: int = 0) -> None:
        """Stream MANUAL_CONTROL to vehicle 0 (x pitch, y roll, r yaw in [-1000, 1000], z
        throttle in [0, 1000]) at 20 Hz while stepping for ``seconds`` (one message first)."""
        every = max(1, round(0.05 / self.dt))
        msg = mavlink.MAVLink_manual_control_message(1, x, y, z, r, 0)
        for k in range(round(seconds / self.dt)):
            if k % every == 0:
                self.deliver(msg)
            self.step()

    def airborne(self, vehicle: int = 0) -> None:
        """Arm, take off to MIS_TAKEOFF_ALT and wait for HOLD."""
        assert self.command(400, 1, vehicle=vehicle) == mavlink.MAV_RESULT_ACCEPTED
        assert self.command(22, *[math.nan] * 7, vehicle=vehicle) == mavlink.MAV_RESULT_ACCEPTED
        ap = self.autopilots[vehicle]
        self.run_until(lambda: ap.mode is FlightMode.HOLD and not ap.landed, 20, "airborne")

    def position(self, vehicle: int = 0) -> list[float]:
        return [float(v) for v in self.physics.position_ned_m[vehicle]]

    def texts(self, vehicle: int = 0) -> list[str]:
        return [text for _, text in self.autopilots[vehicle].status_log]


# ---------------------------------------------------------------------- network helpers
def free_port_config(n: int, *, gcs: bool = True, **overrides: Any) -> PortsConfig:
    """A PortsConfig whose every port (vehicles' and clients') is free right now."""
    return PortsConfig.free(n, gcs=gcs, **overrides)


def _free_run(n: int, rng: random.Random, avoid: set[int]) -> int:
    for _ in range(200):
        base = rng.randrange(20000, 60000 - n - 10, 10)
        run = set(range(base, base + n))
        if not run & avoid and all(udp_port_free(p) for p in run):
            return base
    raise RuntimeError("no free UDP port range found")


def free_truth_stream(n: int, ports: PortsConfig, **overrides: Any) -> TruthStreamConfig:
    """An enabled TruthStreamConfig whose ports are free right now and clear of ``ports``."""
    rng = random.Random()
    avoid = {
        *range(ports.api_remote_base, ports.api_remote_port(n - 1) + 1),
        *range(ports.resolved_api_local_base(n), ports.resolved_api_local_base(n) + n),
        *range(ports.gcs_local_base, ports.gcs_local_base + n),
        ports.gcs_remote_port,
    }
    local = _free_run(n, rng, avoid)
    remote = _free_run(n, rng, avoid | set(range(local, local + n)))
    return TruthStreamConfig(enabled=True, local_base=local, remote_base=remote, **overrides)


class _ClientProtocol(asyncio.DatagramProtocol):
    def __init__(self, client: RawClient) -> None:
        self.client = client

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.client._received(data, addr)


class RawClient:
    """A MAVLink client on UDP ``port`` (like MAVSDK's udpin), sysid 255 / compid 190.

    ``expect(predicate, timeout_s)`` waits for the next matching message (registered before
    the request is sent, so fast replies are not missed).
    """

    def __init__(self, port: int, sysid: int = 255, compid: int = 190) -> None:
        self.port = port
        self.encoder = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.transport: asyncio.DatagramTransport | None = None
        self.vehicle_address: dict[int, tuple[str, int]] = {}
        self.latest: dict[tuple[int, str], Message] = {}
        self.counts: dict[str, int] = {}
        self.messages: list[Message] = []
        self.keep_messages = False
        self._matchers: list[tuple[Callable[[Message], bool], asyncio.Future[Message]]] = []
        self._drain_markers: dict[bytes, asyncio.Future[None]] = {}

    async def __aenter__(self) -> RawClient:
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _ClientProtocol(self), local_addr=("127.0.0.1", self.port)
        )
        self.transport = transport  # type: ignore[assignment]
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        if self.transport is not None:
            self.transport.close()

    def _received(self, data: bytes, addr: tuple[str, int]) -> None:
        marker = self._drain_markers.get(data)
        if marker is not None:
            marker.set_result(None)
            return
        for msg in self.parser.parse_buffer(data) or []:
            if msg.get_msgId() < 0:
                continue
            kind = msg.get_type()
            self.vehicle_address[msg.get_srcSystem()] = addr
            self.latest[(msg.get_srcSystem(), kind)] = msg
            self.counts[kind] = self.counts.get(kind, 0) + 1
            if self.keep_messages:
                self.messages.append(msg)
            for predicate, future in list(self._matchers):
                if not future.done() and predicate(msg):
                    future.set_result(msg)

    def send(self, msg: Message, sysid: int = 1, address: tuple[str, int] | None = None) -> None:
        assert self.transport is not None
        target = address or self.vehicle_address[sysid]
        self.transport.sendto(msg.pack(self.encoder), target)
        self.encoder.seq = (self.encoder.seq + 1) % 256

    @contextlib.contextmanager
    def matching(self, predicate: Callable[[Message], bool]) -> Iterator[asyncio.Future[Message]]:
        future: asyncio.Future[Message] = asyncio.get_running_loop().create_future()
        entry = (predicate, future)
        self._matchers.append(entry)
        try:
            yield future
        finally:
            self._matchers.remove(entry)

    async def expect(
        self, predicate: Callable[[Message], bool], timeout_s: float = 5.0, what: str = ""
    ) -> Message:
        with self.matching(predicate) as future:
            try:
                return await asyncio.wait_for(future, timeout_s)
            except TimeoutError:
                raise AssertionError(
                    f"no {what or 'matching message'} within {timeout_s} s"
                ) from None

    async def drain(self, timeout_s: float = 5.0) -> None:
        """Return once every datagram that reached this client's socket so far has been read.

        The socket is read a datagram per event-loop pass, so under load a backlog can wait
        there for many passes; a datagram this client sends itself queues behind it."""
        assert self.transport is not None
        marker = f"drain {len(self._drain_markers)} {id(self)}".encode()
        arrived = asyncio.get_running_loop().create_future()
        self._drain_markers[marker] = arrived
        try:
            self.transport.sendto(marker, ("127.0.0.1", self.port))
            await asyncio.wait_for(arrived, timeout_s)
        except TimeoutError:
            raise AssertionError(f"port {self.port} not drained within {timeout_s} s") from None
        finally:
            del self._drain_markers[marker]

    async def command(
        self,
        sysid: int,
        command: int,
        *params: float,
        timeout_s: float = 5.0,
        target_component: int = 1,
        retry_s: float = 1.0,
    ) -> int:
        """COMMAND_LONG ``command`` and the result of its COMMAND_ACK. Like every MAVLink
        client (MAVSDK, QGroundControl), it sends the command again, confirmation counted up,
        while no ACK has come within ``retry_s``: a datagram may be lost (UDP on a loaded
        machine drops what a full socket buffer cannot take)."""
        p = [*params, *([0.0] * (7 - len(params)))]
        with self.matching(
            lambda m: (
                m.get_type() == "COMMAND_ACK"
                and m.command == command
                and m.get_srcSystem() == sysid
            )
        ) as ack:
            async with asyncio.timeout(timeout_s):
                for confirmation in itertools.count():
                    msg = mavlink.MAVLink_command_long_message(
                        sysid, target_component, command, min(confirmation, 255), *p
                    )
                    self.send(msg, sysid)
                    done, _ = await asyncio.wait([ack], timeout=retry_s)
                    if done:
                        break
        return ack.result().result

    def heartbeat(self, sysid: int = 1) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3), sysid)

    def velocity(self, sysid: int, vn: float, ve: float, vd: float, yaw: float = math.nan) -> None:
        mask = 2503 if math.isfinite(yaw) else 2503 | 0x400
        self.send(
            mavlink.MAVLink_set_position_target_local_ned_message(
                0,
                sysid,
                1,
                1,
                mask,
                0,
                0,
                0,
                vn,
                ve,
                vd,
                0,
                0,
                0,
                yaw if math.isfinite(yaw) else 0.0,
                0,
            ),
            sysid,
        )
