"""PX4 behaviour of the autopilot state machine, stepped synchronously with fake links."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED as ACCEPTED
from pymavlink.dialects.v20.common import MAV_RESULT_DENIED as DENIED
from pymavlink.dialects.v20.common import MAV_RESULT_TEMPORARILY_REJECTED as TEMPORARILY_REJECTED
from pymavlink.dialects.v20.common import MAV_RESULT_UNSUPPORTED as UNSUPPORTED

from sitl.modes import FlightMode
from sitl.params import int32_to_wire_float, wire_float_to_int32
from tests.sitl.helpers import Bench

ARM = 400
TAKEOFF = 22
LAND = 21
SET_MODE = 176
AUTO, OFFBOARD = 4, 6
HOLD, MISSION, RTL = 3, 4, 5


def airborne(bench: Bench, vehicle: int = 0) -> None:
    bench.airborne(vehicle)


# ------------------------------------------------------------------------- arming
def test_arming_is_refused_until_preflight_checks_pass() -> None:
    bench = Bench(ready_after_s=1.0)
    assert bench.command(ARM, 1) == TEMPORARILY_REJECTED
    assert not bench.ap.armed
    texts = bench.link.of_type("STATUSTEXT")
    assert texts and texts[-1].text.startswith("Arming denied")
    bench.run(1.1)
    assert bench.command(ARM, 1) == ACCEPTED
    assert bench.ap.armed


def test_disarm_in_air_needs_force() -> None:
    bench = Bench()
    airborne(bench)
    assert bench.command(ARM, 0) == DENIED
    assert bench.ap.armed
    assert bench.command(ARM, 0, 21196) == ACCEPTED
    assert not bench.ap.armed
    bench.run(3)
    assert bench.position()[2] == 0.0  # fell


def test_armed_but_never_taking_off_disarms_after_com_disarm_prflt() -> None:
    bench = Bench(params={"COM_DISARM_PRFLT": 3.0})
    bench.command(ARM, 1)
    bench.run(2.9)
    assert bench.ap.armed
    bench.run(0.2)
    assert not bench.ap.armed
    assert "Disarmed by auto preflight disarming" in bench.texts()


# ---------------------------------------------------------------- takeoff / land
def test_takeoff_climbs_to_mis_takeoff_alt_then_holds() -> None:
    bench = Bench(params={"MIS_TAKEOFF_ALT": 4.0})
    airborne(bench)
    assert -bench.position()[2] == pytest.approx(4.0, abs=0.15)
    bench.run(5)
    assert -bench.position()[2] == pytest.approx(4.0, abs=0.05)
    assert bench.ap.landed_state == 2  # IN_AIR


def test_takeoff_while_disarmed_only_switches_the_mode() -> None:
    bench = Bench()
    assert bench.command(TAKEOFF) == ACCEPTED  # PX4 1.15 on: the climb starts on arming
    assert bench.ap.mode is FlightMode.TAKEOFF
    bench.run(2)
    assert not bench.ap.armed and -bench.position()[2] == pytest.approx(0.0, abs=1e-6)


def test_land_descends_then_auto_disarms_after_com_disarm_land() -> None:
    bench = Bench(params={"COM_DISARM_LAND": 1.0})
    airborne(bench)
    assert bench.command(LAND) == ACCEPTED
    bench.step()
    assert bench.ap.landed_state == 4  # LANDING
    landed = bench.run_until(lambda: bench.ap.landed, 20, "landed")
    assert landed > 2.5 / 0.7 * 0.9  # MPC_LAND_SPEED close to the ground
    assert bench.ap.armed
    bench.run_until(lambda: not bench.ap.armed, 1.5, "auto-disarmed")
    assert bench.texts()[-2:] == ["Landing detected", "Disarmed by landing"]


# ---------------------------------------------------------------------- modes
def test_mode_switches_follow_px4_rules() -> None:
    bench = Bench()
    assert bench.set_mode(OFFBOARD) == TEMPORARILY_REJECTED  # no setpoints yet
    assert bench.set_mode(AUTO, MISSION) == TEMPORARILY_REJECTED  # no mission
    assert bench.set_mode(3) == TEMPORARILY_REJECTED  # POSCTL needs RC
    assert bench.set_mode(AUTO, RTL) == ACCEPTED
    assert bench.ap.mode is FlightMode.RTL
    assert bench.set_mode(AUTO, 99) == DENIED
    assert bench.command(SET_MODE, 0, AUTO, HOLD) == DENIED  # custom-mode flag missing
    # param 1 may carry a stale armed bit: only the custom flag matters.
    assert bench.command(SET_MODE, 1 | 128, AUTO, HOLD) == ACCEPTED


def test_heartbeat_reports_px4_custom_mode_and_armed_flag() -> None:
    bench = Bench()
    airborne(bench)
    hb = bench.ap.telemetry.heartbeat(bench.t)
    assert (hb.type, hb.autopilot) == (2, 12)
    assert hb.custom_mode == 50593792  # AUTO_LOITER
    assert hb.base_mode & 128 and hb.base_mode & 1


# ------------------------------------------------------------------- offboard
def test_offboard_velocity_flight_and_loss_failsafe_to_hold() -> None:
    bench = Bench()
    airborne(bench)
    bench.velocity_setpoint(2.0, 0.0, 0.0)
    assert bench.set_mode(OFFBOARD) == ACCEPTED
    start = bench.position()
    for _ in range(50):  # 5 s of setpoints at 10 Hz
        bench.velocity_setpoint(2.0, 0.0, 0.0)
        bench.run(0.1)
    flown = bench.position()[0] - start[0]
    assert 9.0 < flown <= 10.0
    assert bench.ap.mode is FlightMode.OFFBOARD
    bench.run(1.05)  # COM_OF_LOSS_T = 1 s without setpoints
    assert bench.ap.mode is FlightMode.HOLD
    assert bench.ap.failsafe_active
    assert "Failsafe activated: offboard control lost" in bench.texts()
    bench.run(3)
    held = bench.position()
    bench.run(3)
    assert math.dist(held, bench.position()) < 0.05


def test_offboard_loss_lands_with_com_obl_rc_act_4() -> None:
    bench = Bench(params={"COM_OBL_RC_ACT": 4})
    airborne(bench)
    bench.velocity_setpoint(0, 0, 0)
    bench.set_mode(OFFBOARD)
    bench.run(1.1)
    assert bench.ap.mode is FlightMode.LAND


def test_body_frame_velocity_is_rotated_by_heading() -> None:
    bench = Bench()
    airborne(bench)
    bench.physics.yaw_rad[0] = math.pi / 2  # facing east
    bench.snapshot.refresh(bench.physics, bench.odometry)
    body = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 8, 1479, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0
    )
    bench.deliver(body)
    bench.set_mode(OFFBOARD)
    bench.deliver(body)
    assert list(bench.physics.velocity_setpoint_ned_m_s[0]) == pytest.approx([0.0, 1.0, 0.0])


def test_position_setpoints_use_the_vehicle_odometry_frame() -> None:
    # Vehicle 1 starts 5 m east of the world origin: its local (0, 0) is its start point.
    bench = Bench(2)
    airborne(bench, 1)
    msg = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 2, 1, 1, 2552, 3.0, 0.0, -5.0, 0, 0, 0, 0, 0, 0, 0, 0
    )
    bench.deliver(msg, vehicle=1)
    assert bench.set_mode(OFFBOARD, vehicle=1) == ACCEPTED
    for _ in range(100):
        bench.deliver(msg, vehicle=1)
        bench.run(0.1)
    assert bench.position(1) == pytest.approx([3.0, 5.0, -5.0], abs=0.05)


def test_non_finite_or_absurd_setpoints_are_ignored() -> None:
    bench = Bench()
    airborne(bench)
    bench.velocity_setpoint(1.0, 0, 0)
    bench.set_mode(OFFBOARD)
    bench.velocity_setpoint(math.nan, 0, 0)
    bench.velocity_setpoint(math.inf, 0, 0)
    bench.velocity_setpoint(1e9, 0, 0)
    assert bench.ap.rejected_setpoints == 3
    assert list(bench.physics.velocity_setpoint_ned_m_s[0]) == [1.0, 0.0, 0.0]


# ---------------------------------------------------------------- link loss
def test_link_loss_triggers_nav_dll_act_return() -> None:
    bench = Bench(params={"NAV_DLL_ACT": 2, "COM_DL_LOSS_T": 5, "RTL_RETURN_ALT": 5.0})
    gcs_heartbeat = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)
    bench.deliver(gcs_heartbeat)
    airborne(bench)
    bench.deliver(gcs_heartbeat)
    bench.run(4.9)
    assert bench.ap.mode is FlightMode.HOLD
    bench.run(0.2)
    assert bench.ap.mode is FlightMode.RTL
    assert "Connection to ground station lost" in bench.texts()
    bench.deliver(gcs_heartbeat)
    assert "Data link regained" in bench.texts()


def test_vehicle_heartbeats_do_not_count_as_a_ground_station() -> None:
    bench = Bench(params={"NAV_DLL_ACT": 2, "COM_DL_LOSS_T": 5})
    bench.deliver(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3), src=(7, 1))
    airborne(bench)
    bench.run(6)
    assert bench.ap.mode is FlightMode.HOLD


# ------------------------------------------------------------------------ RTL
def test_rtl_climbs_returns_descends_and_lands() -> None:
    bench = Bench(params={"RTL_RETURN_ALT": 8.0, "RTL_DESCEND_ALT": 4.0, "COM_DISARM_LAND": 1})
    airborne(bench)
    bench.velocity_setpoint(5.0, 5.0, 0.0)
    bench.set_mode(OFFBOARD)
    for _ in range(40):
        bench.velocity_setpoint(5.0, 5.0, 0.0)
        bench.run(0.1)
    assert math.hypot(*bench.position()[:2]) > 15
    assert bench.set_mode(AUTO, RTL) == ACCEPTED
    max_altitude = 0.0
    while bench.ap.armed and bench.t < 120:
        bench.step()
        max_altitude = max(max_altitude, -bench.position()[2])
    assert not bench.ap.armed
    assert max_altitude == pytest.approx(8.0, abs=0.3)
    assert math.hypot(*bench.position()[:2]) < 1.0
    assert bench.position()[2] == 0.0


# ------------------------------------------------------------------- commands
def test_every_command_is_acknowledged_and_retries_are_answered() -> None:
    bench = Bench()
    assert bench.command(31337) == UNSUPPORTED
    assert bench.command(ARM, 1) == ACCEPTED
    assert bench.command(ARM, 1) == ACCEPTED  # a retry gets the same answer
    ack = bench.link.of_type("COMMAND_ACK")[-1]
    assert (ack.target_system, ack.target_component) == (255, 190)


def test_commands_for_other_systems_or_components_are_ignored() -> None:
    bench = Bench(2)
    assert bench.command(ARM, 1, vehicle=0, target=2) is None
    assert bench.command(ARM, 1, vehicle=0, target_component=42) is None
    assert not bench.ap.armed
    assert bench.command(ARM, 1, vehicle=0, target_component=0) == ACCEPTED


def test_request_message_answers_after_the_ack() -> None:
    bench = Bench()
    assert bench.command(512, 148) == ACCEPTED
    kinds = [m.get_type() for m in bench.link.sent]
    assert kinds[-2:] == ["COMMAND_ACK", "AUTOPILOT_VERSION"]
    version = bench.link.sent[-1]
    assert version.capabilities & 0x4 and version.capabilities & 0x2000  # MISSION_INT, MAVLINK2
    assert bench.command(520, 1) == ACCEPTED
    assert bench.link.sent[-1].get_type() == "AUTOPILOT_VERSION"
    assert bench.command(512, 242) == ACCEPTED
    assert bench.link.sent[-1].get_type() == "HOME_POSITION"
    assert bench.command(512, 12345) == DENIED


def test_set_message_interval_changes_the_stream_of_that_link() -> None:
    bench = Bench()
    assert bench.command(511, 33, 50_000) == ACCEPTED  # GLOBAL_POSITION_INT at 20 Hz
    assert bench.link.streams.period_s(33) == pytest.approx(0.05)
    assert bench.command(511, 33, -1) == ACCEPTED
    assert bench.link.streams.period_s(33) is None
    assert bench.command(511, 33, 0) == ACCEPTED  # back to the default
    assert bench.link.streams.period_s(33) == pytest.approx(0.1)
    assert bench.command(510, 33) == ACCEPTED
    assert bench.link.sent[-1].get_type() == "MESSAGE_INTERVAL"
    assert bench.link.sent[-1].interval_us == 100_000
    # PX4 answers FAILED for messages it has no stream of, and for its 1 Hz heartbeat.
    assert bench.command(511, 12345, 50_000) == mavlink.MAV_RESULT_FAILED
    assert bench.command(511, 0, 50_000) == mavlink.MAV_RESULT_FAILED


def test_ping_and_timesync_are_answered() -> None:
    bench = Bench()
    bench.run(1)
    bench.deliver(mavlink.MAVLink_ping_message(123, 7, 0, 0))
    pong = bench.link.sent[-1]
    assert (pong.get_type(), pong.time_usec, pong.seq, pong.target_system) == ("PING", 123, 7, 255)
    bench.deliver(mavlink.MAVLink_timesync_message(0, 555))
    sync = bench.link.sent[-1]
    assert sync.get_type() == "TIMESYNC" and sync.ts1 == 555 and sync.tc1 > 0


def test_reposition_flies_to_the_global_target() -> None:
    bench = Bench()
    airborne(bench)
    lat, lon = bench.projection.to_global(20.0, -10.0)
    msg = mavlink.MAVLink_command_int_message(
        1, 1, 5, 192, 0, 0, -1, 1, 0, math.nan, round(lat * 1e7), round(lon * 1e7), 488.0 + 6.0
    )
    bench.deliver(msg)
    assert bench.link.of_type("COMMAND_ACK")[-1].result == ACCEPTED
    bench.run(15)
    assert bench.position() == pytest.approx([20.0, -10.0, -6.0], abs=0.1)


# --------------------------------------------------------------------- params
def test_param_protocol_read_list_and_set() -> None:
    bench = Bench()
    bench.deliver(mavlink.MAVLink_param_request_read_message(1, 1, b"MIS_TAKEOFF_ALT", -1))
    value = bench.link.sent[-1]
    assert (value.param_id, value.param_value, value.param_type) == ("MIS_TAKEOFF_ALT", 2.5, 9)
    bench.deliver(
        mavlink.MAVLink_param_set_message(1, 1, b"NAV_DLL_ACT", int32_to_wire_float(3), 6)
    )
    echo = bench.link.sent[-1]
    assert echo.param_id == "NAV_DLL_ACT" and wire_float_to_int32(echo.param_value) == 3
    assert bench.ap.params["NAV_DLL_ACT"] == 3
    bench.link.clear()
    bench.deliver(mavlink.MAVLink_param_request_list_message(1, 1))
    values = bench.link.of_type("PARAM_VALUE")
    assert len(values) == values[0].param_count == len(bench.ap.params)
    assert sorted(v.param_index for v in values) == list(range(len(values)))
    bench.link.clear()
    bench.deliver(mavlink.MAVLink_param_request_read_message(1, 1, b"NOT_A_PARAM", -1))
    assert bench.link.sent == []


def test_param_set_changes_the_flight_limits() -> None:
    bench = Bench()
    bench.deliver(mavlink.MAVLink_param_set_message(1, 1, b"MPC_XY_VEL_MAX", 3.0, 9))
    assert bench.physics.max_horizontal_speed_m_s[0] == 3.0
    bench.deliver(mavlink.MAVLink_param_set_message(1, 1, b"MPC_XY_VEL_MAX", 99.0, 9))
    assert bench.link.sent[-1].param_value == 3.0  # out of range: the old value is echoed


# -------------------------------------------------------------------- mission
def upload(bench: Bench, items: list[tuple[int, float, float, float]]) -> None:
    """Upload (command, north, east, altitude) items as MAVSDK would."""
    bench.deliver(mavlink.MAVLink_mission_count_message(1, 1, len(items), 0))
    for seq, (command, north, east, altitude) in enumerate(items):
        request = bench.link.sent[-1]
        assert request.get_type() == "MISSION_REQUEST_INT" and request.seq == seq
        lat, lon = bench.projection.to_global(north, east)
        bench.deliver(
            mavlink.MAVLink_mission_item_int_message(
                1,
                1,
                seq,
                6,
                command,
                int(seq == 0),
                1,
                0.5,
                1.0,
                0,
                math.nan,
                round(lat * 1e7),
                round(lon * 1e7),
                altitude,
                0,
            )
        )
    ack = bench.link.sent[-1]
    assert ack.get_type() == "MISSION_ACK" and ack.type == 0


def test_mission_is_flown_item_by_item_and_reported() -> None:
    bench = Bench(params={"COM_DISARM_LAND": 1})
    upload(bench, [(16, 10.0, 0.0, 5.0), (16, 10.0, 10.0, 5.0), (21, 0.0, 10.0, 0.0)])
    assert bench.command(ARM, 1) == ACCEPTED
    assert bench.set_mode(AUTO, MISSION) == ACCEPTED
    bench.run_until(lambda: not bench.ap.armed, 120, "mission flown and landed")
    reached = [m.seq for m in bench.link.of_type("MISSION_ITEM_REACHED")]
    assert reached == [0, 1, 2]
    assert bench.position() == pytest.approx([0.0, 10.0, 0.0], abs=1.0)
    current = bench.link.of_type("MISSION_CURRENT")[-1]
    assert (current.total, current.mission_state) == (3, 5)  # COMPLETE


def test_mission_start_command_and_rtl_item() -> None:
    bench = Bench(params={"RTL_RETURN_ALT": 6, "RTL_DESCEND_ALT": 3, "COM_DISARM_LAND": 1})
    upload(bench, [(16, 10.0, 0.0, 5.0), (20, 0, 0, 0)])
    bench.command(ARM, 1)
    assert bench.command(300, 0, 0) == ACCEPTED
    bench.run_until(lambda: bench.ap.mode is FlightMode.RTL, 60, "RTL item")
    assert [m.seq for m in bench.link.of_type("MISSION_ITEM_REACHED")] == [0]
    bench.run_until(lambda: not bench.ap.armed, 60, "landed home")
    assert math.hypot(*bench.position()[:2]) < 1.0


# ----------------------------------------------------------- sensors and death
def test_flow_loss_stops_local_position_and_clears_its_health_bit() -> None:
    bench = Bench()
    builder = bench.ap.telemetry
    assert builder.local_position_ned(0.0) is not None
    bench.ap.set_sensor("flow", False, 0.0)
    assert builder.local_position_ned(0.0) is None
    status = builder.sys_status(5.0)
    assert not status.onboard_control_sensors_health & 0x40
    assert status.onboard_control_sensors_health & 0x10000000  # GPS still gives position
    bench.ap.set_sensor("gps", False, 0.0)
    assert not builder.sys_status(5.0).onboard_control_sensors_health & 0x10000000


def test_losing_every_position_source_in_flight_lands() -> None:
    bench = Bench()
    airborne(bench)
    bench.ap.set_sensor("flow", False, bench.t)
    bench.ap.set_sensor("gps", False, bench.t)
    bench.step()
    assert bench.ap.mode is FlightMode.LAND


def test_a_killed_vehicle_falls_and_stays_silent() -> None:
    bench = Bench()
    airborne(bench)
    bench.ap.kill(bench.t)
    bench.link.clear()
    assert bench.command(ARM, 0, 21196) is None
    bench.run(3)
    assert bench.position()[2] == 0.0
    assert bench.link.sent == []


def test_odometry_starts_at_the_power_on_point_and_drifts() -> None:
    bench = Bench(2, odometry={"drift_bias_std_m_s": 0.05})
    x, y, z, *_ = bench.autopilots[1].odometry_sample()
    assert (x, y, z) == (0.0, 0.0, 0.0)  # not the world frame (vehicle 1 is 5 m east)
    bench.run(100)
    x, y, _, *_ = bench.autopilots[1].odometry_sample()
    assert math.hypot(x, y) > 0.05  # standing still, but the estimate has wandered


def test_attitude_setpoints_become_an_acceleration() -> None:
    bench = Bench()
    airborne(bench)
    pitch_forward = [math.cos(-0.1), 0.0, math.sin(-0.1), 0.0]  # nose down 0.2 rad, heading north
    msg = mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 0x7, pitch_forward, 0, 0, 0, 0.5)
    bench.deliver(msg)
    climb = bench.physics.velocity_ned_m_s[0, 2]
    assert bench.set_mode(OFFBOARD) == ACCEPTED
    for _ in range(10):
        bench.deliver(msg)
        bench.run(0.1)
    velocity = bench.physics.velocity_ned_m_s[0]
    assert velocity[0] == pytest.approx(9.81 * math.tan(0.2), rel=0.05)  # a = g tan(pitch), 1 s
    assert velocity[2] == pytest.approx(climb, abs=1e-9)  # hover thrust: no vertical accel


def test_global_position_setpoints_fly_to_the_coordinates() -> None:
    bench = Bench()
    airborne(bench)
    lat, lon = bench.projection.to_global(-8.0, 6.0)
    msg = mavlink.MAVLink_set_position_target_global_int_message(
        0, 1, 1, 6, 3576, round(lat * 1e7), round(lon * 1e7), 4.0, 0, 0, 0, 0, 0, 0, 0, 0
    )
    bench.deliver(msg)
    assert bench.set_mode(OFFBOARD) == ACCEPTED
    for _ in range(100):
        bench.deliver(msg)
        bench.run(0.1)
    assert bench.position() == pytest.approx([-8.0, 6.0, -4.0], abs=0.05)
