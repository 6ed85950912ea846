"""What an emulated vehicle reports: MAVLink message builders and per-link stream schedules.

:class:`StreamScheduler` keeps, for one link, the period of every stream in simulated seconds
(from :class:`sitl.config.StreamRates`, changed at run time by SET_MESSAGE_INTERVAL) and says
which streams are due. :class:`TelemetryBuilder` turns one vehicle's state into the message for a
message id; the same builder answers REQUEST_MESSAGE.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal, Protocol

from pymavlink.dialects.v20 import common as mavlink

from sitl import imu
from sitl.messages import MAVLINK_MSG_ID_PROTOCOL_VERSION, MAVLinkProtocolVersionMessage
from sitl.modes import base_mode

if TYPE_CHECKING:
    from sitl.config import StreamRates
    from sitl.modes import FlightMode
    from sitl.params import ParamStore

MSG_HEARTBEAT = 0
MSG_SYS_STATUS = 1
MSG_SYSTEM_TIME = 2
MSG_GPS_RAW_INT = 24
MSG_SCALED_IMU = 26
MSG_ATTITUDE = 30
MSG_ATTITUDE_QUATERNION = 31
MSG_LOCAL_POSITION_NED = 32
MSG_GLOBAL_POSITION_INT = 33
MSG_MISSION_CURRENT = 42
MSG_GPS_GLOBAL_ORIGIN = 49
MSG_VFR_HUD = 74
MSG_HIGHRES_IMU = 105
MSG_HIL_STATE_QUATERNION = 115
MSG_ALTITUDE = 141
MSG_BATTERY_STATUS = 147
MSG_AUTOPILOT_VERSION = 148
MSG_HOME_POSITION = 242
MSG_PROTOCOL_VERSION = MAVLINK_MSG_ID_PROTOCOL_VERSION
MSG_EXTENDED_SYS_STATE = 245

#: Stream message id -> StreamRates field.
STREAM_RATE_FIELDS: dict[int, str] = {
    MSG_HEARTBEAT: "heartbeat_hz",
    MSG_SYS_STATUS: "sys_status_hz",
    MSG_EXTENDED_SYS_STATE: "extended_sys_state_hz",
    MSG_GLOBAL_POSITION_INT: "global_position_int_hz",
    MSG_LOCAL_POSITION_NED: "local_position_ned_hz",
    MSG_ATTITUDE: "attitude_hz",
    MSG_ATTITUDE_QUATERNION: "attitude_quaternion_hz",
    MSG_HOME_POSITION: "home_position_hz",
    MSG_BATTERY_STATUS: "battery_status_hz",
    MSG_GPS_RAW_INT: "gps_raw_int_hz",
    MSG_VFR_HUD: "vfr_hud_hz",
    MSG_ALTITUDE: "altitude_hz",
    MSG_MISSION_CURRENT: "mission_current_hz",
    MSG_HIL_STATE_QUATERNION: "hil_state_quaternion_hz",
    MSG_HIGHRES_IMU: "highres_imu_hz",
    MSG_SCALED_IMU: "scaled_imu_hz",
}

#: Messages that can be requested once (REQUEST_MESSAGE) or streamed (SET_MESSAGE_INTERVAL).
BUILDABLE: frozenset[int] = frozenset(
    [
        *STREAM_RATE_FIELDS,
        MSG_SYSTEM_TIME,
        MSG_GPS_GLOBAL_ORIGIN,
        MSG_AUTOPILOT_VERSION,
        MSG_PROTOCOL_VERSION,
    ]
)
#: Of those, the ones only sent on request here.
NOT_STREAMABLE: frozenset[int] = frozenset([MSG_AUTOPILOT_VERSION, MSG_PROTOCOL_VERSION])

#: Messages PX4 has a stream of (PX4 v1.16 src/modules/mavlink/mavlink_messages.cpp,
#: ``streams_list``; those pymavlink's common dialect knows). PX4 accepts SET_MESSAGE_INTERVAL for
#: any of them (``MavlinkReceiver::set_message_interval``: FAILED only for an id without a stream).
#: The emulator builds only :data:`BUILDABLE`: stopping one of the others is accepted (it is not
#: sent anyway, as a client that stops PX4's defaults expects); starting one is FAILED.
PX4_STREAMS: frozenset[int] = frozenset(
    getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
    for name in (
        "ACTUATOR_OUTPUT_STATUS",
        "ALTITUDE",
        "ATTITUDE",
        "ATTITUDE_QUATERNION",
        "ATTITUDE_TARGET",
        "AUTOPILOT_VERSION",
        "BATTERY_STATUS",
        "CAMERA_IMAGE_CAPTURED",
        "CAMERA_TRIGGER",
        "COMMAND_LONG",
        "DISTANCE_SENSOR",
        "EFI_STATUS",
        "ESTIMATOR_STATUS",
        "EXTENDED_SYS_STATE",
        "FLIGHT_INFORMATION",
        "GLOBAL_POSITION_INT",
        "GPS_GLOBAL_ORIGIN",
        "GPS_RAW_INT",
        "GPS_RTCM_DATA",
        "GPS_STATUS",
        "HIGHRES_IMU",
        "HIL_ACTUATOR_CONTROLS",
        "HIL_STATE_QUATERNION",
        "HOME_POSITION",
        "LANDING_TARGET",
        "LOCAL_POSITION_NED",
        "MAG_CAL_REPORT",
        "MANUAL_CONTROL",
        "MOUNT_ORIENTATION",
        "NAV_CONTROLLER_OUTPUT",
        "OBSTACLE_DISTANCE",
        "ODOMETRY",
        "OPEN_DRONE_ID_BASIC_ID",
        "OPEN_DRONE_ID_LOCATION",
        "OPEN_DRONE_ID_SYSTEM",
        "OPEN_DRONE_ID_ARM_STATUS",
        "OPTICAL_FLOW_RAD",
        "ORBIT_EXECUTION_STATUS",
        "PING",
        "POSITION_TARGET_GLOBAL_INT",
        "POSITION_TARGET_LOCAL_NED",
        "RAW_RPM",
        "RC_CHANNELS",
        "SCALED_IMU",
        "SCALED_IMU2",
        "SCALED_IMU3",
        "SCALED_PRESSURE",
        "SERVO_OUTPUT_RAW",
        "STATUSTEXT",
        "STORAGE_INFORMATION",
        "SYS_STATUS",
        "SYSTEM_TIME",
        "TIMESYNC",
        "VFR_HUD",
        "VIBRATION",
        "WIND_COV",
    )
)

# SYS_STATUS sensor bits (MAV_SYS_STATUS_SENSOR)
_GYRO = 0x1
_ACCEL = 0x2
_MAG = 0x4
_BARO = 0x8
_GPS = 0x20
_FLOW = 0x40
_MOTORS = 0x8000
_AHRS = 0x200000
_BATTERY = 0x2000000
_PREARM = 0x10000000
_SENSORS_PRESENT = _GYRO | _ACCEL | _MAG | _BARO | _GPS | _FLOW | _MOTORS | _AHRS | _BATTERY

MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_PX4 = 12
MAV_STATE_BOOT = 1
MAV_STATE_CALIBRATING = 2
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_STATE_CRITICAL = 5

#: MAV_PROTOCOL_CAPABILITY bits of AUTOPILOT_VERSION: exactly the ones PX4 sets
#: (Mavlink::send_autopilot_capabilities; a running PX4 SITL answers 0xE8FF), each of which the
#: emulator handles. PX4 handles SET_POSITION_TARGET_GLOBAL_INT without setting its bit, and so
#: does the emulator: a client that decides by the bits decides as it would with PX4.
CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT  # MISSION_ITEM / MISSION_REQUEST
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE  # INT32 params in the float's bytes
    | mavlink.MAV_PROTOCOL_CAPABILITY_FTP  # sitl.ftp
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION  # MAV_CMD_DO_FLIGHTTERMINATION
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE  # fence items upload/download (not enforced)
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY  # rally items upload/download
)
GRAVITY_M_S2 = imu.GRAVITY_M_S2
#: HIGHRES_IMU.fields_updated: accelerometer, gyroscope, magnetometer and barometer (absolute
#: pressure, pressure altitude, temperature) - every field but the differential pressure.
_HIGHRES_IMU_FIELDS = 0x1BFF
#: PX4 SIH's ambient temperature, degC.
_AIR_TEMPERATURE_DEGC = 15.0

#: PX4 v1.15.0 release: major << 24 | minor << 16 | patch << 8 | FIRMWARE_VERSION_TYPE_OFFICIAL.
FLIGHT_SW_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255


#: A stream is due this much before its time: sums of float periods must not slip a step.
_DUE_SLACK_S = 1e-9


class StreamScheduler:
    """Which streams of one link are due, in simulated time.

    ``phase_s`` offsets the first emission so many vehicles do not all send in the same step.
    Streams are sent after physics steps, so none runs faster than one message per step
    (``step_s``): a faster SET_MESSAGE_INTERVAL is accepted, as PX4 accepts rates it cannot keep,
    and flown and reported (MESSAGE_INTERVAL) at one per step.
    """

    def __init__(self, rates: StreamRates, phase_s: float = 0.0, step_s: float = 0.0) -> None:
        self._step_s = step_s
        self._default_period_s: dict[int, float | None] = {}
        for msg_id, field in STREAM_RATE_FIELDS.items():
            hz = float(getattr(rates, field))
            self._default_period_s[msg_id] = max(1.0 / hz, step_s) if hz > 0 else None
        self._period_s: dict[int, float | None] = dict(self._default_period_s)
        self._next_due_s: dict[int, float] = {
            msg_id: phase_s for msg_id, period in self._period_s.items() if period is not None
        }
        self.next_due_s = min(self._next_due_s.values(), default=math.inf) - _DUE_SLACK_S

    def period_s(self, msg_id: int) -> float | None:
        return self._period_s.get(msg_id)

    def set_interval(self, msg_id: int, interval_us: float, now_s: float) -> bool:
        """Apply SET_MESSAGE_INTERVAL; False if this message cannot be streamed."""
        if not math.isfinite(interval_us):
            return False
        if msg_id not in BUILDABLE or msg_id in NOT_STREAMABLE:
            # A stream PX4 has and the emulator does not send: stopping it is what PX4 does.
            return interval_us < 0 and msg_id in PX4_STREAMS
        if interval_us < 0:
            period: float | None = None
        elif interval_us == 0:
            period = self._default_period_s.get(msg_id)
        else:
            period = max(interval_us * 1e-6, self._step_s)
        self._period_s[msg_id] = period
        if period is None:
            self._next_due_s.pop(msg_id, None)
        else:
            self._next_due_s[msg_id] = now_s
        self.next_due_s = min(self._next_due_s.values(), default=math.inf) - _DUE_SLACK_S
        return True

    def interval_us(self, msg_id: int) -> int:
        """For MESSAGE_INTERVAL: -1 if off, else the interval in microseconds."""
        period = self._period_s.get(msg_id)
        return -1 if period is None else round(period * 1e6)

    def due(self, now_s: float) -> list[int]:
        """Message ids due at ``now_s``; each is rescheduled one period later."""
        if now_s < self.next_due_s:
            return []
        due = []
        next_due = self._next_due_s
        for msg_id, due_s in next_due.items():
            if now_s >= due_s - _DUE_SLACK_S:
                due.append(msg_id)
                period = self._period_s[msg_id]
                assert period is not None
                next_s = due_s + period
                if next_s <= now_s:
                    # Behind by more than a period (e.g. after a pause): do not burst.
                    next_s = now_s + period
                next_due[msg_id] = next_s
        self.next_due_s = min(next_due.values(), default=math.inf) - _DUE_SLACK_S
        return due


class AutopilotView(Protocol):
    """What telemetry reads of a vehicle (:class:`sitl.autopilot.Px4Autopilot` has it): its state,
    never its parts, so the messages cannot reach into the commander or the navigator."""

    @property
    def armed(self) -> bool: ...
    def attitude(self) -> tuple[float, float, float, float]: ...
    @property
    def battery_remaining_pct(self) -> float: ...
    def battery_voltage_mv(self) -> int: ...
    @property
    def calibrating(self) -> bool: ...
    @property
    def failsafe_active(self) -> bool: ...
    @property
    def flow_ok(self) -> bool: ...
    def global_position(self) -> tuple[float, float, float]: ...
    @property
    def gps_ok(self) -> bool: ...

    ground_amsl_m: float

    def height_above_ground_m(self) -> float: ...
    def home_global(self) -> tuple[float, float, float]: ...
    def home_local_ned(self) -> tuple[float, float, float]: ...
    def inertial_frd(self) -> tuple[imu.Vector3, imu.Vector3, imu.Vector3]: ...
    @property
    def landed(self) -> bool: ...
    @property
    def landed_state(self) -> int: ...
    def local_origin_global(self) -> tuple[float, float, float]: ...
    def mission_status(self) -> tuple[int, int, int, int]: ...
    @property
    def mode(self) -> FlightMode: ...
    def odometry_sample(self) -> tuple[float, float, float, float, float, float]: ...

    params: ParamStore

    def position_ned(self) -> list[float]: ...
    @property
    def position_ok(self) -> bool: ...
    def ready(self, now_s: float) -> bool: ...
    def reported_altitude_above_home_m(self) -> float: ...

    sysid: int

    def time_boot_ms(self, now_s: float) -> int: ...
    def time_usec(self, now_s: float) -> int: ...
    def true_global_position(self) -> tuple[float, float, float]: ...
    def truth_rates(self) -> tuple[float, float, float, list[float], list[float]]: ...
    def unix_time_us(self, now_s: float) -> int: ...
    def velocity_ned(self) -> list[float]: ...


class TelemetryBuilder:
    """Builds one vehicle's MAVLink messages from its current state.

    ``truth_fields`` chooses how HIL_STATE_QUATERNION is filled (see
    :class:`sitl.config.TruthStreamConfig`).
    """

    def __init__(self, autopilot: AutopilotView) -> None:
        self.ap = autopilot
        self.truth_fields: Literal["px4", "mavlink"] = "px4"
        self._builders = {
            MSG_HEARTBEAT: self.heartbeat,
            MSG_SYS_STATUS: self.sys_status,
            MSG_SYSTEM_TIME: self.system_time,
            MSG_GPS_RAW_INT: self.gps_raw_int,
            MSG_ATTITUDE: self.attitude,
            MSG_ATTITUDE_QUATERNION: self.attitude_quaternion,
            MSG_LOCAL_POSITION_NED: self.local_position_ned,
            MSG_GLOBAL_POSITION_INT: self.global_position_int,
            MSG_MISSION_CURRENT: self.mission_current,
            MSG_GPS_GLOBAL_ORIGIN: self.gps_global_origin,
            MSG_VFR_HUD: self.vfr_hud,
            MSG_ALTITUDE: self.altitude,
            MSG_BATTERY_STATUS: self.battery_status,
            MSG_AUTOPILOT_VERSION: self.autopilot_version,
            MSG_PROTOCOL_VERSION: self.protocol_version,
            MSG_HOME_POSITION: self.home_position,
            MSG_EXTENDED_SYS_STATE: self.extended_sys_state,
            MSG_HIL_STATE_QUATERNION: self.hil_state_quaternion,
            MSG_HIGHRES_IMU: self.highres_imu,
            MSG_SCALED_IMU: self.scaled_imu,
        }

    def build(self, msg_id: int, now_s: float) -> mavlink.MAVLink_message | None:
        """The message ``msg_id`` now, or None if the vehicle cannot produce it at the moment
        (e.g. LOCAL_POSITION_NED while the flow sensor has failed)."""
        builder = self._builders.get(msg_id)
        return None if builder is None else builder(now_s)

    # ------------------------------------------------------------- messages
    def heartbeat(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        if ap.calibrating and not ap.armed:
            state = MAV_STATE_CALIBRATING
        elif not ap.ready(now_s):
            state = MAV_STATE_BOOT
        elif ap.failsafe_active:
            state = MAV_STATE_CRITICAL
        elif ap.armed:
            state = MAV_STATE_ACTIVE
        else:
            state = MAV_STATE_STANDBY
        return mavlink.MAVLink_heartbeat_message(
            MAV_TYPE_QUADROTOR,
            MAV_AUTOPILOT_PX4,
            base_mode(ap.mode, ap.armed),
            ap.mode.custom_mode,
            state,
            3,
        )

    def sys_status(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        health = _SENSORS_PRESENT
        if not ap.flow_ok:
            health &= ~_FLOW
        if not ap.gps_ok:
            health &= ~_GPS
        if ap.ready(now_s) and ap.position_ok:
            health |= _PREARM
        voltage_mv, remaining = ap.battery_voltage_mv(), round(ap.battery_remaining_pct)
        return mavlink.MAVLink_sys_status_message(
            _SENSORS_PRESENT | _PREARM,
            _SENSORS_PRESENT | _PREARM,
            health,
            150,  # 15 % load
            voltage_mv,
            -1,
            remaining,
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def system_time(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        return mavlink.MAVLink_system_time_message(ap.unix_time_us(now_s), ap.time_boot_ms(now_s))

    def gps_raw_int(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        lat, lon, alt_m = ap.global_position()
        vn, ve, _ = ap.velocity_ned()
        speed = math.hypot(vn, ve)
        cog = round(math.degrees(math.atan2(ve, vn)) % 360.0 * 100) if speed > 0.2 else 65535
        fix, sats = (3, 12) if ap.gps_ok else (0, 0)
        return mavlink.MAVLink_gps_raw_int_message(
            ap.time_usec(now_s),
            fix,
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt_m * 1000),
            70,  # eph, cm
            100,  # epv, cm
            round(speed * 100),
            cog % 36000 if cog != 65535 else cog,
            sats,
        )

    def attitude(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        roll, pitch, yaw, yaw_rate = ap.attitude()
        return mavlink.MAVLink_attitude_message(
            ap.time_boot_ms(now_s), roll, pitch, yaw, 0.0, 0.0, yaw_rate
        )

    def attitude_quaternion(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        roll, pitch, yaw, yaw_rate = ap.attitude()
        w, x, y, z = euler_to_quaternion(roll, pitch, yaw)
        return mavlink.MAVLink_attitude_quaternion_message(
            ap.time_boot_ms(now_s), w, x, y, z, 0.0, 0.0, yaw_rate
        )

    def local_position_ned(self, now_s: float) -> mavlink.MAVLink_message | None:
        ap = self.ap
        if not ap.flow_ok:
            return None
        x, y, z, vx, vy, vz = ap.odometry_sample()
        return mavlink.MAVLink_local_position_ned_message(
            ap.time_boot_ms(now_s), x, y, z, vx, vy, vz
        )

    def global_position_int(self, now_s: float) -> mavlink.MAVLink_message | None:
        ap = self.ap
        if not ap.gps_ok:
            return None
        lat, lon, alt_m = ap.global_position()
        vn, ve, vd = ap.velocity_ned()
        _, _, yaw, _ = ap.attitude()
        return mavlink.MAVLink_global_position_int_message(
            ap.time_boot_ms(now_s),
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt_m * 1000),
            round(ap.reported_altitude_above_home_m() * 1000),
            _clamp_i16(vn * 100),
            _clamp_i16(ve * 100),
            _clamp_i16(vd * 100),
            round(math.degrees(yaw) % 360.0 * 100) % 36000,
        )

    def mission_current(self, now_s: float) -> mavlink.MAVLink_message:
        seq, total, state, mode = self.ap.mission_status()
        return mavlink.MAVLink_mission_current_message(seq, total, state, mode)

    def gps_global_origin(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        lat, lon, alt_m = ap.local_origin_global()
        return mavlink.MAVLink_gps_global_origin_message(
            round(lat * 1e7), round(lon * 1e7), round(alt_m * 1000), ap.time_usec(now_s)
        )

    def vfr_hud(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        vn, ve, vd = ap.velocity_ned()
        _, _, yaw, _ = ap.attitude()
        speed = math.hypot(vn, ve)
        throttle = 50 if ap.armed and not ap.landed else 0
        _, _, alt_m = ap.global_position()
        return mavlink.MAVLink_vfr_hud_message(
            speed, speed, round(math.degrees(yaw) % 360.0) % 360, throttle, alt_m, -vd
        )

    def altitude(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        _, _, alt_m = ap.global_position()
        rel = ap.reported_altitude_above_home_m()
        local_z = ap.odometry_sample()[2] if ap.flow_ok else math.nan
        return mavlink.MAVLink_altitude_message(
            ap.time_usec(now_s), alt_m, alt_m, -local_z, rel, math.nan, ap.height_above_ground_m()
        )

    def battery_status(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        cells = int(ap.params["BAT1_N_CELLS"])
        per_cell_mv = ap.battery_voltage_mv() // cells
        voltages = [per_cell_mv] * min(cells, 10) + [65535] * (10 - min(cells, 10))
        current_ca = 1500 if ap.armed else 50
        return mavlink.MAVLink_battery_status_message(
            0,
            1,  # MAV_BATTERY_FUNCTION_ALL
            3,  # MAV_BATTERY_TYPE_LIPO
            2500,  # 25 degC in cdegC
            voltages,
            current_ca,
            -1,
            -1,
            round(ap.battery_remaining_pct),
        )

    def autopilot_version(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        return mavlink.MAVLink_autopilot_version_message(
            CAPABILITIES,
            FLIGHT_SW_VERSION,
            FLIGHT_SW_VERSION,
            0,
            0,
            [0] * 8,
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x5349544C00000000 + ap.sysid,  # "SITL" + system id: unique per vehicle
            # PX4 SITL adds the instance (system id - 1) to the first byte of its GUID, which
            # is MAVSDK's info.hardware_uid.
            [(ap.sysid - 1) & 0xFF] + [0] * 17,
        )

    def protocol_version(self, now_s: float) -> mavlink.MAVLink_message:
        """As PX4's Mavlink::send_protocol_version on a MAVLink 2 link: speaks 2.0, accepts
        1.0 to 2.3. PX4 puts its MAVLink library's git hash in library_version_hash; there is
        no such library here, so both hashes are zero."""
        return MAVLinkProtocolVersionMessage(200, 100, 203)

    def home_position(self, now_s: float) -> mavlink.MAVLink_message:
        ap = self.ap
        lat, lon, alt_m = ap.home_global()
        x, y, z = ap.home_local_ned()
        return mavlink.MAVLink_home_position_message(
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt_m * 1000),
            x,
            y,
            z,
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            ap.time_usec(now_s),
        )

    def extended_sys_state(self, now_s: float) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_extended_sys_state_message(0, self.ap.landed_state)

    def highres_imu(self, now_s: float) -> mavlink.MAVLink_message:
        """IMU, magnetometer and barometer in SI units, body frame FRD, as PX4's HIGHRES_IMU
        stream fills it (the air temperature of PX4 SIH, no differential pressure)."""
        ap = self.ap
        (fx, fy, fz), (p, q, r), (mx, my, mz) = ap.inertial_frd()
        alt_m = ap.ground_amsl_m - ap.position_ned()[2]  # the barometer's true altitude
        return mavlink.MAVLink_highres_imu_message(
            ap.time_usec(now_s),
            fx,
            fy,
            fz,
            p,
            q,
            r,
            mx,
            my,
            mz,
            imu.static_pressure_hpa(alt_m),
            0.0,
            alt_m,
            _AIR_TEMPERATURE_DEGC,
            _HIGHRES_IMU_FIELDS,
        )

    def scaled_imu(self, now_s: float) -> mavlink.MAVLink_message:
        """The first IMU in MAVLink's integer units: mG, mrad/s, mgauss, cdegC (FRD)."""
        ap = self.ap
        (fx, fy, fz), (p, q, r), (mx, my, mz) = ap.inertial_frd()
        to_mg = 1000.0 / GRAVITY_M_S2
        return mavlink.MAVLink_scaled_imu_message(
            ap.time_boot_ms(now_s),
            _clamp_i16(fx * to_mg),
            _clamp_i16(fy * to_mg),
            _clamp_i16(fz * to_mg),
            _clamp_i16(p * 1000.0),
            _clamp_i16(q * 1000.0),
            _clamp_i16(r * 1000.0),
            _clamp_i16(mx * 1000.0),
            _clamp_i16(my * 1000.0),
            _clamp_i16(mz * 1000.0),
            round(_AIR_TEMPERATURE_DEGC * 100),
        )

    def hil_state_quaternion(self, now_s: float) -> mavlink.MAVLink_message:
        """The true state, as PX4's HIL_STATE_QUATERNION stream sends SIH's ground truth.

        PX4 (streams/HIL_STATE_QUATERNION.hpp) never sets time_usec, assigns the NED
        acceleration in m/s^2 to the mG fields and leaves the airspeeds 0; its float to integer
        conversions truncate towards zero. ``truth_fields = "mavlink"`` fills the fields as the
        message definition reads instead.
        """
        ap = self.ap
        roll, pitch, yaw, _ = ap.attitude()
        p, q, r, accel, wind = ap.truth_rates()
        lat, lon, alt_m = ap.true_global_position()
        vn, ve, vd = ap.velocity_ned()
        to_int: Callable[[float], int]
        if self.truth_fields == "px4":
            time_usec = 0
            to_int = math.trunc
            acc = [_clamp_i16(math.trunc(a)) for a in accel]
            airspeed = 0
        else:
            time_usec = ap.time_usec(now_s)
            to_int = round
            acc = [_clamp_i16(a / GRAVITY_M_S2 * 1000.0) for a in accel]
            air = math.sqrt((vn - wind[0]) ** 2 + (ve - wind[1]) ** 2 + (vd - wind[2]) ** 2)
            airspeed = min(round(air * 100), 65535)
        return mavlink.MAVLink_hil_state_quaternion_message(
            time_usec,
            list(euler_to_quaternion(roll, pitch, yaw)),
            p,
            q,
            r,
            to_int(lat * 1e7),
            to_int(lon * 1e7),
            to_int(alt_m * 1000),
            _clamp_i16(to_int(vn * 100)),
            _clamp_i16(to_int(ve * 100)),
            _clamp_i16(to_int(vd * 100)),
            airspeed,
            airspeed,
            *acc,
        )


def euler_to_quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the ZYX Euler angles in radians."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def quaternion_to_euler(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in radians of a unit quaternion."""
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def _clamp_i16(value: float) -> int:
    return max(-32768, min(32767, round(value)))
