"""Follow-me (AUTO_FOLLOW_TARGET, FOLLOW_TARGET, FLW_TGT_*): the follower's offset from a still
and a moving target, the height modes and losing the target; stepped synchronously, then with
MAVSDK's follow_me plugin."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable

import numpy as np
import pytest
from mavsdk.asyncio.plugins.follow_me import Config, FollowMeAsync, TargetLocation
from mavsdk.asyncio.plugins.telemetry import FlightMode as MavsdkFlightMode
from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED as ACCEPTED
from pymavlink.dialects.v20.common import MAV_RESULT_TEMPORARILY_REJECTED as TEMPORARILY_REJECTED

from sitl.modes import FlightMode
from tests.sitl.helpers import Bench
from tests.sitl.mavsdk_helpers import api_config, emulated_drones, first, periodically, take_off

AUTO, FOLLOW_TARGET = 4, 8
GROUND_AMSL_M = 488.0  # the Bench's ground
FOLLOW = {"MIS_TAKEOFF_ALT": 5.0, "FLW_TGT_HT": 10.0, "FLW_TGT_DST": 6.0, "FLW_TGT_RS": 0.2}


def follow(
    bench: Bench,
    target: Callable[[float], tuple[float, float, float, float, float]],
    seconds: float,
    rate_hz: float = 2.0,
) -> None:
    """Step ``seconds`` while a phone reports ``target(t)`` = (north, east, altitude AMSL,
    v_north, v_east) with FOLLOW_TARGET at ``rate_hz``."""
    every = round(1.0 / (rate_hz * bench.dt))
    for k in range(round(seconds / bench.dt)):
        if k % every == 0:
            north, east, alt, vn, ve = target(bench.t)
            lat, lon = bench.projection.to_global(north, east)
            bench.deliver(
                mavlink.MAVLink_follow_target_message(
                    round(bench.t * 1000),
                    0,
                    round(lat * 1e7),
                    round(lon * 1e7),
                    alt,
                    [vn, ve, 0.0],
                    [0.0, 0.0, 0.0],
                    [1.0, 0.0, 0.0, 0.0],
                    [0.0, 0.0, 0.0],
                    [0.0, 0.0, 0.0],
                    0,
                )
            )
        bench.step()


def following(params: dict[str, float] | None = None) -> Bench:
    bench = Bench(params={**FOLLOW, **(params or {})})
    bench.airborne()
    assert bench.set_mode(AUTO, FOLLOW_TARGET) == ACCEPTED
    assert bench.ap.mode is FlightMode.FOLLOW_TARGET
    return bench


def offset_from(bench: Bench, north: float, east: float) -> tuple[float, float]:
    """(distance m, bearing deg) of the vehicle seen from (north, east)."""
    n, e, _ = bench.position()
    return math.hypot(n - north, e - east), math.degrees(math.atan2(e - east, n - north))


def test_follower_stays_behind_a_still_target_at_the_set_distance_and_height() -> None:
    bench = following()
    follow(bench, lambda t: (20.0, 0.0, GROUND_AMSL_M, 0.0, 0.0), 25.0)
    # Course unknown (not moving): PX4 takes 0 (north), so 180 deg puts the vehicle south.
    np.testing.assert_allclose(bench.position(), [14.0, 0.0, -10.0], atol=0.05)
    assert math.degrees(bench.physics.yaw_rad[0]) == pytest.approx(0.0, abs=1.0)  # at target
    heartbeat = bench.ap.telemetry.heartbeat(bench.t)
    assert (heartbeat.custom_mode >> 16 & 0xFF, heartbeat.custom_mode >> 24) == (4, 8)


def test_follower_swings_behind_a_moving_target_and_keeps_pace() -> None:
    bench = following()
    speed = 2.0
    follow(bench, lambda t: (20.0, 0.0, GROUND_AMSL_M, 0.0, 0.0), 20.0)
    start = bench.t

    def east_bound(t: float) -> tuple[float, float, float, float, float]:
        return 20.0, speed * (t - start), GROUND_AMSL_M, 0.0, speed

    follow(bench, east_bound, 30.0)
    distance, bearing = offset_from(bench, 20.0, speed * (bench.t - start))
    assert distance == pytest.approx(6.0, abs=0.15)
    assert bearing == pytest.approx(-90.0, abs=2.0)  # behind: west of an eastbound target
    np.testing.assert_allclose(bench.physics.velocity_ned_m_s[0], [0.0, speed, 0.0], atol=0.02)
    assert math.degrees(bench.physics.yaw_rad[0]) == pytest.approx(90.0, abs=2.0)


def test_follow_angle_puts_the_vehicle_on_the_targets_right() -> None:
    bench = following({"FLW_TGT_FA": 90.0})
    start = bench.t

    def north_bound(t: float) -> tuple[float, float, float, float, float]:
        return 20.0 + 1.5 * (t - start), 0.0, GROUND_AMSL_M, 1.5, 0.0

    follow(bench, north_bound, 40.0)
    distance, bearing = offset_from(bench, 20.0 + 1.5 * (bench.t - start), 0.0)
    assert distance == pytest.approx(6.0, abs=0.15)
    assert bearing == pytest.approx(90.0, abs=2.0)  # east: right of a northbound target


def test_height_above_the_target_and_a_lost_target() -> None:
    bench = following({"FLW_TGT_ALT_M": 2})
    follow(bench, lambda t: (10.0, 10.0, GROUND_AMSL_M + 5.0, 0.0, 0.0), 25.0)
    assert bench.position()[2] == pytest.approx(-15.0, abs=0.05)  # 10 m above a target at 5 m
    still = bench.position()
    bench.run(10.0)  # no more messages: the estimate stays where the target was last seen
    np.testing.assert_allclose(bench.position(), still, atol=0.05)
    assert bench.ap.follow_target.estimator.stale(bench.t)


def test_without_a_target_the_vehicle_holds() -> None:
    bench = following()
    held = bench.position()
    bench.run(5.0)
    np.testing.assert_allclose(bench.position(), held, atol=0.05)


def test_follow_target_mode_is_accepted_on_the_ground_but_prevents_arming() -> None:
    bench = Bench()
    assert bench.set_mode(AUTO, FOLLOW_TARGET) == ACCEPTED
    assert bench.command(400, 1) == TEMPORARILY_REJECTED
    assert bench.texts()[-1] == "Arming denied: Resolve system health failures first"


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_follow_me_follows_a_moving_target() -> None:
    config = api_config(speed=5.0, params={"MIS_TAKEOFF_ALT": 5.0})
    async with emulated_drones(config) as (emulator, [drone]):
        follow_me = FollowMeAsync(drone.system)
        await follow_me.set_config(
            Config(
                follow_height_m=10.0,
                follow_distance_m=6.0,
                responsiveness=0.2,
                altitude_mode=Config.FollowAltitudeMode.CONSTANT,
                max_tangential_vel_m_s=5.0,
                follow_angle_deg=180.0,
            )
        )
        params = emulator.autopilot(0).params
        assert (params["FLW_TGT_HT"], params["FLW_TGT_DST"], params["FLW_TGT_FA"]) == (
            10.0,
            6.0,
            180.0,
        )
        assert params["FLW_TGT_RS"] == pytest.approx(0.2)
        await take_off(drone, 5.0)
        await follow_me.start()
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.FOLLOW_ME,
            5,
            "FOLLOW_ME",
        )
        while not await follow_me.is_active():  # MAVSDK: active once it sees the mode
            await asyncio.sleep(0.05)
        speed = 2.0
        moving_since: list[float] = []

        def target_north_east() -> tuple[float, float]:
            t = emulator.time_s
            east = speed * (t - moving_since[0]) if moving_since else 0.0
            return 20.0, east

        def location() -> TargetLocation:
            north, east = target_north_east()
            lat, lon = emulator.projection.to_global(north, east)
            return TargetLocation(
                lat, lon, config.home.altitude_amsl_m, 0.0, speed if moving_since else 0.0, 0.0
            )

        def report() -> Awaitable[None]:  # a phone's position, 10 Hz wall
            return follow_me.set_target_location(location())

        async with periodically(report, 10.0, "follow-me-target"):
            await emulator.run_for(25.0)
            n, e, d = emulator.truth.position_ned_m[0]
            assert math.hypot(n - 14.0, e) < 0.15
            assert d == pytest.approx(-10.0, abs=0.05)
            moving_since.append(emulator.time_s)
            await emulator.run_for(30.0)
            north, east = target_north_east()
            n, e, _ = emulator.truth.position_ned_m[0]
            assert math.hypot(n - north, e - east) == pytest.approx(6.0, abs=0.25)
            assert math.degrees(math.atan2(e - east, n - north)) == pytest.approx(-90.0, abs=3.0)
            np.testing.assert_allclose(emulator.truth.velocity_ned_m_s[0, :2], [0, speed], atol=0.1)
        await follow_me.stop()
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.HOLD,
            5,
            "HOLD after follow_me.stop()",
        )


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_follow_me_never_lands_on_a_target_below_the_ground() -> None:
    """MAVSDK-Python's follow_me example: 3D tracking (FLW_TGT_ALT_M 2), 8 m above a target it
    reports at 480 m AMSL, 8 m below home. PX4 SITL (SIH) stops and climbs whenever it is less
    than 1 m above the ground, so it hovers ~1 m up, armed and following (measured 0.8-1.2 m)."""
    config = api_config(speed=5.0)
    async with emulated_drones(config) as (emulator, [drone]):
        follow_me = FollowMeAsync(drone.system)
        await follow_me.set_config(
            Config(8.0, 2.0, 0.02, Config.FollowAltitudeMode.TARGET_GPS, 10.0, 0.0)
        )
        await take_off(drone)
        await follow_me.start()
        while not await follow_me.is_active():  # MAVSDK: active once it sees the mode
            await asyncio.sleep(0.05)
        target_amsl_m = config.home.altitude_amsl_m - 8.0
        lowest_m = [math.inf]

        def watch(_time_s: float, truth: object) -> None:
            lowest_m[0] = min(lowest_m[0], -float(emulator.truth.position_ned_m[0, 2]))

        def report() -> Awaitable[None]:  # a target walking east at 1 m/s
            lat, lon = emulator.projection.to_global(10.0, emulator.time_s)
            return follow_me.set_target_location(TargetLocation(lat, lon, target_amsl_m, 0, 1, 0))

        remove = emulator.add_step_listener(watch)
        async with periodically(report, 10.0, "follow-me-target"):
            await emulator.run_for(30.0)
        remove()
        status = emulator.vehicle_status(0)
        assert emulator.truth.armed[0] and emulator.autopilot(0).mode is FlightMode.FOLLOW_TARGET
        assert lowest_m[0] > 0.7, status
        assert -emulator.truth.position_ned_m[0, 2] == pytest.approx(1.0, abs=0.1)
