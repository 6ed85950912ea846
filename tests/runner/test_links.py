"""The MAVSDK vehicle link: finding vehicles whose autopilots come up later, arming that PX4
refuses at first, velocity setpoints on the autopilot's own clock."""

import asyncio

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mission_runner.runner.links import (
    MAX_VELOCITY_SCALE,
    UNREAD_STREAMS,
    MavsdkVehicle,
    connected_vehicles,
)
from mission_runner.runner.timesync import MissionTime
from sitl.config import ClockConfig, EmulatorConfig
from sitl.emulator import Emulator
from tests.sitl.helpers import free_port_config

pytestmark = [pytest.mark.mavsdk, pytest.mark.asyncio]


@pytest.mark.timeout(60)
async def test_a_vehicle_that_comes_up_after_its_controller_is_found():
    """A vehicle process started with PX4 (as docs/real-px4.md's block starts them) listens before
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


@pytest.mark.timeout(60)
async def test_offboard_refused_for_a_lost_setpoint_is_asked_again_with_a_fresh_one(caplog):
    """Across a lossy link the one setpoint sent before asking for OFFBOARD can be lost; PX4 (and
    the emulator) then refuses: "no setpoints". A vehicle process across a Wi-Fi link with 2 %
    loss aborted its mission so. Here the first setpoint never leaves."""
    ports = free_port_config(1, gcs=False)
    config = EmulatorConfig(vehicles=1, ports=ports, clock=ClockConfig(speed=1.0))
    async with Emulator(config) as emulator:
        url = f"udpin://0.0.0.0:{ports.api_remote_port(0)}"
        async with (
            connected_vehicles([url], [1]) as systems,
            MavsdkVehicle(systems[1], 1) as vehicle,
        ):
            await vehicle.take_off(3.0)
            send, lost = vehicle.set_velocity_ned, []

            async def lose_the_first(*velocity):
                if not lost:
                    lost.append(velocity)  # lost on the way: the autopilot never sees it
                    return
                await send(*velocity)

            vehicle.set_velocity_ned = lose_the_first
            await vehicle.start_offboard()
            assert lost and vehicle.in_offboard
            assert emulator.autopilot(0).mode.name == "OFFBOARD"
            await vehicle.finish("land")
    refusals = [r.getMessage() for r in caplog.records if "asking again" in r.getMessage()]
    assert len(refusals) == 1 and "no setpoints" in refusals[0], refusals


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("mission_rate", "expected_scale"), [(1.8, 0.9), (2.2, 1.1), (1.0, 1 / MAX_VELOCITY_SCALE)]
)
async def test_velocity_setpoints_are_scaled_to_the_autopilots_clock(
    mission_rate, expected_scale, caplog
):
    """An autopilot integrates a velocity setpoint on its own boot clock. Here it runs at 2x
    wall time (like PX4's speed factor 2, SYSTEM_TIME's UNIX time from the host) and the
    mission clock at ``mission_rate``: 1 m per mission second is mission_rate / 2 m per boot
    second. Unscaled, a SIH vehicle moved 1.4 % (1x) to 7 % (2x: the ground chose 1.82 from
    take-off, PX4 ran at 1.95) off the law's command. A mission clock half the autopilot's is
    not one mission's: bounded."""
    ports = free_port_config(1, gcs=False)
    clock = ClockConfig(speed=2.0, unix_time="host")
    config = EmulatorConfig(vehicles=1, ports=ports, clock=clock)
    async with Emulator(config) as emulator:
        url = f"udpin://0.0.0.0:{ports.api_remote_port(0)}"
        async with (
            connected_vehicles([url], [1]) as systems,
            MavsdkVehicle(systems[1], 1) as vehicle,
        ):
            mission_time = MissionTime()
            mapping = await vehicle.follow_clock(mission_time)
            await vehicle.take_off(3.0)  # seconds of SYSTEM_TIME pairs: the rate is measured
            await vehicle.start_offboard()
            assert vehicle.velocity_scale == 1.0  # before the start: holds, nothing to scale
            mission_time.set(mission_rate, 0.0)  # the ground's start
            taken, scale = emulator.autopilot(0).accepted_setpoints, vehicle.velocity_scale
            await vehicle.set_velocity_ned(1.0, -0.4, 0.2)
            while emulator.autopilot(0).accepted_setpoints == taken:
                await asyncio.sleep(0.01)
            setpoint = emulator.autopilot(0).offboard_setpoint
            assert mapping.fit.boot_rate == pytest.approx(2.0, rel=0.02)
            assert scale == pytest.approx(expected_scale, rel=0.02)
            assert scale != pytest.approx(1.0, rel=0.02)
            assert setpoint is not None and setpoint.kind == "velocity"
            assert setpoint.vector_ned == pytest.approx(
                [1.0 * scale, -0.4 * scale, 0.2 * scale],
                rel=1e-3,  # the fit refines meanwhile
            )
            await vehicle.finish("land")
    warnings = [r.getMessage() for r in caplog.records if "scaled by" in r.getMessage()]
    bounded = expected_scale == 1 / MAX_VELOCITY_SCALE
    assert len(warnings) == bounded  # said once, and only where the scale is bounded


@pytest.mark.timeout(60)
async def test_a_flying_vehicle_stops_the_streams_it_never_reads():
    """PX4 sends a companion computer's link ~480 messages a second, most of them unread; once
    the vehicle flies the mission they are stopped on that link (SET_MESSAGE_INTERVAL -1), and
    the odometry and clock streams the controller reads go on."""
    ports = free_port_config(1, gcs=False)
    config = EmulatorConfig(vehicles=1, ports=ports, clock=ClockConfig(speed=1.0))
    async with Emulator(config) as emulator:
        url = f"udpin://0.0.0.0:{ports.api_remote_port(0)}"
        async with (
            connected_vehicles([url], [1]) as systems,
            MavsdkVehicle(systems[1], 1) as vehicle,
        ):
            (api,) = [link for link in emulator.autopilot(0).links if link.name == "api"]
            streamed = [m for m in UNREAD_STREAMS if api.streams.period_s(m) is not None]
            assert mavlink.MAVLINK_MSG_ID_ATTITUDE in streamed  # PX4's 100 Hz, as emulated
            await vehicle.quiet_unread_streams()
            assert [m for m in streamed if api.streams.period_s(m) is not None] == []
            assert api.streams.period_s(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED) == 1 / 25
