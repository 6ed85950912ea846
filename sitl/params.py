"""PX4 parameters the emulated vehicles know, and the parameter store each vehicle keeps.

The table has two parts. ``_FLOWN`` holds the parameters that drive the emulator's behaviour:
speed and acceleration limits (MPC_*), take-off / RTL altitudes, failsafe timeouts and actions,
the stick modes (MPC_VEL_MANUAL, MPC_MAN_*, MAN_DEADZONE), orbit (MC_ORBIT_*), follow-me
(FLW_TGT_*) and failure injection (SYS_FAILURE_EN); their defaults follow PX4 v1.14/v1.15
multicopter defaults, and PX4 SITL's start script where it changes them (COM_RC_IN_MODE 1:
sticks from MAVLink MANUAL_CONTROL only; SYS_FAILURE_EN 1; COM_LOW_BAT_ACT 3).
``_REPORTED`` holds the ones clients read or set in their common workflows (QGroundControl's
setup pages, MAVSDK's plugins, MAVProxy), with PX4's types and ranges (from PX4's parameter
metadata) and the values PX4 SITL (SIH quadrotor) reports, stored and echoed only.

Ranges are PX4's where PX4 gives them; PX4 lists no bounds for some of the parameters the
emulator flies by, which it bounds itself (e.g. MIS_TAKEOFF_ALT <= 80 m). Unlike PX4, a value out
of range is refused (the vehicle answers with the value it keeps).

INT32 parameters travel in PARAM_VALUE's float field byte-wise, as PX4 does (capability
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): the four bytes of the int32 are read as a float32.
"""

from __future__ import annotations

import difflib
import math
import struct
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Literal

ParamType = Literal["INT32", "REAL32"]

#: MAV_PARAM_TYPE values used on the wire.
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One PX4 parameter: name, type, default and allowed range (inclusive)."""

    name: str
    type: ParamType
    default: float
    minimum: float
    maximum: float
    description: str

    @property
    def mav_type(self) -> int:
        return MAV_PARAM_TYPE_INT32 if self.type == "INT32" else MAV_PARAM_TYPE_REAL32

    def check(self, value: float) -> float:
        """Return ``value`` converted to this parameter's type, or raise ``ValueError``."""
        if not math.isfinite(value):
            raise ValueError(f"{self.name} must be finite, got {value!r}")
        if self.type == "INT32":
            if value != int(value):
                raise ValueError(f"{self.name} is an integer parameter, got {value!r}")
            value = int(value)
        if not self.minimum <= value <= self.maximum:
            raise ValueError(
                f"{self.name} must be within [{self.minimum:g}, {self.maximum:g}], got {value!r}"
            )
        return value


INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1
#: Largest float32: the range of a REAL32 parameter PX4 gives no bounds for.
FLT_MAX = 3.4028234663852886e38


def _p(  # noqa: PLR0917 - table rows read best positionally
    name: str, type_: ParamType, default: float, lo: float, hi: float, description: str
) -> ParamSpec:
    return ParamSpec(name, type_, default, lo, hi, description)


#: The parameters the emulator acts on: speed and acceleration limits, take-off and return
#: altitudes, failsafe timeouts and actions, the battery's cells, the system id.
_FLOWN: list[ParamSpec] = [
    _p("BAT1_N_CELLS", "INT32", 4, 1, 16, "Number of battery cells (telemetry only)"),
    _p(
        "COM_DISARM_LAND",
        "REAL32",
        2.0,
        -1.0,
        20.0,
        "Seconds on the ground after landing before auto-disarm; negative disables",
    ),
    _p(
        "COM_DISARM_PRFLT",
        "REAL32",
        10.0,
        -1.0,
        20.0,
        "Seconds armed on the ground without taking off before auto-disarm; negative disables",
    ),
    _p(
        "COM_DL_LOSS_T",
        "INT32",
        10,
        5,
        300,
        "Seconds without a GCS/API heartbeat before the data link counts as lost",
    ),
    _p("COM_FAIL_ACT_T", "REAL32", 5.0, 0.0, 25.0, "Failsafe hold before return or land, s"),
    _p("COM_LOW_BAT_ACT", "INT32", 3, 0, 3, "Empty battery: 0 warn only, 2 or 3 land"),
    _p(
        "COM_OBL_RC_ACT",
        "INT32",
        0,
        0,
        7,
        "Offboard loss action: 0-2,5 hold (no RC here), 3 return, 4 land, 6-7 disarm",
    ),
    _p(
        "COM_OF_LOSS_T",
        "REAL32",
        1.0,
        0.0,
        60.0,
        "Seconds without offboard setpoints before offboard counts as lost",
    ),
    _p("COM_RCL_EXCEPT", "INT32", 0, 0, 31, "RC loss ignored in: 1 mission, 2 auto, 4 offboard"),
    _p("COM_RC_IN_MODE", "INT32", 1, 0, 8, "Sticks: MANUAL_CONTROL unless 0 (RC only), 4 (none)"),
    _p("COM_RC_LOSS_T", "REAL32", 0.5, 0.0, 35.0, "Manual control loss timeout, s"),
    _p("FLW_TGT_ALT_M", "INT32", 0, 0, 2, "Follow-me height above: 0 home, 1 ground, 2 target"),
    _p("FLW_TGT_DST", "REAL32", 8.0, 1.0, 100.0, "Follow-me distance to the target, m"),
    _p("FLW_TGT_FA", "REAL32", 180.0, -180.0, 180.0, "Follow-me angle from the course, deg"),
    _p("FLW_TGT_HT", "REAL32", 8.0, 8.0, 100.0, "Follow-me height, m"),
    _p("FLW_TGT_MAX_VEL", "REAL32", 5.0, 0.0, 20.0, "Follow-me speed around the target, m/s"),
    _p("FLW_TGT_RS", "REAL32", 0.1, 0.0, 1.0, "Follow-me target smoothing (lower: faster)"),
    _p("MAN_DEADZONE", "REAL32", 0.1, 0.0, 1.0, "Stick deadzone, fraction of the travel"),
    _p("MAV_COMP_ID", "INT32", 1, 1, 250, "Autopilot component id"),
    _p("MAV_SYS_ID", "INT32", 1, 1, 250, "System id (set per vehicle, read only here)"),
    _p("MC_ORBIT_RAD_MAX", "REAL32", 1000.0, 1.0, 10000.0, "Largest orbit radius, m"),
    _p("MC_ORBIT_YAW_MOD", "INT32", 0, 0, 4, "Orbit yaw when not commanded (ORBIT_YAW_BEHAVIOUR)"),
    _p(
        "MIS_TAKEOFF_ALT",
        "REAL32",
        2.5,
        0.0,
        80.0,
        "Take-off altitude above home in metres (takeoff command and mission start)",
    ),
    _p("MPC_ACC_DOWN_MAX", "REAL32", 3.0, 2.0, 15.0, "Maximum downward accel, m/s^2"),
    _p(
        "MPC_ACC_HOR",
        "REAL32",
        3.0,
        2.0,
        15.0,
        "Horizontal acceleration limit in m/s^2 (offboard and auto modes)",
    ),
    _p("MPC_ACC_UP_MAX", "REAL32", 4.0, 2.0, 15.0, "Maximum upward accel, m/s^2"),
    _p("MPC_LAND_SPEED", "REAL32", 0.7, 0.6, 4.0, "Landing descent speed, m/s"),
    _p("MPC_MAN_TILT_MAX", "REAL32", 35.0, 1.0, 70.0, "Full-stick tilt in Altitude mode, deg"),
    _p("MPC_MAN_Y_MAX", "REAL32", 150.0, 0.0, 400.0, "Full-stick yaw rate, deg/s"),
    _p("MPC_TKO_SPEED", "REAL32", 1.5, 1.0, 5.0, "Take-off climb speed, m/s"),
    _p("MPC_VEL_MANUAL", "REAL32", 10.0, 3.0, 20.0, "Full-stick speed in Position mode, m/s"),
    _p(
        "MPC_XY_CRUISE",
        "REAL32",
        5.0,
        3.0,
        20.0,
        "Horizontal speed in auto modes (goto, mission, return), m/s",
    ),
    _p(
        "MPC_XY_VEL_MAX",
        "REAL32",
        12.0,
        0.0,
        20.0,
        "Horizontal speed limit in every mode, m/s",
    ),
    _p("MPC_YAWRAUTO_MAX", "REAL32", 45.0, 5.0, 360.0, "Yaw rate limit, deg/s"),
    _p("MPC_Z_VEL_MAX_DN", "REAL32", 1.5, 0.5, 4.0, "Descent speed limit, m/s"),
    _p("MPC_Z_VEL_MAX_UP", "REAL32", 3.0, 0.5, 8.0, "Climb speed limit, m/s"),
    _p(
        "NAV_ACC_RAD",
        "REAL32",
        10.0,
        0.05,
        200.0,
        "Mission waypoint acceptance radius when the item gives none, m",
    ),
    _p(
        "NAV_DLL_ACT",
        "INT32",
        0,
        0,
        6,
        "Data link loss action: 0 off, 1 hold, 2 return, 3 land, 5-6 disarm",
    ),
    _p("NAV_MC_ALT_RAD", "REAL32", 0.8, 0.05, 200.0, "Waypoint altitude acceptance, m"),
    _p("NAV_RCL_ACT", "INT32", 2, 1, 6, "Manual control loss: 1 hold, 2 return, 3 land, 6 disarm"),
    _p(
        "RTL_DESCEND_ALT",
        "REAL32",
        30.0,
        0.0,
        500.0,
        "Return: altitude above home to descend to before landing, m",
    ),
    _p(
        "RTL_LAND_DELAY",
        "REAL32",
        0.0,
        -1.0,
        300.0,
        "Return: seconds to hover above home before landing; negative hovers forever",
    ),
    _p(
        "RTL_RETURN_ALT",
        "REAL32",
        60.0,
        0.0,
        150.0,
        "Return: minimum altitude above home while flying back, m",
    ),
    _p("SYS_AUTOSTART", "INT32", 10040, 0, 9999999, "Airframe (10040: SIH quadrotor)"),
    _p("SYS_FAILURE_EN", "INT32", 1, 0, 1, "Accept MAV_CMD_INJECT_FAILURE (PX4 0, SITL 1)"),
]

#: Parameters PX4 SITL reports that ground stations and SDKs read or set in their common
#: workflows (QGroundControl's vehicle setup pages: sensors, power, safety, flight modes, radio;
#: MAVSDK's action, calibration and failure plugins; MAVProxy's parameter files). The emulator
#: stores and echoes them with PX4's names, types, ranges and PX4 SITL's values, and acts on
#: none of them.
_REPORTED: list[ParamSpec] = [
    _p("BAT1_CAPACITY", "REAL32", -1.0, -1.0, 100000.0, "Battery 1 capacity, mAh"),
    _p(
        "BAT1_R_INTERNAL",
        "REAL32",
        -1.0,
        -1.0,
        0.2,
        "Battery 1 internal resistance per cell (-1: estimated), Ohm",
    ),
    _p("BAT1_SOURCE", "INT32", 0, -1, 2, "Battery 1 monitoring source"),
    _p("BAT1_V_CHARGED", "REAL32", 4.05, -FLT_MAX, FLT_MAX, "Full cell voltage, V"),
    _p("BAT1_V_EMPTY", "REAL32", 3.6, -FLT_MAX, FLT_MAX, "Empty cell voltage, V"),
    _p("BAT_AVRG_CURRENT", "REAL32", 15.0, 0.0, 500.0, "Expected battery current in flight, A"),
    _p("BAT_CRIT_THR", "REAL32", 0.07, 0.05, 0.5, "Critical threshold, norm"),
    _p("BAT_EMERGEN_THR", "REAL32", 0.05, 0.03, 0.5, "Emergency threshold, norm"),
    _p("BAT_LOW_THR", "REAL32", 0.15, 0.12, 0.5, "Low threshold, norm"),
    _p(
        "CAL_ACC0_ID",
        "INT32",
        1310988,
        INT32_MIN,
        INT32_MAX,
        "Accelerometer 0 calibration device ID",
    ),
    _p("CAL_ACC0_PRIO", "INT32", -1, -1, 100, "Accelerometer 0 priority"),
    _p("CAL_ACC0_ROT", "INT32", -1, -1, 40, "Accelerometer 0 rotation relative to airframe"),
    _p("CAL_ACC0_XOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Accelerometer 0 X-axis offset, m/s^2"),
    _p("CAL_ACC0_XSCALE", "REAL32", 1.0, 0.1, 3.0, "Accelerometer 0 X-axis scaling factor"),
    _p("CAL_ACC0_YOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Accelerometer 0 Y-axis offset, m/s^2"),
    _p("CAL_ACC0_YSCALE", "REAL32", 1.0, 0.1, 3.0, "Accelerometer 0 Y-axis scaling factor"),
    _p("CAL_ACC0_ZOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Accelerometer 0 Z-axis offset, m/s^2"),
    _p("CAL_ACC0_ZSCALE", "REAL32", 1.0, 0.1, 3.0, "Accelerometer 0 Z-axis scaling factor"),
    _p("CAL_BARO0_ID", "INT32", 6620172, INT32_MIN, INT32_MAX, "Barometer 0 calibration device ID"),
    _p("CAL_BARO0_OFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Barometer 0 offset"),
    _p("CAL_BARO0_PRIO", "INT32", 50, -1, 100, "Barometer 0 priority"),
    _p("CAL_GYRO0_ID", "INT32", 1310988, INT32_MIN, INT32_MAX, "Gyroscope 0 calibration device ID"),
    _p("CAL_GYRO0_PRIO", "INT32", -1, -1, 100, "Gyroscope 0 priority"),
    _p("CAL_GYRO0_ROT", "INT32", -1, -1, 40, "Gyroscope 0 rotation relative to airframe"),
    _p("CAL_GYRO0_XOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Gyroscope 0 X-axis offset, rad/s"),
    _p("CAL_GYRO0_YOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Gyroscope 0 Y-axis offset, rad/s"),
    _p("CAL_GYRO0_ZOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Gyroscope 0 Z-axis offset, rad/s"),
    _p(
        "CAL_MAG0_ID", "INT32", 197388, INT32_MIN, INT32_MAX, "Magnetometer 0 calibration device ID"
    ),
    _p("CAL_MAG0_PRIO", "INT32", 50, -1, 100, "Magnetometer 0 priority"),
    _p("CAL_MAG0_ROT", "INT32", -1, -1, 100, "Magnetometer 0 rotation relative to airframe"),
    _p("CAL_MAG0_XOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Magnetometer 0 X-axis offset, gauss"),
    _p("CAL_MAG0_XSCALE", "REAL32", 1.0, 0.1, 3.0, "Magnetometer 0 X-axis scaling factor"),
    _p("CAL_MAG0_YOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Magnetometer 0 Y-axis offset, gauss"),
    _p("CAL_MAG0_YSCALE", "REAL32", 1.0, 0.1, 3.0, "Magnetometer 0 Y-axis scaling factor"),
    _p("CAL_MAG0_ZOFF", "REAL32", 0.0, -FLT_MAX, FLT_MAX, "Magnetometer 0 Z-axis offset, gauss"),
    _p("CAL_MAG0_ZSCALE", "REAL32", 1.0, 0.1, 3.0, "Magnetometer 0 Z-axis scaling factor"),
    _p(
        "CAL_MAG_SIDES",
        "INT32",
        63,
        INT32_MIN,
        INT32_MAX,
        "Magnetometer calibration sides (kept for QGroundControl)",
    ),
    _p(
        "CBRK_FLIGHTTERM",
        "INT32",
        121212,
        0,
        121212,
        "Circuit breaker for flight termination (121212: disabled)",
    ),
    _p("CBRK_IO_SAFETY", "INT32", 22027, 0, 22027, "Circuit breaker for IO safety"),
    _p("CBRK_SUPPLY_CHK", "INT32", 0, 0, 894281, "Circuit breaker for power supply check"),
    _p("CBRK_USB_CHK", "INT32", 197848, 0, 197848, "Circuit breaker for USB link check"),
    _p("COM_ACT_FAIL_ACT", "INT32", 0, 0, 3, "Set the actuator failure failsafe mode"),
    _p("COM_ARM_AUTH_REQ", "INT32", 0, 0, 1, "Require arm authorization to arm"),
    _p("COM_ARM_BAT_MIN", "REAL32", -1.0, -1.0, 0.9, "Minimum battery level for arming, norm"),
    _p("COM_ARM_CHK_ESCS", "INT32", 0, 0, 1, "Enable checks on ESCs that report telemetry"),
    _p(
        "COM_ARM_IMU_ACC",
        "REAL32",
        0.7,
        0.1,
        1.0,
        "Accelerometer inconsistency between IMUs that still allows arming, m/s^2",
    ),
    _p(
        "COM_ARM_IMU_GYR",
        "REAL32",
        0.25,
        0.02,
        0.3,
        "Gyro inconsistency between IMUs that still allows arming, rad/s",
    ),
    _p(
        "COM_ARM_MAG_ANG",
        "INT32",
        60,
        3,
        180,
        "Magnetometer inconsistency that still allows arming, deg",
    ),
    _p("COM_ARM_MAG_STR", "INT32", 2, 0, 2, "Enable mag strength preflight check"),
    _p("COM_ARM_SDCARD", "INT32", 1, 0, 2, "Enable FMU SD card detection check"),
    _p("COM_ARM_SWISBTN", "INT32", 0, 0, 1, "Arm switch is a momentary button"),
    _p("COM_ARM_WO_GPS", "INT32", 1, 0, 2, "Arming without GPS: 0 deny, 1 warn, 2 allow"),
    _p("COM_CPU_MAX", "REAL32", -1.0, -1.0, 100.0, "Maximum allowed CPU load to still arm, %"),
    _p("COM_FLTMODE1", "INT32", -1, -1, 107, "Mode slot 1"),
    _p("COM_FLTMODE2", "INT32", -1, -1, 107, "Mode slot 2"),
    _p("COM_FLTMODE3", "INT32", -1, -1, 107, "Mode slot 3"),
    _p("COM_FLTMODE4", "INT32", -1, -1, 107, "Mode slot 4"),
    _p("COM_FLTMODE5", "INT32", -1, -1, 107, "Mode slot 5"),
    _p("COM_FLTMODE6", "INT32", -1, -1, 107, "Mode slot 6"),
    _p("COM_FLTT_LOW_ACT", "INT32", 0, 0, 3, "Remaining flight time low failsafe"),
    _p("COM_FLT_TIME_MAX", "INT32", -1, -1, INT32_MAX, "Maximum allowed flight time, s"),
    _p("COM_HOME_EN", "INT32", 1, 0, 1, "Home position enabled"),
    _p("COM_HOME_IN_AIR", "INT32", 0, 0, 1, "Allows setting the home position after takeoff"),
    _p(
        "COM_KILL_DISARM",
        "REAL32",
        5.0,
        0.0,
        30.0,
        "Disarm timeout while the kill switch is engaged, s",
    ),
    _p(
        "COM_LKDOWN_TKO",
        "REAL32",
        3.0,
        -1.0,
        5.0,
        "Timeout for detecting a failure after takeoff, s",
    ),
    _p(
        "COM_POS_LOW_EPH",
        "REAL32",
        -1.0,
        -1.0,
        1000.0,
        "Low position accuracy failsafe threshold, m",
    ),
    _p("COM_PREARM_MODE", "INT32", 0, 0, 2, "Condition to enter prearmed mode"),
    _p("COM_RAM_MAX", "REAL32", -1.0, -1.0, 100.0, "Maximum allowed RAM usage to pass checks, %"),
    _p("COM_RC_OVERRIDE", "INT32", 1, 0, 3, "Enable manual control stick override"),
    _p("COM_RC_STICK_OV", "REAL32", 30.0, 5.0, 80.0, "Stick override threshold, %"),
    _p("COM_SPOOLUP_TIME", "REAL32", 1.0, 0.0, 30.0, "Delay between arming and navigation, s"),
    _p("COM_TAKEOFF_ACT", "INT32", 0, 0, 1, "Action after TAKEOFF has been accepted"),
    _p("COM_VEL_FS_EVH", "REAL32", 1.0, 0.0, FLT_MAX, "Horizontal velocity error threshold, m/s"),
    _p("COM_WIND_MAX", "REAL32", -1.0, -1.0, FLT_MAX, "High wind speed failsafe threshold, m/s"),
    _p("COM_WIND_MAX_ACT", "INT32", 0, 0, 5, "High wind failsafe mode"),
    _p("COM_WIND_WARN", "REAL32", -1.0, -1.0, FLT_MAX, "Wind speed warning threshold, m/s"),
    _p("EKF2_BARO_CTRL", "INT32", 1, 0, 1, "Barometric sensor height aiding"),
    _p("EKF2_EN", "INT32", 1, 0, 1, "EKF2 enabled"),
    _p("EKF2_EV_CTRL", "INT32", 0, 0, 15, "External vision (EV) sensor aiding"),
    _p("EKF2_GPS_CTRL", "INT32", 7, 0, 15, "GNSS sensor aiding"),
    _p("EKF2_HGT_REF", "INT32", 1, 0, 3, "Height reference: 0 baro, 1 GPS, 2 range, 3 vision"),
    _p("EKF2_IMU_CTRL", "INT32", 7, 0, 7, "IMU control"),
    _p("EKF2_MAG_TYPE", "INT32", 0, 0, 6, "Type of magnetometer fusion"),
    _p("EKF2_OF_CTRL", "INT32", 1, 0, 1, "Optical flow aiding"),
    _p("EKF2_REQ_GPS_H", "REAL32", 0.5, 0.1, FLT_MAX, "Required GPS health time at start-up, s"),
    _p("EKF2_RNG_CTRL", "INT32", 1, 0, 2, "Range sensor height aiding"),
    _p("GF_ACTION", "INT32", 2, 0, 5, "Geofence violation action"),
    _p("GF_MAX_HOR_DIST", "REAL32", 0.0, 0.0, 10000.0, "Max horizontal distance from Home, m"),
    _p("GF_MAX_VER_DIST", "REAL32", 0.0, 0.0, 10000.0, "Max vertical distance from Home, m"),
    _p("GF_PREDICT", "INT32", 0, 0, 1, "Pre-emptive geofence triggering (experimental)"),
    _p("GF_SOURCE", "INT32", 0, 0, 1, "Geofence source"),
    _p("MAV_FWDEXTSP", "INT32", 1, 0, 1, "Forward external setpoint messages"),
    _p("MAV_HASH_CHK_EN", "INT32", 1, 0, 1, "Parameter hash check"),
    _p("MAV_HB_FORW_EN", "INT32", 1, 0, 1, "Heartbeat message forwarding"),
    _p("MAV_PROTO_VER", "INT32", 2, 1, 2, "MAVLink protocol version"),
    _p("MAV_RADIO_TOUT", "INT32", 5, 1, 250, "Timeout of RADIO_STATUS reports, s"),
    _p("MAV_TYPE", "INT32", 2, 0, 22, "MAVLink airframe type"),
    _p("MIS_MNT_YAW_CTL", "INT32", 0, 0, 1, "Yaw control of the mount (multicopters, ROI items)"),
    _p(
        "MIS_YAW_ERR",
        "REAL32",
        12.0,
        0.0,
        90.0,
        "Yaw error accepted as the heading at a waypoint, deg",
    ),
    _p(
        "MIS_YAW_TMT",
        "REAL32",
        -1.0,
        -1.0,
        20.0,
        "Time to wait for the waypoint heading if it is forced, s",
    ),
    _p("MNT_MODE_IN", "INT32", -1, -1, 4, "Mount input mode"),
    _p("MPC_ACC_HOR_MAX", "REAL32", 5.0, 2.0, 15.0, "Maximum horizontal acceleration, m/s^2"),
    _p("MPC_ALT_MODE", "INT32", 2, 0, 2, "Altitude reference mode"),
    _p("MPC_JERK_AUTO", "REAL32", 4.0, 1.0, 80.0, "Jerk limit in autonomous modes, m/s^3"),
    _p("MPC_JERK_MAX", "REAL32", 8.0, 0.5, 500.0, "Jerk limit in Position/Altitude mode, m/s^3"),
    _p(
        "MPC_LAND_ALT1",
        "REAL32",
        10.0,
        0.0,
        122.0,
        "Altitude where slow landing's first step (descend) starts, m",
    ),
    _p(
        "MPC_LAND_ALT2",
        "REAL32",
        5.0,
        0.0,
        122.0,
        "Altitude where slow landing's second step (landing speed) starts, m",
    ),
    _p(
        "MPC_LAND_ALT3",
        "REAL32",
        1.0,
        0.0,
        122.0,
        "Altitude where slow landing's third step starts, m",
    ),
    _p("MPC_POS_MODE", "INT32", 4, 0, 4, "Position/Altitude mode variant"),
    _p("MPC_THR_HOVER", "REAL32", 0.5, 0.1, 0.8, "Vertical thrust required to hover, norm"),
    _p(
        "MPC_THR_MAX",
        "REAL32",
        1.0,
        0.0,
        1.0,
        "Maximum collective thrust in climb rate controlled modes, norm",
    ),
    _p(
        "MPC_THR_MIN",
        "REAL32",
        0.12,
        0.05,
        0.5,
        "Minimum collective thrust in climb rate controlled modes, norm",
    ),
    _p("MPC_TILTMAX_AIR", "REAL32", 45.0, 20.0, 89.0, "Maximum tilt angle in air, deg"),
    _p("MPC_TILTMAX_LND", "REAL32", 12.0, 5.0, 89.0, "Tilt limit during the take-off ramp, deg"),
    _p("MPC_TKO_RAMP_T", "REAL32", 3.0, 0.0, 5.0, "Smooth takeoff ramp time constant, s"),
    _p("MPC_XY_P", "REAL32", 0.95, 0.0, 2.0, "Proportional gain for horizontal position error"),
    _p(
        "MPC_XY_TRAJ_P",
        "REAL32",
        0.5,
        0.1,
        1.0,
        "Proportional gain for the horizontal trajectory position error",
    ),
    _p(
        "MPC_XY_VEL_P_ACC",
        "REAL32",
        1.8,
        1.2,
        5.0,
        "Proportional gain for horizontal velocity error",
    ),
    _p(
        "MPC_YAWRAUTO_ACC",
        "REAL32",
        20.0,
        5.0,
        360.0,
        "Maximum yaw acceleration in autonomous modes, deg/s^2",
    ),
    _p("MPC_YAW_MODE", "INT32", 0, 0, 4, "Heading behavior in autonomous modes"),
    _p("MPC_Z_P", "REAL32", 1.0, 0.1, 1.5, "Proportional gain for vertical position error"),
    _p(
        "MPC_Z_VEL_P_ACC", "REAL32", 4.0, 2.0, 15.0, "Proportional gain for vertical velocity error"
    ),
    _p("MPC_Z_V_AUTO_DN", "REAL32", 1.5, 0.5, 4.0, "Descent velocity in autonomous modes, m/s"),
    _p("MPC_Z_V_AUTO_UP", "REAL32", 3.0, 0.5, 8.0, "Ascent velocity in autonomous modes, m/s"),
    _p(
        "NAV_MIN_GND_DIST",
        "REAL32",
        -1.0,
        -1.0,
        FLT_MAX,
        "Minimum height above ground in Mission and RTL, m",
    ),
    _p("NAV_MIN_LTR_ALT", "REAL32", -1.0, -1.0, FLT_MAX, "Minimum Loiter altitude, m"),
    _p("NAV_TRAFF_AVOID", "INT32", 1, 0, 4, "Set traffic avoidance mode"),
    _p("RC_CHAN_CNT", "INT32", 0, 0, 18, "RC channel count"),
    _p("RC_MAP_ARM_SW", "INT32", 0, 0, 18, "Arm switch channel"),
    _p("RC_MAP_FLTMODE", "INT32", 0, 0, 18, "Single channel flight mode selection"),
    _p("RC_MAP_KILL_SW", "INT32", 0, 0, 18, "Emergency Kill switch channel"),
    _p("RC_MAP_LOITER_SW", "INT32", 0, 0, 18, "Loiter switch channel"),
    _p("RC_MAP_OFFB_SW", "INT32", 0, 0, 18, "Offboard switch channel"),
    _p("RC_MAP_PITCH", "INT32", 0, 0, 18, "Pitch control channel mapping"),
    _p("RC_MAP_RETURN_SW", "INT32", 0, 0, 18, "Return switch channel"),
    _p("RC_MAP_ROLL", "INT32", 0, 0, 18, "Roll control channel mapping"),
    _p("RC_MAP_THROTTLE", "INT32", 0, 0, 18, "Throttle control channel mapping"),
    _p("RC_MAP_YAW", "INT32", 0, 0, 18, "Yaw control channel mapping"),
    _p("RTL_CONE_ANG", "INT32", 45, 0, 90, "Half-angle of the return mode altitude cone, deg"),
    _p("RTL_LOITER_RAD", "REAL32", 80.0, 25.0, FLT_MAX, "Loiter radius of the return descent, m"),
    _p(
        "RTL_MIN_DIST",
        "REAL32",
        10.0,
        0.5,
        FLT_MAX,
        "Radius around the return point with special return rules, m",
    ),
    _p("RTL_PLD_MD", "INT32", 0, 0, 2, "RTL precision land mode"),
    _p("RTL_TIME_FACTOR", "REAL32", 1.1, 1.0, 2.0, "RTL time estimate safety margin factor"),
    _p("RTL_TIME_MARGIN", "INT32", 100, 0, 3600, "RTL time estimate safety margin offset, s"),
    _p("RTL_TYPE", "INT32", 0, 0, 5, "Return type"),
    _p("SDLOG_BACKEND", "INT32", 3, 0, 3, "Logging backend (bitmask: 1 SD card, 2 MAVLink)"),
    _p("SDLOG_BOOT_BAT", "INT32", 0, 0, 1, "Battery-only Logging"),
    _p("SDLOG_DIRS_MAX", "INT32", 7, 0, 1000, "Maximum number of log directories to keep"),
    _p("SDLOG_MISSION", "INT32", 0, 0, 2, "Mission Log"),
    _p("SDLOG_MODE", "INT32", 1, 0, 4, "Logging Mode (PX4 SITL: 1, from boot)"),
    _p("SDLOG_PROFILE", "INT32", 131, 0, 4095, "Logged topic profile (bitmask)"),
    _p("SDLOG_UTC_OFFSET", "INT32", 0, -1000, 1000, "UTC offset of log file names, min"),
    _p("SDLOG_UUID", "INT32", 1, 0, 1, "Log UUID"),
    _p("SENS_BOARD_ROT", "INT32", 0, -1, 40, "Board rotation"),
    _p("SENS_BOARD_X_OFF", "REAL32", 0.0, -45.0, 45.0, "Board rotation X (roll) offset, deg"),
    _p("SENS_BOARD_Y_OFF", "REAL32", 0.0, -45.0, 45.0, "Board rotation Y (pitch) offset, deg"),
    _p("SENS_BOARD_Z_OFF", "REAL32", 0.0, -45.0, 45.0, "Board rotation Z (yaw) offset, deg"),
    _p("SYS_HAS_BARO", "INT32", 1, 0, 1, "Control if the vehicle has a barometer"),
    _p("SYS_HAS_GPS", "INT32", 1, 0, 1, "Control if the vehicle has a GPS"),
    _p("SYS_HAS_MAG", "INT32", 1, INT32_MIN, INT32_MAX, "Number of magnetometers expected"),
    _p("SYS_HAS_NUM_ASPD", "INT32", 0, 0, 1, "Control if the vehicle has an airspeed sensor"),
    _p("SYS_HAS_NUM_DIST", "INT32", 0, 0, 4, "Number of distance sensors expected"),
    _p("SYS_HITL", "INT32", 0, -1, 2, "HITL/SIH mode on next boot"),
    _p("SYS_PARAM_VER", "INT32", 1, 0, INT32_MAX, "Parameter version"),
    _p(
        "SYS_VEHICLE_RESP",
        "REAL32",
        -0.4,
        -1.0,
        1.0,
        "Responsiveness (-1 to 1; negative: use the individual parameters)",
    ),
    _p("TRIG_INTERFACE", "INT32", 3, 1, 4, "Camera trigger interface"),
    _p("TRIG_MODE", "INT32", 0, 0, 4, "Camera trigger mode"),
]

# Sorted by name, as PX4 sorts its parameters, so that PARAM_REQUEST_LIST indices are stable.
PARAM_TABLE: Mapping[str, ParamSpec] = {
    spec.name: spec for spec in sorted(_FLOWN + _REPORTED, key=lambda spec: spec.name)
}

PARAM_NAMES: tuple[str, ...] = tuple(PARAM_TABLE)
_INDEX: Mapping[str, int] = {name: i for i, name in enumerate(PARAM_NAMES)}


def int32_to_wire_float(value: int) -> float:
    """Encode an int32 byte-wise into a float32, as PX4 does in PARAM_VALUE/PARAM_SET."""
    (encoded,) = struct.unpack("<f", struct.pack("<i", int(value)))
    return float(encoded)


def wire_float_to_int32(value: float) -> int:
    """Decode a byte-wise encoded int32 from the float field of PARAM_SET/PARAM_VALUE."""
    (decoded,) = struct.unpack("<i", struct.pack("<f", value))
    return int(decoded)


def validate_overrides(overrides: Mapping[str, float]) -> dict[str, float]:
    """Check parameter overrides from a configuration; raise ``ValueError`` naming the problem."""
    checked: dict[str, float] = {}
    for name, value in overrides.items():
        spec = PARAM_TABLE.get(name)
        if spec is None:
            close = difflib.get_close_matches(name, PARAM_NAMES, n=3)
            hint = f"did you mean {' or '.join(close)}? " if close else ""
            raise ValueError(
                f"unknown parameter {name!r}; {hint}the {len(PARAM_NAMES)} known ones are in "
                "sitl/params.py"
            )
        checked[name] = spec.check(float(value))
    return checked


class ParamStore:
    """The parameter values of one vehicle.

    ``on_change(name, value)`` is called after every successful :meth:`set`, so the vehicle can
    update limits that live elsewhere (e.g. physics arrays).
    """

    def __init__(
        self,
        overrides: Mapping[str, float] | None = None,
        on_change: Callable[[str, float], None] | None = None,
    ) -> None:
        self._values: dict[str, float] = {name: spec.default for name, spec in PARAM_TABLE.items()}
        self._values.update(validate_overrides(overrides or {}))
        self._on_change = on_change

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __contains__(self, name: object) -> bool:
        return name in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(PARAM_NAMES)

    def __len__(self) -> int:
        return len(PARAM_NAMES)

    def set(self, name: str, value: float) -> float:
        """Set a parameter (``ValueError`` if unknown or out of range); returns the stored value."""
        spec = PARAM_TABLE.get(name)
        if spec is None:
            raise ValueError(f"unknown parameter {name!r}")
        stored = spec.check(value)
        self._values[name] = stored
        if self._on_change is not None:
            self._on_change(name, stored)
        return stored

    def set_silently(self, name: str, value: float) -> None:
        """Set a read-only-to-clients value (e.g. MAV_SYS_ID) without notification."""
        self._values[name] = PARAM_TABLE[name].check(value)

    def index_of(self, name: str) -> int:
        return _INDEX[name]

    def wire_value(self, name: str) -> tuple[float, int]:
        """``(param_value, param_type)`` as they go into PARAM_VALUE."""
        spec = PARAM_TABLE[name]
        value = self._values[name]
        if spec.type == "INT32":
            return int32_to_wire_float(int(value)), MAV_PARAM_TYPE_INT32
        return float(value), MAV_PARAM_TYPE_REAL32

    def decode_wire_value(self, name: str, param_value: float, param_type: int) -> float:
        """Interpret PARAM_SET's float for ``name``: byte-wise for INT32 parameters."""
        spec = PARAM_TABLE[name]
        if spec.type == "INT32":
            if param_type == MAV_PARAM_TYPE_REAL32:
                # A client that sends an INT32 as a plain float (not byte-wise) still means it.
                return float(param_value)
            return float(wire_float_to_int32(param_value))
        return float(param_value)


#: ArduPilot's packed parameter file (``@PARAM/param.pck`` over MAVLink FTP): magic, with
#: defaults, and the type codes of its entries.
PARAM_PCK_MAGIC = 0x671B
PARAM_PCK_MAGIC_WITH_DEFAULTS = 0x671C
_PCK_INT32 = 3
_PCK_FLOAT = 4
_PCK_HAS_DEFAULT = 0x10


def pack_param_pck(store: ParamStore, *, with_defaults: bool = False) -> bytes:
    """The parameters in ArduPilot's ``param.pck`` layout, which MAVProxy and QGroundControl
    download over FTP from ArduPilot (PX4 has no such file).

    Header ``<HHH``: magic, count, total count. Then per parameter in name order: a type byte
    (3 int32, 4 float; 0x10 set when a default follows), a byte with the length of the name
    part minus 1 (high nibble) and the length of the prefix shared with the previous name (low
    nibble), that name part, the value, and the default if it differs from the value.
    """
    out = bytearray(
        struct.pack(
            "<HHH",
            PARAM_PCK_MAGIC_WITH_DEFAULTS if with_defaults else PARAM_PCK_MAGIC,
            len(store),
            len(store),
        )
    )
    previous = b""
    for name in store:
        spec = PARAM_TABLE[name]
        raw = name.encode()
        common = 0
        limit = min(len(raw) - 1, len(previous), 15)
        while common < limit and raw[common] == previous[common]:
            common += 1
        suffix = raw[common:]
        value, default = store[name], spec.default
        kind, code = ("<i", _PCK_INT32) if spec.type == "INT32" else ("<f", _PCK_FLOAT)
        differs = with_defaults and value != default
        out.append(code | (_PCK_HAS_DEFAULT if differs else 0))
        out.append(((len(suffix) - 1) << 4) | common)
        out += suffix
        out += struct.pack(kind, int(value) if spec.type == "INT32" else value)
        if differs:
            out += struct.pack(kind, int(default) if spec.type == "INT32" else default)
        previous = raw
    return bytes(out)
