"""Helpers for the tests that fly emulated vehicles with the real MAVSDK (``mavsdk.asyncio``)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncGenerator, AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, System
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mission import MissionAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig
from tests.sitl.helpers import free_port_config

T = TypeVar("T")


@dataclass
class Drone:
    """One MAVSDK system with the plugins the tests use."""

    system: System
    sysid: int
    action: ActionAsync
    telemetry: TelemetryAsync
    offboard: OffboardAsync
    param: ParamAsync
    mission: MissionAsync

    @classmethod
    async def of(cls, system: System) -> Drone:
        return cls(
            system,
            await system.get_system_id(),
            ActionAsync(system),
            TelemetryAsync(system),
            OffboardAsync(system),
            ParamAsync(system),
            MissionAsync(system),
        )


async def first(
    stream: AsyncGenerator[T, None], predicate: Callable[[T], bool], timeout_s: float, what: str
) -> T:
    """The first item of a MAVSDK subscription that satisfies ``predicate``."""
    async with contextlib.aclosing(stream):
        try:
            async with asyncio.timeout(timeout_s):
                async for item in stream:
                    if predicate(item):
                        return item
        except TimeoutError:
            raise AssertionError(f"MAVSDK did not report {what} within {timeout_s} s") from None
    raise AssertionError(f"subscription for {what} ended")


@contextlib.asynccontextmanager
async def mavsdk_connected(
    urls: list[str], systems: int, timeout_s: float = 15.0
) -> AsyncIterator[tuple[Mavsdk, list[Drone], list[Any]]]:
    """One Mavsdk (ground station) with a connection per URL, once ``systems`` autopilots have
    been discovered. Yields the Mavsdk, the drones sorted by system id, the connection handles.
    """
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        handles = [await mavsdk.add_any_connection(url) for url in urls]
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    found = await mavsdk.get_systems()
                    with_autopilot = [s for s in found if await s.has_autopilot()]
                    if len(with_autopilot) >= systems:
                        break
                    await asyncio.sleep(0.05)
        except TimeoutError:
            raise AssertionError(
                f"MAVSDK discovered {len(with_autopilot)} of {systems} systems in {timeout_s} s"
            ) from None
        drones = sorted([await Drone.of(s) for s in with_autopilot], key=lambda d: d.sysid)
        yield mavsdk, drones, handles


def api_config(vehicles: int = 1, speed: float = 2.0, **settings: Any) -> EmulatorConfig:
    """An emulator for MAVSDK clients: API links on free ports, no GCS links, ``speed``."""
    return EmulatorConfig(
        vehicles=vehicles,
        ports=free_port_config(vehicles, gcs=False),
        clock=ClockConfig(speed=speed),
        **settings,
    )


@contextlib.asynccontextmanager
async def emulated_drones(config: EmulatorConfig) -> AsyncIterator[tuple[Emulator, list[Drone]]]:
    """The emulator of ``config`` running, and MAVSDK connected to all its vehicles."""
    async with (
        Emulator(config) as emulator,
        mavsdk_connected([ep.mavsdk_url for ep in emulator.endpoints], config.vehicles) as (
            _,
            drones,
            _,
        ),
    ):
        yield emulator, drones


@contextlib.asynccontextmanager
async def periodically(
    action: Callable[[], Awaitable[object]], rate_hz: float, name: str
) -> AsyncIterator[None]:
    """Await ``action()`` now and then every 1 / ``rate_hz`` wall seconds until the block
    ends, as MAVSDK asks of users of its manual_control and follow_me plugins (the task is
    named ``name`` and owned by a task group)."""

    async def repeat() -> None:
        while True:
            await asyncio.sleep(1.0 / rate_hz)
            await action()

    await action()  # before the block: MAVSDK refuses to start without one
    async with asyncio.TaskGroup() as group:
        task = group.create_task(repeat(), name=name)
        try:
            yield
        finally:
            task.cancel()


async def healthy(drone: Drone, timeout_s: float = 10.0) -> None:
    await first(drone.telemetry.subscribe_health_all_ok(), bool, timeout_s, "health_all_ok")


async def take_off(drone: Drone, altitude_m: float = 2.5, timeout_s: float = 15.0) -> None:
    """Arm, take off and wait until the relative altitude is within 0.2 m of ``altitude_m``."""
    await healthy(drone)
    await drone.action.arm()
    await drone.action.takeoff()
    await first(
        drone.telemetry.subscribe_position(),
        lambda p: p.relative_altitude_m > altitude_m - 0.2,
        timeout_s,
        f"altitude {altitude_m} m",
    )


async def landed_and_disarmed(drone: Drone, timeout_s: float = 30.0) -> None:
    await first(drone.telemetry.subscribe_armed(), lambda armed: not armed, timeout_s, "disarmed")
