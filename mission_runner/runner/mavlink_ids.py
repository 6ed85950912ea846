"""The MAVLink numbers a vehicle's link uses (common dialect), as literals.

``pymavlink``'s common dialect module builds a class for every message and an entry for every
enum value at import: about 20 ms of a vehicle process's start (``python -X importtime``), for
the few dozen numbers below. ``tests/runner/test_mavlink_ids.py`` checks each against
pymavlink's; :func:`result_name` imports it only to name a refused command.
"""

from __future__ import annotations

# Streams (message ids)
MAVLINK_MSG_ID_ATTITUDE = 30
MAVLINK_MSG_ID_ATTITUDE_QUATERNION = 31
MAVLINK_MSG_ID_HIGHRES_IMU = 105
MAVLINK_MSG_ID_GLOBAL_POSITION_INT = 33
MAVLINK_MSG_ID_ODOMETRY = 331
MAVLINK_MSG_ID_RC_CHANNELS = 65
MAVLINK_MSG_ID_ALTITUDE = 141
MAVLINK_MSG_ID_ATTITUDE_TARGET = 83
MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED = 85
MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT = 87
MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT = 62
MAVLINK_MSG_ID_VFR_HUD = 74
MAVLINK_MSG_ID_SERVO_OUTPUT_RAW = 36
MAVLINK_MSG_ID_WIND_COV = 231
MAVLINK_MSG_ID_DISTANCE_SENSOR = 132
MAVLINK_MSG_ID_GPS_RAW_INT = 24
MAVLINK_MSG_ID_SYSTEM_TIME = 2

# Commands, results, modes, frames
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_DO_SET_MODE = 176
MAV_RESULT_ACCEPTED = 0
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_FRAME_LOCAL_NED = 1
MAV_COMP_ID_MISSIONPLANNER = 190

# SET_POSITION_TARGET_LOCAL_NED type_mask bits
POSITION_TARGET_TYPEMASK_X_IGNORE = 1
POSITION_TARGET_TYPEMASK_Y_IGNORE = 2
POSITION_TARGET_TYPEMASK_Z_IGNORE = 4
POSITION_TARGET_TYPEMASK_AX_IGNORE = 64
POSITION_TARGET_TYPEMASK_AY_IGNORE = 128
POSITION_TARGET_TYPEMASK_AZ_IGNORE = 256
POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE = 2048


def result_name(result: int) -> str:
    """MAV_RESULT ``result``'s name (``DENIED``...), or the number if it has none."""
    from pymavlink.dialects.v20 import common  # noqa: PLC0415 - only for a refusal's words

    entry = common.enums["MAV_RESULT"].get(result)
    return str(entry.name) if entry is not None else str(result)
