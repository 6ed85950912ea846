"""Telemetry schedule per link and message contents."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig, PhysicsConfig, StreamRates
from sitl.telemetry import StreamScheduler, euler_to_quaternion, quaternion_to_euler
from tests.sitl.helpers import Bench, RawClient, free_port_config


def test_streams_fire_at_their_rates() -> None:
    scheduler = StreamScheduler(StreamRates())
    counts: dict[int, int] = {}
    for step in range(500):  # 10 s at 50 Hz
        for msg_id in scheduler.due(step * 0.02):
            counts[msg_id] = counts.get(msg_id, 0) + 1
    assert counts[0] == 10  # HEARTBEAT 1 Hz
    assert counts[33] == 100  # GLOBAL_POSITION_INT 10 Hz
    assert counts[245] == 50  # EXTENDED_SYS_STATE 5 Hz


def test_a_pause_does_not_cause_a_burst() -> None:
    scheduler = StreamScheduler(StreamRates())
    scheduler.due(0.0)
    assert scheduler.due(10.0).count(33) == 1
    assert 33 not in scheduler.due(10.05)
    assert 33 in scheduler.due(10.1)


def test_interval_changes() -> None:
    scheduler = StreamScheduler(StreamRates(attitude_hz=0))
    assert scheduler.period_s(30) is None
    assert scheduler.set_interval(30, 20_000, now_s=1.0)
    assert 30 in scheduler.due(1.0)
    assert not scheduler.set_interval(148, 1_000_000, now_s=1.0)  # AUTOPILOT_VERSION
    assert not scheduler.set_interval(9999, 1_000_000, now_s=1.0)
    assert scheduler.interval_us(30) == 20_000


def test_a_px4_stream_the_emulator_does_not_send_can_be_stopped_as_on_px4() -> None:
    """A companion computer stops PX4's onboard defaults it never reads (ATTITUDE_TARGET,
    SERVO_OUTPUT_RAW, ...): PX4 accepts, the emulator refused each (9 FAILED commands and log
    lines per vehicle). Starting one it cannot build stays FAILED; an id PX4 has no stream of
    (RAW_IMU) is FAILED either way, as on PX4."""
    scheduler = StreamScheduler(StreamRates())
    for msg_id in (
        mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET,
        mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
        mavlink.MAVLINK_MSG_ID_ODOMETRY,
    ):
        assert scheduler.set_interval(msg_id, -1, now_s=1.0)
        assert not scheduler.set_interval(msg_id, 20_000, now_s=1.0)
        assert msg_id not in scheduler.due(2.0)
    assert not scheduler.set_interval(mavlink.MAVLINK_MSG_ID_RAW_IMU, -1, now_s=1.0)


def test_health_bits_for_mavsdk() -> None:
    bench = Bench(ready_after_s=1.0)
    early = bench.ap.telemetry.sys_status(0.5)
    assert not early.onboard_control_sensors_health & 0x10000000
    late = bench.ap.telemetry.sys_status(1.0)
    for bit in (0x1, 0x2, 0x4, 0x20, 0x10000000):  # gyro, accel, mag, GPS, pre-arm
        assert late.onboard_control_sensors_present & bit
        assert late.onboard_control_sensors_health & bit


def test_global_position_comes_from_the_true_position_around_home() -> None:
    bench = Bench(2)
    msg = bench.autopilots[1].telemetry.global_position_int(0.0)
    lat, lon = bench.projection.to_global(0.0, 5.0)
    assert msg.lat == round(lat * 1e7) and msg.lon == round(lon * 1e7)
    assert msg.alt == 488_000 and msg.relative_alt == 0
    home = bench.autopilots[1].telemetry.home_position(0.0)
    assert (home.latitude, home.longitude) == (msg.lat, msg.lon)
    assert (home.x, home.y, home.z) == (0.0, 0.0, 0.0)  # home is the odometry origin


@pytest.mark.parametrize("angles", [(0.1, -0.2, 2.5), (0.0, 0.0, -3.0), (-0.5, 0.4, 0.0)])
def test_quaternion_roundtrip(angles: tuple[float, float, float]) -> None:
    q = euler_to_quaternion(*angles)
    assert math.fsum(v * v for v in q) == pytest.approx(1.0)
    assert quaternion_to_euler(*q) == pytest.approx(angles)


async def rate_over_udp(physics_hz: float, interval_us: float) -> tuple[int, int, float]:
    """A pymavlink client asks one vehicle for HIGHRES_IMU every ``interval_us``: the answer,
    the interval MESSAGE_INTERVAL then reports, and the messages per simulated second (by
    their timestamps, over 2 s: at 33.3/s a message more or less is 1.5 %)."""
    config = EmulatorConfig(
        vehicles=1,
        ports=free_port_config(1, gcs=False),
        clock=ClockConfig(speed=2.0),
        physics=PhysicsConfig(rate_hz=physics_hz),
    )
    msg_id = mavlink.MAVLINK_MSG_ID_HIGHRES_IMU
    async with Emulator(config) as emulator, RawClient(config.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "a heartbeat")
        result = await client.command(1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
        with client.matching(lambda m: m.get_type() == "MESSAGE_INTERVAL") as reply:
            await client.command(1, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, msg_id)
            reported = (await reply).interval_us
        client.keep_messages = True
        await emulator.run_for(3.0)
        stamps_s = [m.time_usec / 1e6 for m in client.messages if m.get_type() == "HIGHRES_IMU"]
        start_s = stamps_s[0] + 0.5  # the new rate has set in
        in_window = [t for t in stamps_s if start_s <= t < start_s + 2.0 - 1e-6]
        return result, reported, len(in_window) / 2.0


@pytest.mark.asyncio
@pytest.mark.parametrize(
    ("physics_hz", "interval_us", "reported_us", "rate_hz"),
    [
        (200.0, 5_000, 5_000, 200.0),  # PX4 SITL: 136/s
        (1000.0, 2_000, 2_000, 500.0),  # PX4 SITL: 250-265/s
        (50.0, 5_000, 20_000, 50.0),  # one per physics step at most, and said so
        (50.0, 1, 20_000, 50.0),  # PX4 SITL: MESSAGE_INTERVAL 1, and nothing at all
        (50.0, 30_000, 30_000, 33.3),
    ],
)
async def test_set_message_interval_is_kept_or_the_rate_kept_is_reported(
    physics_hz: float, interval_us: int, reported_us: int, rate_hz: float
) -> None:
    result, reported, measured_hz = await rate_over_udp(physics_hz, interval_us)
    assert result == mavlink.MAV_RESULT_ACCEPTED  # PX4 accepts every rate, kept or not
    assert reported == reported_us
    assert measured_hz == pytest.approx(rate_hz, rel=0.02)
