"""SIH's ground-truth link: HIL_STATE_QUATERNION from UDP local_base+i to remote_base+i, checked
with a pymavlink client against ``emulator.truth`` while a vehicle takes off and flies."""

from __future__ import annotations

import math
import socket
from collections.abc import Callable

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig, PortInUseError, Truth
from sitl.config import ClockConfig, GpsErrorConfig, TruthStreamConfig, WindConfig
from tests.sitl.helpers import Bench, RawClient, free_port_config, free_truth_stream

ARM, TAKEOFF, REPOSITION = 400, 22, 192
GET_MESSAGE_INTERVAL, REQUEST_MESSAGE = 510, 512
GRAVITY = 9.80665
BOOT_OFFSET_S = 5.0


def lockstep_config(**kwargs: object) -> EmulatorConfig:
    ports = free_port_config(1, gcs=False)
    truth = kwargs.pop("truth_stream", {})
    return EmulatorConfig(
        vehicles=1,
        ports=ports,
        # Capped so that the client keeps up with 25 Hz x the speed-up.
        clock=ClockConfig(mode="lockstep", lockstep_max_speed=20.0),
        truth_stream=free_truth_stream(1, ports, **truth),  # type: ignore[arg-type]
        **kwargs,  # type: ignore[arg-type]
    )


async def fly(emulator: Emulator, api: RawClient) -> None:
    """Take off to 2.5 m, then go 12 m north and 5 m east."""
    await api.expect(lambda m: m.get_type() == "HEARTBEAT", 5, "heartbeat")
    await emulator.run_for(1.2)
    assert await api.command(1, ARM, 1) == 0
    assert await api.command(1, TAKEOFF, *[math.nan] * 7) == 0
    await emulator.wait_for(
        lambda: emulator.truth.position_ned_m[0, 2] < -2.3, timeout_s=20, what="take-off"
    )
    lat, lon = emulator.projection.to_global(12.0, 5.0)
    assert await api.command(1, REPOSITION, -1, 0, 0, math.nan, lat, lon, 490.5) == 0
    await emulator.wait_for(
        lambda: emulator.truth.position_ned_m[0, 0] > 11.0, timeout_s=20, what="12 m north"
    )
    await emulator.run_for(1.0)


async def stop_and_drain(emulator: Emulator, client: RawClient) -> None:
    """Hold simulated time, then make sure every datagram the vehicle sent to ``client`` has
    arrived: a command's ACK comes from the same socket, after them."""
    emulator.clock.register("drain")
    assert await client.command(1, GET_MESSAGE_INTERVAL, 115) == 0


def body_rates(truth: Truth) -> tuple[float, float, float]:
    """Body rates (p, q, r) from the Euler angles and their rates (ZYX convention)."""
    roll, pitch = float(truth.roll_rad[0]), float(truth.pitch_rad[0])
    droll, dpitch = float(truth.roll_rate_rad_s[0]), float(truth.pitch_rate_rad_s[0])
    dyaw = float(truth.yaw_rate_rad_s[0])
    return (
        droll - dyaw * math.sin(pitch),
        dpitch * math.cos(roll) + dyaw * math.sin(roll) * math.cos(pitch),
        -dpitch * math.sin(roll) + dyaw * math.cos(roll) * math.cos(pitch),
    )


def euler_of(q: list[float]) -> tuple[float, float, float]:
    """Roll, pitch, yaw of the body-to-NED rotation of quaternion ``q`` (w, x, y, z)."""
    w, x, y, z = q
    r10, r00 = 2 * (x * y + w * z), 1 - 2 * (y * y + z * z)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return math.atan2(r21, r22), -math.asin(max(-1.0, min(1.0, r20))), math.atan2(r10, r00)


def recorder(emulator: Emulator, key: Callable[[float, Truth], object]) -> dict[object, object]:
    records: dict[object, object] = {}
    emulator.add_step_listener(lambda time_s, truth: records.update([key(time_s, truth)]))
    return records


@pytest.mark.asyncio
async def test_ground_truth_as_the_message_definition_reads() -> None:
    wind_north = 2.0
    cfg = lockstep_config(
        truth_stream={"fields": "mavlink"},
        boot_clock={"offset_s": [BOOT_OFFSET_S]},
        # The reported position is off by metres; the ground truth must not be.
        gps_error=GpsErrorConfig(bias_std_m=3.0),
        wind=WindConfig(north_m_s=wind_north),
    )

    def snapshot(time_s: float, truth: Truth) -> tuple[int, dict[str, object]]:
        stamp = int((time_s + BOOT_OFFSET_S) * 1e6)
        lat, lon, alt = truth.global_position(0)
        return stamp, {
            "lla": (lat, lon, alt),
            "velocity": truth.velocity_ned_m_s[0].copy(),
            "acceleration": truth.acceleration_ned_m_s2[0].copy(),
            "euler": (float(truth.roll_rad[0]), float(truth.pitch_rad[0])),
            "yaw": float(truth.yaw_rad[0]),
            "rates": body_rates(truth),
        }

    emulator = Emulator(cfg)
    records = recorder(emulator, snapshot)  # from the first step on
    async with (
        RawClient(cfg.ports.api_remote_port(0)) as api,
        RawClient(cfg.truth_stream.remote_base) as ground_truth,
    ):
        ground_truth.keep_messages = True
        async with emulator:
            await fly(emulator, api)
            await stop_and_drain(emulator, ground_truth)
            end_s = emulator.time_s
            assert emulator.endpoints[0].truth_local_port == cfg.truth_stream.local_base
        sender = ground_truth.vehicle_address[1]

    states = [m for m in ground_truth.messages if m.get_type() == "HIL_STATE_QUATERNION"]
    assert sender[1] == cfg.truth_stream.local_base
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in ground_truth.messages} == {(1, 1)}
    # Like every PX4 MAVLink instance, SIH's link also sends HEARTBEAT at 1 Hz.
    heartbeats = [m for m in ground_truth.messages if m.get_type() == "HEARTBEAT"]
    assert len(heartbeats) == pytest.approx(end_s, abs=1.5)
    # 25 Hz of simulated time, stamped on the vehicle's boot clock.
    stamps = np.array([m.time_usec for m in states])
    assert np.median(np.diff(stamps)) == 40_000
    assert len(states) == pytest.approx(25 * end_s, abs=3)
    moving = 0
    for msg in states:
        rec = records[msg.time_usec]
        assert isinstance(rec, dict)
        lat, lon, alt = rec["lla"]
        assert abs(msg.lat - lat * 1e7) <= 0.5 + 1e-6
        assert abs(msg.lon - lon * 1e7) <= 0.5 + 1e-6
        assert abs(msg.alt - alt * 1e3) <= 0.5 + 1e-6
        velocity = rec["velocity"]
        assert [msg.vx, msg.vy, msg.vz] == pytest.approx(velocity * 100, abs=0.5 + 1e-6)
        acceleration_mg = rec["acceleration"] / GRAVITY * 1000
        assert [msg.xacc, msg.yacc, msg.zacc] == pytest.approx(acceleration_mg, abs=0.5 + 1e-6)
        air = np.linalg.norm(velocity - [wind_north, 0.0, 0.0]) * 100
        assert msg.true_airspeed == msg.ind_airspeed == pytest.approx(air, abs=0.5 + 1e-6)
        roll, pitch, yaw = euler_of(list(msg.attitude_quaternion))
        assert (roll, pitch) == pytest.approx(rec["euler"], abs=1e-5)
        assert math.remainder(yaw - rec["yaw"], 2 * math.pi) == pytest.approx(0.0, abs=1e-5)
        assert [msg.rollspeed, msg.pitchspeed, msg.yawspeed] == pytest.approx(
            rec["rates"], abs=1e-5
        )
        moving += math.hypot(msg.vx, msg.vy) > 100
    assert moving > 10  # the comparison covered the flight, not only the ground


@pytest.mark.asyncio
async def test_ground_truth_exactly_as_px4_fills_it_at_a_configured_rate() -> None:
    cfg = lockstep_config(truth_stream={"rate_hz": 10.0})
    assert cfg.truth_stream.fields == "px4"

    def expected(time_s: float, truth: Truth) -> tuple[tuple[int, ...], None]:
        # PX4: msg.lat = gpos.lat * 1e7 etc., C conversions truncating towards zero, and the
        # m/s^2 acceleration assigned to the mG fields as it is.
        lat, lon, alt = truth.global_position(0)
        v = truth.velocity_ned_m_s[0]
        a = truth.acceleration_ned_m_s2[0]
        return (
            math.trunc(lat * 1e7),
            math.trunc(lon * 1e7),
            math.trunc(alt * 1e3),
            *(math.trunc(c * 100) for c in v),
            *(math.trunc(c) for c in a),
        ), None

    emulator = Emulator(cfg)
    records = recorder(emulator, expected)  # from the first step on
    async with (
        RawClient(cfg.ports.api_remote_port(0)) as api,
        RawClient(cfg.truth_stream.remote_base) as ground_truth,
    ):
        ground_truth.keep_messages = True
        async with emulator:
            await fly(emulator, api)
            await stop_and_drain(emulator, ground_truth)
            end_s = emulator.time_s
    states = [m for m in ground_truth.messages if m.get_type() == "HIL_STATE_QUATERNION"]
    assert len(states) == pytest.approx(10 * end_s, abs=2)
    for msg in states:
        assert msg.time_usec == 0  # PX4 never sets it
        assert (msg.ind_airspeed, msg.true_airspeed) == (0, 0)
        fields = (msg.lat, msg.lon, msg.alt, msg.vx, msg.vy, msg.vz, msg.xacc, msg.yacc, msg.zacc)
        assert fields in records, f"{fields} matches no simulated step"
    assert any(abs(msg.zacc) >= 1 for msg in states)  # a take-off's m/s^2, truncated


@pytest.mark.asyncio
async def test_a_taken_ground_truth_port_names_its_setting() -> None:
    cfg = EmulatorConfig(
        vehicles=2, ports=(ports := free_port_config(2)), truth_stream=free_truth_stream(2, ports)
    )
    busy = cfg.truth_stream.local_base + 1
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as blocker:
        blocker.bind(("0.0.0.0", busy))
        with pytest.raises(PortInUseError) as info:
            async with Emulator(cfg):
                pass
    assert (info.value.port, info.value.vehicle_index) == (busy, 1)
    assert "truth_stream.local_base" in str(info.value)


def test_ground_truth_settings() -> None:
    default = EmulatorConfig()
    assert not default.truth_stream.enabled
    assert (default.truth_stream.local_base, default.truth_stream.remote_base) == (19450, 19410)
    assert default.truth_stream.rate_hz == 25.0
    assert default.telemetry.api.hil_state_quaternion_hz == 0.0
    with pytest.raises(ValueError, match="overlaps"):
        EmulatorConfig(vehicles=3, truth_stream=TruthStreamConfig(enabled=True, remote_base=14541))
    with pytest.raises(ValueError, match="gcs_remote_port"):
        EmulatorConfig(vehicles=3, truth_stream=TruthStreamConfig(enabled=True, local_base=14548))
    # Off, its ports are not checked (or bound).
    EmulatorConfig(vehicles=3, truth_stream=TruthStreamConfig(remote_base=14541))


def test_hil_state_quaternion_can_be_requested_and_streamed_on_any_link() -> None:
    bench = Bench()
    bench.run(0.5)
    assert bench.command(REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION) == 0
    (state,) = bench.link.of_type("HIL_STATE_QUATERNION")
    assert state.alt == 488_000 and state.time_usec == 0
    assert bench.command(511, 115, 100_000) == 0  # SET_MESSAGE_INTERVAL: 10 Hz
    assert bench.link.streams.period_s(115) == pytest.approx(0.1)
