"""Stick modes driven by MANUAL_CONTROL: acceptance, the stick-to-motion mapping PX4 uses, and
the manual-control-loss failsafe; stepped synchronously, then flown with MAVSDK's
manual_control plugin.

Expected values are PX4's: MPC_VEL_MANUAL 10 m/s at full stick in Position mode,
MPC_Z_VEL_MAX_UP/DN 3 / 1.5 m/s, MPC_MAN_Y_MAX 150 deg/s, deadzone 0.1 and expo 0.6 on the
sticks; tilt MPC_MAN_TILT_MAX 35 deg at full stick in Altitude mode (no expo).
"""

from __future__ import annotations

import math
from collections.abc import Awaitable

import numpy as np
import pytest
from mavsdk.asyncio.plugins.manual_control import ManualControlAsync
from mavsdk.asyncio.plugins.telemetry import FlightMode as MavsdkFlightMode
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED as ACCEPTED
from pymavlink.dialects.v20.common import MAV_RESULT_TEMPORARILY_REJECTED as TEMPORARILY_REJECTED

from sitl.manual_control import deadzone, expo
from sitl.modes import FlightMode
from tests.sitl.helpers import Bench
from tests.sitl.mavsdk_helpers import api_config, emulated_drones, first, periodically, take_off

POSCTL, ALTCTL, STABILIZED = 3, 2, 7


def stick(value: float) -> float:
    """What PX4 makes of a stick at ``value`` (deadzone 0.1, expo 0.6)."""
    return expo(deadzone(value, 0.1), 0.6)


def flying_in(mode: int) -> Bench:
    bench = Bench()
    bench.airborne()
    bench.sticks(0.5)
    assert bench.set_mode(mode) == ACCEPTED
    return bench


def test_stick_modes_need_manual_control_input() -> None:
    bench = Bench()
    for mode, name in ((POSCTL, "Position"), (ALTCTL, "Altitude"), (STABILIZED, "Stabilized")):
        assert bench.set_mode(mode) == TEMPORARILY_REJECTED
        assert bench.texts()[-1] == f"Switching to {name} is currently not available"
    bench.sticks(0.1)
    assert bench.set_mode(POSCTL) == ACCEPTED
    assert bench.ap.mode is FlightMode.POSCTL
    bench.run(1.0)  # the input stopped: COM_RC_LOSS_T = 0.5 s
    assert bench.set_mode(4, 3) == ACCEPTED  # HOLD
    assert bench.set_mode(POSCTL) == TEMPORARILY_REJECTED


def test_arming_in_stick_modes_checks_the_throttle_like_px4() -> None:
    bench = Bench()
    bench.sticks(0.1, z=800)
    assert bench.set_mode(POSCTL) == ACCEPTED
    assert bench.command(400, 1) == TEMPORARILY_REJECTED
    assert bench.texts()[-1] == "Arming denied: throttle above center"
    bench.sticks(0.1, z=500)
    assert bench.set_mode(STABILIZED) == ACCEPTED
    assert bench.command(400, 1) == TEMPORARILY_REJECTED
    assert bench.texts()[-1] == "Arming denied: high throttle"
    bench.sticks(0.1, z=0)
    assert bench.command(400, 1) == ACCEPTED


def test_position_mode_pitch_stick_flies_at_mpc_vel_manual_times_the_stick() -> None:
    bench = flying_in(POSCTL)
    yaw = float(bench.physics.yaw_rad[0])
    for x in (1000, 500):
        bench.sticks(15.0, x=x)  # the time constant is 10 / (2 x 3) = 1.7 s
        velocity = bench.physics.velocity_ned_m_s[0]
        expected = 10.0 * stick(x / 1000)
        np.testing.assert_allclose(
            velocity, [expected * math.cos(yaw), expected * math.sin(yaw), 0.0], atol=0.02
        )
    held = bench.position()
    bench.sticks(8.0)  # centred: brake, then hold the position
    np.testing.assert_allclose(bench.physics.velocity_ned_m_s[0], 0.0, atol=0.01)
    stopped = bench.position()
    bench.sticks(5.0)
    np.testing.assert_allclose(bench.position(), stopped, atol=0.01)
    assert math.dist(held, stopped) < 10.0


def test_position_mode_roll_throttle_and_yaw_sticks() -> None:
    bench = flying_in(POSCTL)
    yaw = float(bench.physics.yaw_rad[0])
    bench.sticks(15.0, y=-500)  # left
    expected = 10.0 * stick(-0.5)
    np.testing.assert_allclose(
        bench.physics.velocity_ned_m_s[0, :2],
        [-expected * math.sin(yaw), expected * math.cos(yaw)],
        atol=0.02,
    )
    bench.sticks(8.0)
    bench.sticks(3.0, z=1000)
    assert bench.physics.velocity_ned_m_s[0, 2] == pytest.approx(-3.0, abs=0.01)
    bench.sticks(3.0, z=0)
    assert bench.physics.velocity_ned_m_s[0, 2] == pytest.approx(1.5, abs=0.01)
    bench.sticks(3.0, z=750)
    assert bench.physics.velocity_ned_m_s[0, 2] == pytest.approx(-3.0 * stick(0.5), abs=0.01)
    bench.sticks(3.0, r=500)
    assert math.degrees(bench.physics.yaw_rate_rad_s[0]) == pytest.approx(
        150.0 * stick(0.5), abs=0.1
    )
    bench.sticks(1.0)
    heading = float(bench.physics.yaw_rad[0])
    bench.sticks(2.0)
    assert float(bench.physics.yaw_rad[0]) == pytest.approx(heading, abs=1e-6)


def test_altitude_mode_tilts_and_drifts_without_a_position_hold() -> None:
    bench = flying_in(ALTCTL)
    yaw = float(bench.physics.yaw_rad[0])
    bench.sticks(10.0, x=500)
    # Tilt 0.5 x 35 deg: g tan(35 deg) / 2 = 3.43 m/s^2 against a drag of 1/s.
    speed = 0.5 * 9.80665 * math.tan(math.radians(35.0))
    np.testing.assert_allclose(
        bench.physics.velocity_ned_m_s[0, :2],
        [speed * math.cos(yaw), speed * math.sin(yaw)],
        atol=0.01,
    )
    bench.sticks(1.0)  # released: the speed decays with the drag, nothing brakes
    lag_s = 0.15  # the kinematic model's velocity time constant
    assert float(np.hypot(*bench.physics.velocity_ned_m_s[0, :2])) == pytest.approx(
        speed * math.exp(-(1.0 - lag_s)), rel=0.03
    )


def test_manual_control_loss_holds_then_returns_after_com_fail_act_t() -> None:
    bench = flying_in(POSCTL)
    bench.sticks(1.0, x=300)
    lost_at = bench.t
    bench.run_until(lambda: bench.ap.mode is FlightMode.HOLD, 2.0, "hold")
    assert bench.t - lost_at == pytest.approx(0.5, abs=0.05)  # COM_RC_LOSS_T
    assert bench.texts()[-1] == "Failsafe activated: entering Hold for 5 seconds"
    assert bench.ap.failsafe_active
    bench.run_until(lambda: bench.ap.mode is FlightMode.RTL, 6.0, "return")
    assert bench.t - lost_at == pytest.approx(5.5, abs=0.05)  # + COM_FAIL_ACT_T
    assert "Failsafe activated" in bench.texts()


def test_manual_control_loss_action_and_exceptions_follow_the_params() -> None:
    bench = Bench(params={"NAV_RCL_ACT": 3, "COM_FAIL_ACT_T": 0.0})
    bench.airborne()
    bench.sticks(0.5)
    assert bench.set_mode(POSCTL) == ACCEPTED
    bench.run(0.6)
    assert bench.ap.mode is FlightMode.LAND  # no hold first with COM_FAIL_ACT_T = 0

    bench = Bench(params={"COM_RCL_EXCEPT": 2})  # bit 1: auto modes
    bench.airborne()
    bench.sticks(0.5)
    bench.run(2.0)
    assert bench.ap.mode is FlightMode.HOLD
    assert not bench.ap.failsafe_active


def test_no_failsafe_when_manual_control_was_missing_at_arming() -> None:
    bench = Bench()
    bench.airborne()
    bench.run(3.0)
    assert not bench.ap.failsafe_active
    assert "Failsafe activated" not in " ".join(bench.texts())


def test_a_user_mode_switch_cancels_the_delayed_action() -> None:
    bench = flying_in(POSCTL)
    bench.run(1.0)
    assert bench.ap.mode is FlightMode.HOLD
    bench.sticks(0.5)  # regained
    assert bench.set_mode(POSCTL) == ACCEPTED
    bench.sticks(8.0)
    assert bench.ap.mode is FlightMode.POSCTL


def test_sticks_take_off_from_the_ground_only_above_the_takeoff_throttle() -> None:
    bench = Bench()
    bench.sticks(0.1)
    assert bench.set_mode(POSCTL) == ACCEPTED
    assert bench.command(400, 1) == ACCEPTED
    bench.sticks(2.0, z=600, x=1000)
    assert bench.position() == [0.0, 0.0, 0.0]
    bench.sticks(2.0, z=1000)
    assert bench.position()[2] < -3.0
    assert not bench.ap.landed


# --------------------------------------------------------------------------- MAVSDK
SPEED = 2.0


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_manual_control_flies_position_and_altitude_modes() -> None:
    # MAVSDK's users send the sticks on wall time; PX4 SITL's rcS scales COM_RC_LOSS_T with
    # the speed factor for the same reason.
    config = api_config(speed=SPEED, params={"COM_RC_LOSS_T": 1.0 * SPEED})
    async with emulated_drones(config) as (emulator, [drone]):
        manual = ManualControlAsync(drone.system)
        await take_off(drone)
        sticks = [0.0, 0.0, 0.5, 0.0]  # x pitch, y roll, z throttle (0.5 centred), r yaw

        def send_sticks() -> Awaitable[None]:
            return manual.set_manual_control_input(*sticks)

        async with periodically(send_sticks, 20.0, "manual-control-input"):
            await manual.start_position_control()
            await first(
                drone.telemetry.subscribe_flight_mode(),
                lambda m: m == MavsdkFlightMode.POSCTL,
                5,
                "POSCTL",
            )
            yaw = float(emulator.truth.yaw_rad[0])
            sticks[0] = 0.5
            await emulator.run_for(15.0)
            expected = 10.0 * stick(0.5)
            np.testing.assert_allclose(
                emulator.truth.velocity_ned_m_s[0],
                [expected * math.cos(yaw), expected * math.sin(yaw), 0.0],
                atol=0.03,
            )
            velocity = await drone.telemetry.velocity_ned()
            assert math.hypot(velocity.north_m_s, velocity.east_m_s) == pytest.approx(
                expected, abs=0.05
            )
            sticks[0], sticks[2] = 0.0, 1.0
            await emulator.run_for(3.0)
            assert emulator.truth.velocity_ned_m_s[0, 2] == pytest.approx(-3.0, abs=0.02)

            sticks[2] = 0.5
            await manual.start_altitude_control()
            await first(
                drone.telemetry.subscribe_flight_mode(),
                lambda m: m == MavsdkFlightMode.ALTCTL,
                5,
                "ALTCTL",
            )
            await emulator.run_for(5.0)  # centred throttle: brake, then hold the altitude
            assert emulator.truth.velocity_ned_m_s[0, 2] == pytest.approx(0.0, abs=0.02)
        # The input stops: hold for COM_FAIL_ACT_T, then return (NAV_RCL_ACT 2).
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.HOLD,
            5,
            "HOLD after manual control loss",
        )
        await first(
            drone.telemetry.subscribe_flight_mode(),
            lambda m: m == MavsdkFlightMode.RETURN_TO_LAUNCH,
            10,
            "RETURN after COM_FAIL_ACT_T",
        )
        texts = emulator.vehicle_status(0).status_texts
        assert "Failsafe activated: entering Hold for 5 seconds" in texts
