"""Finding the vehicles: MAVSDK connections made before the autopilots are up."""

import asyncio

import pytest

from mission_runner.runner.links import MavsdkVehicle, connected_vehicles
from sitl.config import ClockConfig, EmulatorConfig
from sitl.emulator import Emulator
from tests.sitl.helpers import free_port_config

pytestmark = [pytest.mark.mavsdk, pytest.mark.asyncio]


@pytest.mark.timeout(60)
async def test_a_vehicle_that_comes_up_after_its_controller_is_found():
    """A vehicle process started with PX4 (as the README's block starts them) listens before
    the autopilot exists; discovery must keep looking. It died after its first 0.2 s wait."""
    ports = free_port_config(2, gcs=False)
    config = EmulatorConfig(vehicles=2, ports=ports, clock=ClockConfig(speed=1.0))
    urls = [f"udpin://0.0.0.0:{ports.api_remote_port(i)}" for i in range(2)]
    async with asyncio.TaskGroup() as group:
        looking = group.create_task(_discover(urls))
        await asyncio.sleep(1.0)  # the autopilots boot a second later than the controller
        assert not looking.done()
        async with Emulator(config):
            assert await looking == [1, 2]


async def _discover(urls):
    async with connected_vehicles(urls, [1, 2], timeout_s=30.0) as systems:
        return sorted(systems)


@pytest.mark.timeout(60)
async def test_an_arm_refused_while_checks_settle_is_asked_again(caplog):
    """PX4 refuses to arm for a few seconds after boot or a parameter change even when MAVSDK
    already reports it healthy; the vehicle asks again instead of aborting the mission."""
    ports = free_port_config(1, gcs=False)
    config = EmulatorConfig(vehicles=1, ports=ports, clock=ClockConfig(speed=1.0))
    async with Emulator(config) as emulator:
        emulator.deny_arming(0, count=2)
        url = f"udpin://0.0.0.0:{ports.api_remote_port(0)}"
        async with (
            connected_vehicles([url], [1]) as systems,
            MavsdkVehicle(systems[1], 1) as vehicle,
        ):
            await vehicle.take_off(3.0)
            assert emulator.autopilot(0).armed
    assert emulator.autopilot(0).arm_refusals_pending == 0
    refusals = [r.getMessage() for r in caplog.records if "arm refused" in r.getMessage()]
    assert len(refusals) == 1  # said once, not at every attempt
    assert "Resolve system health failures first" in refusals[0]
