"""Orbit mode (MAV_CMD_DO_ORBIT): the circle flown, its direction, speed and heading, and PX4's
answers; stepped synchronously, then with MAVSDK's action.do_orbit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mavsdk.asyncio.plugins.action import OrbitYawBehavior
from mavsdk.asyncio.plugins.telemetry import FlightMode as MavsdkFlightMode
from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED as ACCEPTED
from pymavlink.dialects.v20.common import MAV_RESULT_TEMPORARILY_REJECTED as TEMPORARILY_REJECTED

from sitl.modes import FlightMode
from tests.sitl.helpers import Bench
from tests.sitl.mavsdk_helpers import api_config, emulated_drones, first, take_off

DO_ORBIT = mavlink.MAV_CMD_DO_ORBIT
GROUND_AMSL_M = 488.0  # the Bench's ground
NAN = math.nan


def orbit_int(
    bench: Bench,
    radius: float,
    speed: float,
    yaw_behaviour: float,
    center_ne: tuple[float, float] | None,
    *,
    altitude_amsl: float = NAN,
) -> int | None:
    """DO_ORBIT as COMMAND_INT the way MAVSDK sends it (frame GLOBAL_RELATIVE_ALT, altitude
    AMSL all the same); None centre: INT32_MAX (not given)."""
    if center_ne is None:
        x = y = 2**31 - 1
    else:
        lat, lon = bench.projection.to_global(*center_ne)
        x, y = round(lat * 1e7), round(lon * 1e7)
    link = bench.link
    before = len(link.sent)
    bench.deliver(
        mavlink.MAVLink_command_int_message(
            1,
            1,
            mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
            DO_ORBIT,
            0,
            0,
            radius,
            speed,
            yaw_behaviour,
            NAN,
            x,
            y,
            altitude_amsl,
        )
    )
    acks = [m for m in link.sent[before:] if m.get_type() == "COMMAND_ACK"]
    return acks[0].result if acks else None


def track(bench: Bench, center_ne: tuple[float, float], seconds: float) -> dict[str, np.ndarray]:
    """Step ``seconds`` and record radius, bearing from the centre (deg), speed and the yaw
    error to the centre (deg) every step."""
    rows = []
    for _ in range(round(seconds / bench.dt)):
        bench.step()
        n, e, _ = bench.position()
        dn, de = n - center_ne[0], e - center_ne[1]
        vn, ve, _ = bench.physics.velocity_ned_m_s[0]
        yaw = math.degrees(bench.physics.yaw_rad[0])
        to_center = math.degrees(math.atan2(-de, -dn))
        rows.append(
            (
                math.hypot(dn, de),
                math.degrees(math.atan2(de, dn)),
                math.hypot(vn, ve),
                (yaw - to_center + 180.0) % 360.0 - 180.0,
            )
        )
    data = np.array(rows)
    return {
        "radius": data[:, 0],
        "bearing": np.unwrap(np.radians(data[:, 1])),
        "speed": data[:, 2],
        "yaw_error": data[:, 3],
    }


def test_orbit_flies_the_commanded_circle_clockwise_facing_the_centre() -> None:
    bench = Bench(params={"MIS_TAKEOFF_ALT": 10.0})
    bench.airborne()
    assert (
        orbit_int(bench, 10.0, 2.0, 0, (20.0, 0.0), altitude_amsl=GROUND_AMSL_M + 12.0) == ACCEPTED
    )
    assert bench.ap.mode is FlightMode.ORBIT
    heartbeat = bench.ap.telemetry.heartbeat(bench.t)
    assert (heartbeat.custom_mode >> 16 & 0xFF, heartbeat.custom_mode >> 24) == (3, 1)
    assert heartbeat.base_mode & mavlink.MAV_MODE_FLAG_AUTO_ENABLED == 0
    track(bench, (20.0, 0.0), 15.0)  # approach, then ramp up the speed
    lap_s = 2 * math.pi * 10.0 / 2.0
    lap = track(bench, (20.0, 0.0), lap_s)
    np.testing.assert_allclose(lap["radius"], 10.0, atol=0.1)
    np.testing.assert_allclose(lap["speed"], 2.0, atol=0.01)
    assert lap["bearing"][-1] - lap["bearing"][0] == pytest.approx(2 * math.pi, abs=0.05)
    np.testing.assert_allclose(lap["yaw_error"], 0.0, atol=1.0)
    assert bench.position()[2] == pytest.approx(-12.0, abs=0.05)  # the centre's altitude


def test_negative_radius_orbits_counter_clockwise_around_the_vehicle_by_default() -> None:
    bench = Bench(params={"MIS_TAKEOFF_ALT": 5.0})
    bench.airborne()
    start = bench.position()
    heading = float(bench.physics.yaw_rad[0])
    assert orbit_int(bench, -5.0, NAN, 1, None) == ACCEPTED  # hold the initial heading
    track(bench, (start[0], start[1]), 15.0)
    lap = track(bench, (start[0], start[1]), 10.0)
    np.testing.assert_allclose(lap["radius"], 5.0, atol=0.1)
    np.testing.assert_allclose(lap["speed"], 1.0, atol=0.01)  # PX4's default 1 m/s
    assert lap["bearing"][-1] < lap["bearing"][0]  # counter-clockwise
    assert float(bench.physics.yaw_rad[0]) == pytest.approx(heading, abs=0.01)
    assert bench.ap.orbit.radius_m == -5.0


def test_orbit_speed_is_limited_by_centripetal_acceleration_and_yaw_can_follow_the_tangent() -> (
    None
):
    bench = Bench(params={"MIS_TAKEOFF_ALT": 5.0})
    bench.airborne()
    start = bench.position()
    assert orbit_int(bench, 8.0, 20.0, 3, None) == ACCEPTED
    assert bench.ap.orbit.velocity_m_s == pytest.approx(4.0)  # sqrt(2 m/s^2 x 8 m)
    track(bench, (start[0], start[1]), 20.0)
    lap = track(bench, (start[0], start[1]), 5.0)
    np.testing.assert_allclose(lap["speed"], 4.0, atol=0.03)
    vn, ve, _ = bench.physics.velocity_ned_m_s[0]
    course = math.atan2(ve, vn)
    assert float(bench.physics.yaw_rad[0]) == pytest.approx(course, abs=math.radians(3.0))


def test_radius_out_of_range_is_accepted_then_refused_and_the_vehicle_holds() -> None:
    bench = Bench(params={"MIS_TAKEOFF_ALT": 5.0})
    bench.airborne()
    bench.run(1.0)
    held = bench.position()
    assert orbit_int(bench, 2000.0, 2.0, 0, None) == ACCEPTED  # PX4's commander accepts ...
    assert bench.texts()[-1] == "Orbit radius limit exceeded"  # ... its flight task refuses
    assert bench.ap.mode is FlightMode.ORBIT
    bench.run(5.0)
    np.testing.assert_allclose(bench.position(), held, atol=0.05)
    assert orbit_int(bench, 0.5, 2.0, 0, None) == ACCEPTED
    assert bench.texts()[-1] == "Orbit radius limit exceeded"
    assert orbit_int(bench, 3.0, 1.0, 0, None) == ACCEPTED  # a valid one flies again
    track(bench, (held[0], held[1]), 10.0)
    lap = track(bench, (held[0], held[1]), 5.0)
    np.testing.assert_allclose(lap["radius"], 3.0, atol=0.1)


def test_orbit_while_disarmed_switches_the_mode_and_prevents_arming() -> None:
    bench = Bench()
    assert bench.command(DO_ORBIT, 5.0, 1.0, 0, 0, NAN, NAN, NAN) == ACCEPTED
    assert bench.ap.mode is FlightMode.ORBIT
    assert bench.command(400, 1) == TEMPORARILY_REJECTED
    assert bench.texts()[-1] == "Arming denied: Resolve system health failures first"


def test_orbit_needs_a_position_estimate() -> None:
    bench = Bench()
    bench.airborne()
    bench.ap.set_sensor("gps", False, bench.t)
    bench.ap.set_sensor("flow", False, bench.t)
    assert bench.command(DO_ORBIT, 5.0, 1.0, 0, 0, NAN, NAN, NAN) == TEMPORARILY_REJECTED
    assert bench.texts()[-1] == "Orbit command rejected"


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_do_orbit_flies_the_circle() -> None:
    config = api_config(speed=5.0, params={"MIS_TAKEOFF_ALT": 10.0})
    async with emulated_drones(config) as (emulator, [drone]):
        await take_off(drone, 10.0)
        lat, lon = emulator.projection.to_global(20.0, 0.0)
        amsl = config.home.altitude_amsl_m + 10.0
        await drone.action.do_orbit(
            10.0, 2.0, OrbitYawBehavior.HOLD_FRONT_TO_CIRCLE_CENTER, lat, lon, amsl
        )
        assert emulator.autopilot(0).mode is FlightMode.ORBIT
        # MAVSDK has no orbit flight mode: it reports PX4's POSCTL sub-mode ORBIT as POSCTL.
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.POSCTL,
            5,
            "ORBIT (as POSCTL)",
        )
        await emulator.run_for(15.0)
        samples: list[tuple[float, float, float]] = []

        def record(time_s: float, truth: object) -> None:
            n, e, _ = emulator.truth.position_ned_m[0]
            vn, ve, _ = emulator.truth.velocity_ned_m_s[0]
            samples.append((math.hypot(n - 20.0, e), math.atan2(e, n - 20.0), math.hypot(vn, ve)))

        remove = emulator.add_step_listener(record)
        await emulator.run_for(2 * math.pi * 10.0 / 2.0)
        remove()
        data = np.array(samples)
        np.testing.assert_allclose(data[:, 0], 10.0, atol=0.15)
        np.testing.assert_allclose(data[:, 2], 2.0, atol=0.02)
        assert np.unwrap(data[:, 1])[-1] - data[0, 1] == pytest.approx(2 * math.pi, abs=0.1)
        heading = await drone.telemetry.heading()
        n, e, _ = emulator.truth.position_ned_m[0]
        to_center = math.degrees(math.atan2(-e, 20.0 - n)) % 360.0
        assert (heading.heading_deg - to_center + 180.0) % 360.0 - 180.0 == pytest.approx(
            0.0, abs=3.0
        )
