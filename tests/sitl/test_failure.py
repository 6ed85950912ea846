"""PX4's failure injection (SYS_FAILURE_EN, MAV_CMD_INJECT_FAILURE) and the emulator's fault API
that injects the same failures: what each is answered and what it does; stepped synchronously,
over UDP with pymavlink, and with MAVSDK's failure plugin."""

from __future__ import annotations

import math

import pytest
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureError, FailureType, FailureUnit
from mavsdk.asyncio.plugins.failure import FailureResult as MavsdkFailureResult
from mavsdk.asyncio.plugins.telemetry import FixType
from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED as ACCEPTED
from pymavlink.dialects.v20.common import MAV_RESULT_DENIED as DENIED
from pymavlink.dialects.v20.common import MAV_RESULT_UNSUPPORTED as UNSUPPORTED

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig
from sitl.modes import FlightMode
from tests.sitl.helpers import Bench, RawClient, free_port_config
from tests.sitl.mavsdk_helpers import api_config, emulated_drones, first, healthy, take_off

INJECT = mavlink.MAV_CMD_INJECT_FAILURE
U = mavlink  # FAILURE_UNIT_* / FAILURE_TYPE_* live in the dialect module
GPS_BIT, FLOW_BIT = 0x20, 0x40


def inject(bench: Bench, unit: int, failure_type: int, instance: int = 0) -> int | None:
    return bench.command(INJECT, unit, failure_type, instance)


def test_failure_injection_is_denied_without_sys_failure_en_and_says_nothing() -> None:
    bench = Bench(params={"SYS_FAILURE_EN": 0})
    assert inject(bench, U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_OFF) == DENIED
    assert bench.texts() == []
    assert bench.ap.gps_ok


def test_gps_and_optical_flow_off_then_ok() -> None:
    bench = Bench()
    assert inject(bench, U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_OFF) == ACCEPTED
    now = bench.t
    telemetry = bench.ap.telemetry
    assert telemetry.global_position_int(now) is None
    assert telemetry.gps_raw_int(now).fix_type == 0
    assert not telemetry.sys_status(now).onboard_control_sensors_health & GPS_BIT
    assert inject(bench, U.FAILURE_UNIT_SENSOR_OPTICAL_FLOW, U.FAILURE_TYPE_OFF) == ACCEPTED
    assert telemetry.local_position_ned(now) is None
    assert inject(bench, U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_OK) == ACCEPTED
    assert inject(bench, U.FAILURE_UNIT_SENSOR_OPTICAL_FLOW, U.FAILURE_TYPE_OK) == ACCEPTED
    assert telemetry.sys_status(now).onboard_control_sensors_health & (GPS_BIT | FLOW_BIT) == (
        GPS_BIT | FLOW_BIT
    )
    assert bench.texts() == [
        "GPS lost",
        "Optical flow lost",
        "GPS regained",
        "Optical flow regained",
    ]


def test_motor_off_drops_the_vehicle_which_keeps_talking_then_ok_flies_again() -> None:
    bench = Bench()
    bench.airborne()
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, U.FAILURE_TYPE_OFF, 1) == ACCEPTED
    bench.run_until(lambda: bench.position()[2] == 0.0, 5.0, "fallen")
    assert bench.ap.alive and bench.ap.motors_failed
    bench.run_until(lambda: not bench.ap.armed, 5.0, "auto-disarmed")
    assert bench.texts()[-2:] == ["Landing detected", "Disarmed by landing"]
    # Another motor back is not enough; all of them are.
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, U.FAILURE_TYPE_OK, 2) == ACCEPTED
    assert bench.ap.motors_failed
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, U.FAILURE_TYPE_OK, 0) == ACCEPTED
    bench.airborne()
    assert bench.position()[2] < -2.0


def test_motor_stuck_and_wrong_touch_only_esc_telemetry_so_nothing_changes() -> None:
    bench = Bench()
    bench.airborne()
    for failure_type in (U.FAILURE_TYPE_STUCK, U.FAILURE_TYPE_WRONG):
        assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, failure_type, 3) == ACCEPTED
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, U.FAILURE_TYPE_GARBAGE, 3) == UNSUPPORTED
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, U.FAILURE_TYPE_OFF, 9) == UNSUPPORTED
    bench.run(2.0)
    assert not bench.ap.landed and not bench.ap.motors_failed


def test_battery_off_warns_holds_for_com_fail_act_t_and_lands() -> None:
    bench = Bench()
    bench.airborne()
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_BATTERY, U.FAILURE_TYPE_OFF) == ACCEPTED
    bench.step()
    assert bench.texts()[-3:] == [
        "Low battery",
        "Failsafe activated: entering Hold for 5 seconds",
        "Emergency battery level",
    ]
    assert bench.ap.telemetry.battery_status(bench.t).battery_remaining == 0
    assert bench.ap.mode is FlightMode.HOLD and bench.ap.failsafe_active
    bench.run(4.9)
    assert bench.ap.mode is FlightMode.HOLD
    bench.run(0.2)
    assert bench.ap.mode is FlightMode.LAND
    bench.run_until(lambda: not bench.ap.armed, 30.0, "landed and disarmed")
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_BATTERY, U.FAILURE_TYPE_OK) == ACCEPTED
    assert bench.ap.battery_remaining_pct > 90.0


def test_rc_signal_off_is_a_manual_control_loss() -> None:
    bench = Bench()
    bench.airborne()
    bench.sticks(0.5)
    assert bench.set_mode(3) == ACCEPTED  # POSCTL
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_RC_SIGNAL, U.FAILURE_TYPE_OFF) == ACCEPTED
    bench.sticks(1.0)  # still streaming, but the failed RC signal drops it
    assert bench.ap.mode is FlightMode.HOLD
    assert bench.texts()[-1] == "Failsafe activated: entering Hold for 5 seconds"


@pytest.mark.parametrize(
    ("unit", "failure_type"),
    [
        (U.FAILURE_UNIT_SENSOR_GYRO, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SENSOR_ACCEL, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SENSOR_MAG, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SENSOR_BARO, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SENSOR_VIO, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SENSOR_DISTANCE_SENSOR, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SENSOR_AIRSPEED, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SYSTEM_SERVO, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SYSTEM_AVOIDANCE, U.FAILURE_TYPE_OFF),
        (U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_STUCK),
        (U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_GARBAGE),
        (U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_WRONG),
        (U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_SLOW),
        (U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_DELAYED),
        (U.FAILURE_UNIT_SENSOR_GPS, U.FAILURE_TYPE_INTERMITTENT),
        (U.FAILURE_UNIT_SYSTEM_BATTERY, U.FAILURE_TYPE_STUCK),
        (200, U.FAILURE_TYPE_OFF),
    ],
)
def test_failures_the_emulator_has_no_model_for_are_unsupported(
    unit: int, failure_type: int
) -> None:
    bench = Bench()
    assert inject(bench, unit, failure_type) == UNSUPPORTED
    assert bench.ap.gps_ok and bench.ap.flow_ok and not bench.ap.motors_failed


def test_mavlink_signal_needs_the_emulator_links() -> None:
    bench = Bench()  # fake links: nobody to switch them
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, U.FAILURE_TYPE_OFF) == UNSUPPORTED


def test_px4s_failure_shell_command_injects_the_same_failures() -> None:
    bench = Bench()
    pxh = bench.ap._receiver.shell.pxh
    assert pxh.run("failure gps off") == (
        "WARN  [failure] inject failure unit: gps (4), type: off (1), instance: 0\n"
    )
    assert not bench.ap.gps_ok
    assert pxh.run("failure motor off -i 1").endswith("type: off (1), instance: 1\n")
    assert bench.ap.motors_failed
    assert pxh.run("failure gyro off").endswith(
        "ERROR [failure] Result: 3\nCommand 'failure' failed, returned 1.\n"
    )
    assert pxh.run("failure compass off") == (
        "ERROR [failure] Component 'compass' not found\nCommand 'failure' failed, returned 1.\n"
    )
    assert pxh.run("failure gps").endswith("ERROR [failure] Not enough arguments.\n" + FAILED)
    bench.ap.params.set("SYS_FAILURE_EN", 0)
    assert pxh.run("failure gps ok") == (
        "ERROR [failure] Failure injection disabled by SYS_FAILURE_EN param.\n" + FAILED
    )


FAILED = "Command 'failure' failed, returned 1.\n"


def config(**kwargs: object) -> EmulatorConfig:
    return EmulatorConfig(
        vehicles=1,
        ports=free_port_config(1),
        clock=ClockConfig(speed=10.0),
        **kwargs,  # type: ignore[arg-type]
    )


@pytest.mark.asyncio
async def test_mavlink_signal_off_is_acknowledged_then_every_link_goes_silent() -> None:
    cfg = config(params={"COM_DL_LOSS_T": 5, "NAV_DLL_ACT": 3})
    async with (
        Emulator(cfg) as emulator,
        RawClient(cfg.ports.api_remote_port(0)) as api,
        RawClient(cfg.ports.gcs_remote_port) as gcs,
    ):
        await api.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "heartbeat")
        await gcs.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "heartbeat on the GCS link")
        await emulator.wait_for(lambda: emulator.autopilot(0).ready(emulator.time_s), timeout_s=3)
        api.heartbeat(1)
        assert await api.command(1, 400, 1) == ACCEPTED
        assert await api.command(1, 22, *[math.nan] * 7) == ACCEPTED
        result = await api.command(
            1, INJECT, U.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, U.FAILURE_TYPE_OFF, 0
        )
        assert result == ACCEPTED
        await emulator.run_for(0.1)
        api.counts.clear()
        gcs.counts.clear()
        await emulator.run_for(2.0)
        assert api.counts == {} and gcs.counts == {}
        assert (0, "all link dropped") in [(i, what) for _, i, what in emulator.events]
        # No client heartbeat gets through either: after COM_DL_LOSS_T, NAV_DLL_ACT lands.
        await emulator.wait_for(
            lambda: emulator.vehicle_status(0).mode is FlightMode.LAND, timeout_s=5, what="land"
        )
        assert "Connection to ground station lost" in emulator.vehicle_status(0).status_texts
        emulator.inject_failure(0, "mavlink_signal", "ok")
        await api.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "heartbeat after ok")


@pytest.mark.asyncio
async def test_fault_api_and_config_inject_the_same_failures() -> None:
    faults = [
        {"kind": "failure", "vehicle_index": 0, "unit": "gps", "at_s": 0.5, "duration_s": 1.0},
        {"kind": "sensor", "vehicle_index": 0, "sensor": "flow", "at_s": 0.5},
    ]
    async with Emulator(config(faults=faults)) as emulator:
        await emulator.run_for(1.0)
        status = emulator.vehicle_status(0)
        assert not status.gps_ok and not status.flow_ok
        await emulator.run_for(1.0)
        assert emulator.vehicle_status(0).gps_ok
        injected = [
            (round(t, 2), what)
            for t, _, what in emulator.events
            if what.split()[-1] in ("off", "ok")
        ]
        assert injected == [(0.5, "gps off"), (0.5, "optical_flow off"), (1.5, "gps ok")]
        emulator.inject_failure(0, "battery")
        assert emulator.vehicle_status(0).battery_percent == 0.0
        with pytest.raises(ValueError, match="cannot inject gyro off"):
            emulator.inject_failure(0, "gyro")
        with pytest.raises(ValueError, match="unknown failure unit 'compass'"):
            emulator.inject_failure(0, "compass")


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_failure_plugin_injects_gps_and_motor_failures() -> None:
    async with emulated_drones(api_config(speed=5.0)) as (emulator, [drone]):
        failure = FailureAsync(drone.system)
        await healthy(drone)
        await failure.inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)
        await first(
            drone.telemetry.subscribe_gps_info(),
            lambda g: g.fix_type in (FixType.NO_GPS, FixType.NO_FIX),
            5,
            "no GPS fix",
        )
        await failure.inject(FailureUnit.SENSOR_GPS, FailureType.OK, 0)
        await first(
            drone.telemetry.subscribe_gps_info(),
            lambda g: g.fix_type == FixType.FIX_3D,
            5,
            "GPS fix again",
        )
        with pytest.raises(FailureError) as unsupported:
            await failure.inject(FailureUnit.SENSOR_GYRO, FailureType.OFF, 0)
        assert unsupported.value.result == MavsdkFailureResult.UNSUPPORTED

        await take_off(drone)
        await failure.inject(FailureUnit.SYSTEM_MOTOR, FailureType.OFF, 1)
        await first(drone.telemetry.subscribe_in_air(), lambda air: not air, 10, "on the ground")
        assert emulator.truth.position_ned_m[0, 2] == 0.0
        await first(drone.telemetry.subscribe_armed(), lambda armed: not armed, 10, "disarmed")
        assert math.isclose(emulator.vehicle_status(0).battery_percent, 100.0, abs_tol=5.0)

        await drone.param.set_param_int("SYS_FAILURE_EN", 0)
        with pytest.raises(FailureError) as denied:
            await failure.inject(FailureUnit.SYSTEM_MOTOR, FailureType.OK, 0)
        assert denied.value.result == MavsdkFailureResult.DENIED


def test_motors_back_in_a_climb_finish_the_same_takeoff() -> None:
    bench = Bench(params={"MIS_TAKEOFF_ALT": 5.0})
    assert bench.command(400, 1) == ACCEPTED
    assert bench.command(22, -1, 0, 0, *[math.nan] * 4) == ACCEPTED
    bench.run_until(lambda: bench.position()[2] < -2.0, 10.0, "2 m up")
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, U.FAILURE_TYPE_OFF, 0) == ACCEPTED
    bench.run(0.2)
    assert inject(bench, U.FAILURE_UNIT_SYSTEM_MOTOR, U.FAILURE_TYPE_OK, 0) == ACCEPTED
    bench.run_until(lambda: bench.ap.mode is FlightMode.HOLD, 15.0, "the climb's end")
    assert -bench.position()[2] == pytest.approx(5.0, abs=0.1)
    assert bench.texts().count("Using default takeoff altitude: 5.0 m") == 1
