"""Offboard control of one vehicle: the setpoints a client streams, and whether they still come.

The MAVLink receiver (:mod:`sitl.mavlink_receiver`) hands SET_POSITION_TARGET_LOCAL_NED,
SET_POSITION_TARGET_GLOBAL_INT and SET_ATTITUDE_TARGET to :class:`Offboard`, which checks and
converts each to one world-frame setpoint (position, velocity or acceleration) and, while the
vehicle is armed in OFFBOARD, writes it into the vehicle's physics row. As in PX4, setpoints are
kept in every mode: a client streams first, then asks for OFFBOARD. The commander
(:mod:`sitl.commander`) asks :meth:`Offboard.signal_fresh` before it arms or switches to
OFFBOARD, and fails safe when the stream has been quiet for COM_OF_LOSS_T.

Implausible setpoints (non-finite, absurd magnitudes, unsupported frames) are counted in
``rejected_setpoints`` and otherwise ignored, as PX4 does.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from pymavlink.dialects.v20 import common as mavlink

from sitl import physics as ph
from sitl.modes import FlightMode
from sitl.telemetry import quaternion_to_euler
from sitl.vehicle_state import Link, VehicleContext

# SET_POSITION_TARGET_*.type_mask: a vector is ignored when any of its bits is set.
_IGNORE_POS = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
)
_IGNORE_VEL = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
)
_IGNORE_ACC = (
    mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
)

_LOCAL_FRAMES = frozenset(
    [
        mavlink.MAV_FRAME_LOCAL_NED,
        mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
        mavlink.MAV_FRAME_BODY_NED,
        mavlink.MAV_FRAME_BODY_OFFSET_NED,
    ]
)
_BODY_FRAMES = frozenset([mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED])
_GLOBAL_FRAMES = frozenset(
    [
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_INT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    ]
)
# Flat ground: terrain altitude is altitude above home.
_GLOBAL_RELATIVE_FRAMES = frozenset(
    [
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    ]
)

_MAX_POSITION_M = 1e6
_MAX_SPEED_M_S = 100.0
_MAX_ACCEL_M_S2 = 100.0
_HOVER_THRUST = 0.5
_MAX_TILT_RAD = 0.8

SetpointKind = Literal["velocity", "position", "acceleration"]


@dataclass(slots=True)
class OffboardSetpoint:
    """The latest accepted setpoint, world NED: a position (m, with an optional velocity
    feed-forward in m/s), a velocity (m/s) or an acceleration (m/s^2). NaN yaw or yaw rate
    means none was given."""

    kind: SetpointKind
    vector_ned: list[float]
    feedforward_ned_m_s: list[float] | None
    yaw_rad: float
    yaw_rate_rad_s: float


class Offboard:
    """The offboard setpoint stream of one vehicle (PX4: MAVLink receiver -> trajectory
    setpoint, and the commander's offboard-signal check)."""

    def __init__(self, vehicle: VehicleContext) -> None:
        self._vehicle = vehicle
        self._setpoint: OffboardSetpoint | None = None
        self._last_setpoint_s = -math.inf
        self.rejected_setpoints = 0
        self.accepted_setpoints = 0
        #: Called (synchronously, no arguments) after every setpoint taken.
        self.setpoint_listeners: list[Callable[[], None]] = []

    @property
    def setpoint(self) -> OffboardSetpoint | None:
        """The latest accepted setpoint, as the vehicle took it (None before the first)."""
        return self._setpoint

    # ------------------------------------------------------------- messages in
    def on_position_target_local(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        vehicle = self._vehicle
        if not vehicle.is_for_me(msg):
            return
        mask = msg.type_mask
        frame = msg.coordinate_frame
        if frame not in _LOCAL_FRAMES:
            self.rejected_setpoints += 1
            return
        use_pos = not mask & _IGNORE_POS
        use_vel = not mask & _IGNORE_VEL
        use_acc = not mask & _IGNORE_ACC
        pos = [msg.x, msg.y, msg.z]
        vel = [msg.vx, msg.vy, msg.vz]
        acc = [msg.afx, msg.afy, msg.afz]
        if not _valid_vectors(
            pos=pos if use_pos else None,
            vel=vel if use_vel else None,
            acc=acc if use_acc else None,
        ):
            self.rejected_setpoints += 1
            return
        yaw_now = vehicle.attitude()[2]
        if frame in _BODY_FRAMES:
            pos = _rotate_yaw(pos, yaw_now)
            vel = _rotate_yaw(vel, yaw_now)
            acc = _rotate_yaw(acc, yaw_now)
        world = None
        if use_pos:
            if frame == mavlink.MAV_FRAME_LOCAL_NED:
                world = vehicle.odometry.to_world(vehicle.index, (pos[0], pos[1], pos[2]))
            else:
                here = vehicle.position_ned()
                world = [here[k] + pos[k] for k in range(3)]
        self._accept_or_reject(msg, world, vel if use_vel else None, acc if use_acc else None)

    def on_position_target_global(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        vehicle = self._vehicle
        if not vehicle.is_for_me(msg):
            return
        mask = msg.type_mask
        if msg.coordinate_frame not in _GLOBAL_FRAMES:
            self.rejected_setpoints += 1
            return
        use_pos = not mask & _IGNORE_POS
        use_vel = not mask & _IGNORE_VEL
        vel = [msg.vx, msg.vy, msg.vz]
        if not _valid_vectors(vel=vel if use_vel else None):
            self.rejected_setpoints += 1
            return
        world = None
        if use_pos:
            lat, lon, alt = msg.lat_int * 1e-7, msg.lon_int * 1e-7, msg.alt
            if not (-90 <= lat <= 90 and -180 <= lon <= 180 and math.isfinite(alt)):
                self.rejected_setpoints += 1
                return
            n, e = vehicle.projection.to_local(lat, lon)
            relative = msg.coordinate_frame in _GLOBAL_RELATIVE_FRAMES
            world = [n, e, vehicle.down_from_altitude(alt, relative)]
        self._accept_or_reject(msg, world, vel if use_vel else None, None)

    def on_attitude_target(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        """Approximation: the tilt and thrust become an acceleration command."""
        if not self._vehicle.is_for_me(msg):
            return
        mask = msg.type_mask
        if mask & mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE:
            thrust = _HOVER_THRUST
        else:
            thrust = msg.thrust
        q = list(msg.q)
        if not (math.isfinite(thrust) and all(math.isfinite(v) for v in q)):
            self.rejected_setpoints += 1
            return
        norm = math.sqrt(sum(v * v for v in q))
        yaw_rate = math.nan
        if not mask & mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE and math.isfinite(
            msg.body_yaw_rate
        ):
            yaw_rate = msg.body_yaw_rate
        if mask & mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE or norm < 1e-6:
            roll = pitch = 0.0
            yaw = math.nan
        else:
            roll, pitch, yaw = quaternion_to_euler(*(v / norm for v in q))
            if math.isfinite(yaw_rate):
                yaw = math.nan
        g = ph.GRAVITY_M_S2
        forward = -g * math.tan(max(-_MAX_TILT_RAD, min(_MAX_TILT_RAD, pitch)))
        right = g * math.tan(max(-_MAX_TILT_RAD, min(_MAX_TILT_RAD, roll)))
        heading = self._vehicle.attitude()[2]
        acc = [
            forward * math.cos(heading) - right * math.sin(heading),
            forward * math.sin(heading) + right * math.cos(heading),
            g * (1.0 - max(0.0, min(1.0, thrust)) / _HOVER_THRUST),
        ]
        self._accept(OffboardSetpoint("acceleration", acc, None, yaw, yaw_rate))

    # ---------------------------------------------------------------- control
    def signal_fresh(self) -> bool:
        """A setpoint arrived within the last COM_OF_LOSS_T seconds."""
        vehicle = self._vehicle
        return vehicle.state.now_s - self._last_setpoint_s <= vehicle.params["COM_OF_LOSS_T"]

    def apply(self) -> None:
        """Steer the vehicle by the latest setpoint (nothing before the first one)."""
        sp = self._setpoint
        if sp is None:
            return
        i = self._vehicle.index
        phys = self._vehicle.physics
        if sp.kind == "velocity":
            phys.control_mode[i] = ph.VELOCITY
            phys.velocity_setpoint_ned_m_s[i] = sp.vector_ned
        elif sp.kind == "position":
            phys.control_mode[i] = ph.POSITION
            phys.position_setpoint_ned_m[i] = sp.vector_ned
            phys.velocity_feedforward_ned_m_s[i] = sp.feedforward_ned_m_s or (0.0, 0.0, 0.0)
        else:
            phys.control_mode[i] = ph.ACCELERATION
            phys.acceleration_setpoint_ned_m_s2[i] = sp.vector_ned
        phys.yaw_setpoint_rad[i] = sp.yaw_rad
        phys.yaw_rate_setpoint_rad_s[i] = sp.yaw_rate_rad_s

    def _accept_or_reject(
        self,
        msg: mavlink.MAVLink_message,
        position_ned_m: list[float] | None,
        velocity_ned_m_s: list[float] | None,
        acceleration_ned_m_s2: list[float] | None,
    ) -> None:
        """Accept the setpoint of a SET_POSITION_TARGET_* whose used vectors (world NED, None
        when ignored) are given: a position first (with the velocity as feed-forward), else a
        velocity, else an acceleration; with none of them it is rejected."""
        yaw, yaw_rate = _yaw(msg)
        if position_ned_m is not None:
            self._accept(
                OffboardSetpoint("position", position_ned_m, velocity_ned_m_s, yaw, yaw_rate)
            )
        elif velocity_ned_m_s is not None:
            self._accept(OffboardSetpoint("velocity", velocity_ned_m_s, None, yaw, yaw_rate))
        elif acceleration_ned_m_s2 is not None:
            self._accept(
                OffboardSetpoint("acceleration", acceleration_ned_m_s2, None, yaw, yaw_rate)
            )
        else:
            self.rejected_setpoints += 1

    def _accept(self, sp: OffboardSetpoint) -> None:
        state = self._vehicle.state
        self._setpoint = sp
        self._last_setpoint_s = state.now_s
        self.accepted_setpoints += 1
        if state.mode is FlightMode.OFFBOARD and state.armed:
            self.apply()
        for listener in self.setpoint_listeners:
            listener()


def _valid_vectors(
    *,
    pos: list[float] | None = None,
    vel: list[float] | None = None,
    acc: list[float] | None = None,
) -> bool:
    """The used vectors (not None) are finite and physically plausible."""
    for vector, limit in (
        (pos, _MAX_POSITION_M),
        (vel, _MAX_SPEED_M_S),
        (acc, _MAX_ACCEL_M_S2),
    ):
        if vector is not None and not all(math.isfinite(v) and abs(v) < limit for v in vector):
            return False
    return True


def _yaw(msg: mavlink.MAVLink_message) -> tuple[float, float]:
    """(yaw rad, yaw rate rad/s) of a SET_POSITION_TARGET_*, NaN for each one not given."""
    mask = msg.type_mask
    yaw = math.nan
    if not mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE and math.isfinite(msg.yaw):
        yaw = msg.yaw
    rate = math.nan
    if not mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE and math.isfinite(msg.yaw_rate):
        rate = msg.yaw_rate
    return yaw, rate


def _rotate_yaw(v: list[float], yaw_rad: float) -> list[float]:
    """Body (forward, right, down) -> NED for a vehicle heading ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return [v[0] * c - v[1] * s, v[0] * s + v[1] * c, v[2]]
