"""IMU streams: HIGHRES_IMU and SCALED_IMU read what a body-fixed IMU on the kinematic vehicle
would (specific force and body rates in FRD, the earth's field, the static pressure), streamed per
link and changed by SET_MESSAGE_INTERVAL as on PX4; MAVSDK's telemetry.imu()/scaled_imu() report
the vehicle's true acceleration + gravity and rates."""

from __future__ import annotations

import asyncio
import contextlib
import math

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given
from hypothesis import strategies as st
from mavsdk.asyncio.plugins.telemetry import Imu, TelemetryError
from pymavlink.dialects.v20 import common as mavlink

from sitl import imu
from sitl.config import StreamRates, TelemetryConfig
from sitl.emulator import Truth
from tests.sitl.helpers import Bench, FakeLink
from tests.sitl.mavsdk_helpers import api_config, emulated_drones, first, healthy

G = imu.GRAVITY_M_S2
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
FAILED = mavlink.MAV_RESULT_FAILED
angles = st.floats(-math.pi, math.pi)


def body_to_ned(roll: float, pitch: float, yaw: float) -> npt.NDArray[np.float64]:
    """(3, 3) rotation R_z(yaw) R_y(pitch) R_x(roll), built independently of sitl.imu."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def expected_force_frd(
    accel_ned: npt.ArrayLike, roll: float, pitch: float, yaw: float
) -> npt.NDArray[np.float64]:
    return body_to_ned(roll, pitch, yaw).T @ (np.asarray(accel_ned) - [0.0, 0.0, G])


def expected_rates_frd(
    roll: float, pitch: float, roll_rate: float, pitch_rate: float, yaw_rate: float
) -> npt.NDArray[np.float64]:
    # Body rates from ZYX Euler rates: omega = E(roll, pitch) @ (roll', pitch', yaw').
    e = np.array(
        [
            [1, 0, -math.sin(pitch)],
            [0, math.cos(roll), math.sin(roll) * math.cos(pitch)],
            [0, -math.sin(roll), math.cos(roll) * math.cos(pitch)],
        ]
    )
    return e @ [roll_rate, pitch_rate, yaw_rate]


# ------------------------------------------------------------------ the sensor model
@given(angles, st.floats(-1.4, 1.4), angles)
def test_at_rest_the_accelerometer_reads_g_upwards_in_any_attitude(
    roll: float, pitch: float, yaw: float
) -> None:
    force = imu.specific_force_frd((0.0, 0.0, 0.0), roll, pitch, yaw)
    np.testing.assert_allclose(force, expected_force_frd([0, 0, 0], roll, pitch, yaw), atol=1e-9)
    assert math.dist(force, (0.0, 0.0, 0.0)) == pytest.approx(G)


@given(st.tuples(*[st.floats(-20, 20)] * 3), angles, st.floats(-1.4, 1.4), angles)
def test_specific_force_is_acceleration_minus_gravity_in_the_body(
    accel: tuple[float, float, float], roll: float, pitch: float, yaw: float
) -> None:
    force = imu.specific_force_frd(accel, roll, pitch, yaw)
    np.testing.assert_allclose(force, expected_force_frd(accel, roll, pitch, yaw), atol=1e-9)


def test_level_vehicle_facing_east_feels_a_northward_push_on_its_left() -> None:
    fx, fy, fz = imu.specific_force_frd((2.0, 0.0, 0.0), 0.0, 0.0, math.pi / 2)
    assert (fx, fy, fz) == pytest.approx((0.0, -2.0, -G))


@given(angles, st.floats(-1.4, 1.4), *[st.floats(-3, 3)] * 3)
def test_gyro_reads_body_rates_of_the_euler_rates(
    roll: float, pitch: float, droll: float, dpitch: float, dyaw: float
) -> None:
    rates = imu.body_rates_frd(roll, pitch, droll, dpitch, dyaw)
    np.testing.assert_allclose(
        rates, expected_rates_frd(roll, pitch, droll, dpitch, dyaw), atol=1e-9
    )


def test_magnetometer_and_barometer_read_plausible_values() -> None:
    north, east, down = imu.earth_field_ned_gauss(47.397742)
    assert north == pytest.approx(0.21, abs=0.01) and east == 0.0
    assert down == pytest.approx(0.46, abs=0.01)  # PX4 SIH there: about (0.21, 0.01, 0.44)
    assert imu.static_pressure_hpa(0.0) == pytest.approx(1013.25)
    assert imu.static_pressure_hpa(489.4) == pytest.approx(955.79, abs=0.05)  # PX4 SIH reads
    field = imu.ned_to_frd((north, east, down), 0.0, 0.0, math.pi / 2)
    assert field == pytest.approx((0.0, -north, down))  # facing east, north is on the left


# ------------------------------------------------------------------ the messages
def test_highres_and_scaled_imu_of_a_vehicle_at_rest() -> None:
    bench = Bench()
    bench.run(0.5)
    ap = bench.ap
    highres = ap.telemetry.build(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, bench.t)
    assert highres.time_usec == round(bench.t * 1e6)
    assert (highres.xacc, highres.yacc, highres.zacc) == pytest.approx((0.0, 0.0, -G))
    assert (highres.xgyro, highres.ygyro, highres.zgyro) == (0.0, 0.0, 0.0)
    assert (highres.xmag, highres.zmag) == pytest.approx((0.21, 0.46), abs=0.01)
    assert highres.abs_pressure == pytest.approx(imu.static_pressure_hpa(488.0))
    assert highres.pressure_alt == pytest.approx(488.0)
    scaled = ap.telemetry.build(mavlink.MAVLINK_MSG_ID_SCALED_IMU, bench.t)
    assert (scaled.xacc, scaled.yacc, scaled.zacc) == (0, 0, -1000)
    assert (scaled.xmag, scaled.zmag) == (round(highres.xmag * 1000), round(highres.zmag * 1000))
    assert scaled.time_boot_ms == round(bench.t * 1000) and scaled.temperature == 1500


def test_imu_follows_the_vehicle_through_a_turning_acceleration() -> None:
    bench = Bench()
    bench.run(1.0)
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
    assert bench.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == ACCEPTED
    bench.run(6.0)
    # A goto sideways: the vehicle turns to face the target while it accelerates.
    lat, lon = bench.projection.to_global(15.0, 10.0)
    bench.deliver(
        mavlink.MAVLink_command_int_message(
            1, 1, 5, 192, 0, 0, -1, 1, 0, math.nan, round(lat * 1e7), round(lon * 1e7), 491.0
        )
    )
    physics = bench.physics
    checked = 0
    for _ in range(150):
        bench.step()
        highres = bench.ap.telemetry.build(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, bench.t)
        roll, pitch, yaw = (
            float(physics.roll_rad[0]),
            float(physics.pitch_rad[0]),
            float(physics.yaw_rad[0]),
        )
        force = expected_force_frd(physics.acceleration_ned_m_s2[0], roll, pitch, yaw)
        rates = expected_rates_frd(
            roll,
            pitch,
            float(physics.roll_rate_rad_s[0]),
            float(physics.pitch_rate_rad_s[0]),
            float(physics.yaw_rate_rad_s[0]),
        )
        np.testing.assert_allclose([highres.xacc, highres.yacc, highres.zacc], force, atol=1e-9)
        np.testing.assert_allclose([highres.xgyro, highres.ygyro, highres.zgyro], rates, atol=1e-9)
        checked += abs(force[0]) > 0.1 and abs(rates[2]) > 0.01
    assert checked > 10  # the turn did accelerate and rotate the vehicle


def test_default_rates_per_link_and_set_message_interval_changes_them() -> None:
    api, gcs = TelemetryConfig().api, TelemetryConfig().gcs
    # PX4's onboard mode streams HIGHRES_IMU at 50 Hz; 10 Hz here like the other API streams
    # (a datagram in every physics step otherwise). Its normal (GCS) mode streams neither.
    assert (api.highres_imu_hz, api.scaled_imu_hz) == (10.0, 0.0)
    assert (gcs.highres_imu_hz, gcs.scaled_imu_hz) == (0.0, 0.0)
    bench = Bench()
    link = bench.link
    assert link.streams.period_s(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU) == pytest.approx(0.1)
    assert bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 26, 40_000) == ACCEPTED
    assert link.streams.period_s(mavlink.MAVLINK_MSG_ID_SCALED_IMU) == pytest.approx(0.04)
    assert bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 105, -1) == ACCEPTED
    assert link.streams.period_s(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU) is None
    # As PX4: no stream of RAW_IMU, and the heartbeat's rate is not negotiable.
    assert bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 27, 20_000) == FAILED
    assert bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 20_000) == FAILED
    gcs_link = FakeLink("gcs", StreamRates(**gcs.model_dump()))
    assert gcs_link.streams.period_s(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU) is None


# ------------------------------------------------------------------ MAVSDK
class TruthRecorder:
    """The true state after every step, by boot-clock microsecond (the IMU's timestamp)."""

    def __init__(self) -> None:
        self.by_time_us: dict[int, tuple[list[float], list[float]]] = {}

    def __call__(self, time_s: float, truth: Truth) -> None:
        attitude = [
            float(truth.roll_rad[0]),
            float(truth.pitch_rad[0]),
            float(truth.yaw_rad[0]),
            float(truth.roll_rate_rad_s[0]),
            float(truth.pitch_rate_rad_s[0]),
            float(truth.yaw_rate_rad_s[0]),
        ]
        self.by_time_us[int(time_s * 1e6)] = (truth.acceleration_ned_m_s2[0].tolist(), attitude)

    def check(self, sample: Imu) -> None:
        accel, (roll, pitch, yaw, droll, dpitch, dyaw) = self.by_time_us[sample.timestamp_us]
        force = expected_force_frd(accel, roll, pitch, yaw)
        rates = expected_rates_frd(roll, pitch, droll, dpitch, dyaw)
        a, w = sample.acceleration_frd, sample.angular_velocity_frd
        # float32 on the wire
        np.testing.assert_allclose([a.forward_m_s2, a.right_m_s2, a.down_m_s2], force, atol=1e-5)
        np.testing.assert_allclose([w.forward_rad_s, w.right_rad_s, w.down_rad_s], rates, atol=1e-6)


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_imu_matches_the_true_acceleration_through_a_take_off() -> None:
    recorder = TruthRecorder()
    async with emulated_drones(api_config(params={"MIS_TAKEOFF_ALT": 3.0})) as (emulator, drones):
        emulator.add_step_listener(recorder)
        drone = drones[0]
        await drone.telemetry.set_rate_imu(25.0)
        link = emulator._links[0][0]  # the API link's schedule, as the request left it
        assert link.streams.period_s(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU) == pytest.approx(0.04)
        await healthy(drone)
        climbing: list[Imu] = []
        resting: list[Imu] = []
        async with contextlib.aclosing(drone.telemetry.subscribe_imu()) as samples:
            async with asyncio.timeout(30):
                await drone.action.arm()
                await drone.action.takeoff()
                async for sample in samples:
                    if sample.timestamp_us not in recorder.by_time_us:
                        continue  # sent before the recorder was added
                    recorder.check(sample)
                    target = climbing if sample.acceleration_frd.down_m_s2 < -G - 0.5 else resting
                    target.append(sample)
                    if len(climbing) >= 5 and len(resting) >= 5:
                        break
        assert all(abs(s.angular_velocity_frd.down_rad_s) < 1e-6 for s in resting)
        await drone.telemetry.set_rate_scaled_imu(10.0)
        scaled = await first(drone.telemetry.subscribe_scaled_imu(), bool, 5, "SCALED_IMU")
        # Stamped in whole milliseconds; MAVSDK turns mG into m/s^2 with g = 9.81.
        (time_us,) = [t for t in recorder.by_time_us if abs(t - scaled.timestamp_us) < 1000]
        accel, (roll, pitch, yaw, *_) = recorder.by_time_us[time_us]
        force_mg = np.round(expected_force_frd(accel, roll, pitch, yaw) / G * 1000.0)
        a = scaled.acceleration_frd
        np.testing.assert_allclose(
            [a.forward_m_s2, a.right_m_s2, a.down_m_s2], force_mg * 9.81 / 1000.0, atol=1e-5
        )
        with pytest.raises(TelemetryError):
            await drone.telemetry.set_rate_raw_imu(10.0)  # PX4 has no RAW_IMU stream either
