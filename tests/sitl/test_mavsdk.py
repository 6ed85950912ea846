"""The emulator as MAVSDK sees it: real ``mavsdk.asyncio`` over real UDP.

The clock runs 5x faster than wall time; MAVSDK's own timers are wall-clock, which these speeds
keep well inside its limits (1 s heartbeats, 20 Hz offboard resend vs COM_OF_LOSS_T = 1 s).
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from mavsdk.asyncio.plugins.mission import MissionItem, MissionPlan
from mavsdk.asyncio.plugins.offboard import VelocityNedYaw
from mavsdk.asyncio.plugins.telemetry import FlightMode as MavsdkFlightMode

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig
from sitl.modes import FlightMode
from tests.sitl.helpers import free_port_config
from tests.sitl.mavsdk_helpers import (
    first,
    healthy,
    landed_and_disarmed,
    mavsdk_connected,
    take_off,
)

pytestmark = [pytest.mark.mavsdk, pytest.mark.asyncio]

SPEED = 5.0


def config(n: int = 1, speed: float = SPEED, **kwargs: object) -> EmulatorConfig:
    return EmulatorConfig(
        vehicles=n,
        ports=free_port_config(n, gcs=False),
        clock=ClockConfig(speed=speed),
        **kwargs,  # type: ignore[arg-type]
    )


async def test_connect_health_and_parameters() -> None:
    async with (
        Emulator(config()) as emulator,
        mavsdk_connected([emulator.endpoints[0].mavsdk_url], 1) as (_, drones, _),
    ):
        drone = drones[0]
        assert drone.sysid == 1
        await healthy(drone)
        assert await drone.param.get_param_float("MIS_TAKEOFF_ALT") == pytest.approx(2.5)
        assert await drone.param.get_param_int("NAV_DLL_ACT") == 0
        await drone.param.set_param_int("COM_OBL_RC_ACT", 4)
        assert await drone.param.get_param_int("COM_OBL_RC_ACT") == 4
        await drone.action.set_takeoff_altitude(4.0)
        assert await drone.action.get_takeoff_altitude() == pytest.approx(4.0)
        assert emulator.autopilot(0).params["MIS_TAKEOFF_ALT"] == 4.0
        home = await first(drone.telemetry.subscribe_home(), lambda h: True, 5, "home")
        assert home.absolute_altitude_m == pytest.approx(488.0, abs=0.01)


async def test_arm_takeoff_offboard_velocity_and_land() -> None:
    async with (
        Emulator(config()) as emulator,
        mavsdk_connected([emulator.endpoints[0].mavsdk_url], 1) as (_, drones, _),
    ):
        drone = drones[0]
        await take_off(drone)
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.HOLD,
            5,
            "HOLD after take-off",
        )
        assert await drone.telemetry.in_air()

        await drone.offboard.set_velocity_ned(VelocityNedYaw(2.0, 1.0, 0.0, 30.0))
        await drone.offboard.start()
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.OFFBOARD,
            5,
            "OFFBOARD",
        )
        await emulator.run_for(2.0)  # reach the commanded velocity
        start, t0 = emulator.truth.position_ned_m[0].copy(), emulator.time_s
        await emulator.run_for(5.0)
        flown = emulator.truth.position_ned_m[0] - start
        elapsed = emulator.time_s - t0
        np.testing.assert_allclose(flown[:2], [2.0 * elapsed, 1.0 * elapsed], atol=0.05)
        assert math.degrees(emulator.truth.yaw_rad[0]) == pytest.approx(30.0, abs=1.0)
        velocity = await drone.telemetry.velocity_ned()
        assert velocity.north_m_s == pytest.approx(2.0, abs=0.05)

        await drone.offboard.stop()
        await drone.action.land()
        await landed_and_disarmed(drone)
        assert emulator.truth.position_ned_m[0, 2] == 0.0
        assert not await drone.telemetry.in_air()


async def test_goto_then_return_to_launch() -> None:
    cfg = config(params={"RTL_RETURN_ALT": 8.0, "RTL_DESCEND_ALT": 4.0})
    async with (
        Emulator(cfg) as emulator,
        mavsdk_connected([emulator.endpoints[0].mavsdk_url], 1) as (_, drones, _),
    ):
        drone = drones[0]
        await take_off(drone)
        lat, lon = emulator.projection.to_global(15.0, -20.0)
        await drone.action.goto_location(lat, lon, 488.0 + 6.0, float("nan"))
        await emulator.wait_for(
            lambda: math.dist(emulator.truth.position_ned_m[0], (15.0, -20.0, -6.0)) < 0.3,
            timeout_s=20,
            what="goto target",
        )
        await drone.action.return_to_launch()
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.RETURN_TO_LAUNCH,
            5,
            "RTL",
        )
        await landed_and_disarmed(drone, timeout_s=40)
        assert np.linalg.norm(emulator.truth.position_ned_m[0]) < 1.0


async def test_offboard_loss_failsafe_when_the_client_goes_away() -> None:
    async with Emulator(config()) as emulator:
        url = emulator.endpoints[0].mavsdk_url
        async with mavsdk_connected([url], 1) as (mavsdk, drones, handles):
            drone = drones[0]
            await drone.param.set_param_int("COM_OBL_RC_ACT", 4)  # land on offboard loss
            await take_off(drone)
            await drone.offboard.set_velocity_ned(VelocityNedYaw(1.0, 0.0, 0.0, 0.0))
            await drone.offboard.start()
            await emulator.wait_for(
                lambda: emulator.vehicle_status(0).mode is FlightMode.OFFBOARD,
                timeout_s=5,
                what="offboard",
            )
            await emulator.run_for(2.0)
            assert emulator.vehicle_status(0).mode is FlightMode.OFFBOARD
            lost_from = emulator.time_s
            await mavsdk.remove_connection(handles[0])  # the setpoints stop
            await emulator.wait_for(
                lambda: emulator.vehicle_status(0).mode is FlightMode.LAND,
                timeout_s=5,
                what="offboard-loss failsafe",
            )
            assert emulator.time_s - lost_from < 1.0 + 0.5
            status = emulator.vehicle_status(0)
            assert status.failsafe
            assert "Failsafe activated: offboard control lost" in status.status_texts
            await emulator.wait_for(
                lambda: not emulator.vehicle_status(0).armed,
                timeout_s=20,
                what="landed and disarmed",
            )


async def test_mission_upload_download_and_flight() -> None:
    async with (
        Emulator(config()) as emulator,
        mavsdk_connected([emulator.endpoints[0].mavsdk_url], 1) as (_, drones, _),
    ):
        drone = drones[0]
        waypoints = [(10.0, 0.0, 5.0), (10.0, 10.0, 6.0), (0.0, 10.0, 5.0)]
        items = []
        for north, east, altitude in waypoints:
            lat, lon = emulator.projection.to_global(north, east)
            items.append(
                MissionItem(
                    latitude_deg=lat,
                    longitude_deg=lon,
                    relative_altitude_m=altitude,
                    speed_m_s=4.0,
                    is_fly_through=False,
                    acceptance_radius_m=0.5,
                    vehicle_action=MissionItem.VehicleAction.NONE,
                )
            )
        await drone.mission.set_return_to_launch_after_mission(False)
        await drone.mission.upload_mission(MissionPlan(items))
        downloaded = await drone.mission.download_mission()
        assert len(downloaded.mission_items) == 3
        assert downloaded.mission_items[1].relative_altitude_m == pytest.approx(6.0)
        await healthy(drone)
        await drone.action.arm()
        await drone.mission.start_mission()
        progress = await first(
            drone.mission.subscribe_mission_progress(),
            lambda p: p.current == p.total == 3,
            40,
            "mission progress 3/3",
        )
        assert progress.total == 3
        assert await drone.mission.is_mission_finished()
        np.testing.assert_allclose(emulator.truth.position_ned_m[0], (0.0, 10.0, -5.0), atol=0.6)
        reached = [t for t in emulator.vehicle_status(0).status_texts if "Mission" in t]
        assert reached == ["Mission finished, loitering"]


async def test_ten_vehicles_from_one_mavsdk() -> None:
    n = 10
    async with Emulator(config(n, speed=3.0)) as emulator:
        urls = [ep.mavsdk_url for ep in emulator.endpoints]
        async with mavsdk_connected(urls, n, timeout_s=20) as (_, drones, _):
            assert [d.sysid for d in drones] == list(range(1, n + 1))
            async with asyncio.TaskGroup() as tg:
                for drone in drones:
                    tg.create_task(take_off(drone, timeout_s=30), name=f"takeoff-{drone.sysid}")
            assert all(emulator.truth.position_ned_m[:, 2] < -2.2)
            async with asyncio.TaskGroup() as tg:
                for drone in drones:
                    tg.create_task(drone.action.land(), name=f"land-{drone.sysid}")
            async with asyncio.TaskGroup() as tg:
                for drone in drones:
                    tg.create_task(landed_and_disarmed(drone, 40), name=f"disarm-{drone.sysid}")
            assert not any(emulator.truth.armed)
        assert emulator.stats().handler_errors == 0


async def test_px4_compat_ports_share_one_client_port_and_filter_by_system_id() -> None:
    n = 12  # vehicles 9, 10 and 11 all send to the same client port, as PX4 SITL does
    cfg = EmulatorConfig(
        vehicles=n,
        ports=free_port_config(n, gcs=False, px4_compat_ports=True),
        clock=ClockConfig(speed=2.0),
    )
    async with Emulator(cfg) as emulator:
        urls = sorted({ep.mavsdk_url for ep in emulator.endpoints})
        assert len(urls) == 10
        async with mavsdk_connected(urls, n, timeout_s=20) as (_, drones, _):
            drone_11 = next(d for d in drones if d.sysid == 11)
            await healthy(drone_11)
            await drone_11.action.arm()
            await emulator.wait_for(
                lambda: bool(emulator.truth.armed[10]), timeout_s=5, what="vehicle 11 armed"
            )
            assert list(np.flatnonzero(emulator.truth.armed)) == [10]
