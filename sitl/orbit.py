"""Orbit mode of one vehicle: MAV_CMD_DO_ORBIT and the flight task that flies the circle.

As in PX4, the command switches to ORBIT (reported as POSCTL with sub-mode ORBIT) and the orbit
flight task (``FlightTaskOrbit``) takes its parameters:

- param 1 radius, m: its sign is the direction (positive clockwise seen from above); it must lie
  in [1, MC_ORBIT_RAD_MAX], else PX4 says "Orbit radius limit exceeded" and holds where the
  vehicle is, still in ORBIT;
- param 2 tangential speed, m/s, at most MPC_XY_VEL_MAX and at most sqrt(2 m/s^2 x radius);
- param 3 yaw behaviour (ORBIT_YAW_BEHAVIOUR): face the centre, hold the initial heading,
  uncontrolled, tangent to the circle, or left to the pilot (held here); 5 keeps it;
- params 5/6 centre latitude/longitude, param 7 its altitude AMSL.

Anything not given (NaN) keeps what the orbit had: a fresh orbit starts with PX4's 1 m radius,
1 m/s, clockwise, centred where the vehicle is. A vehicle away from the circle first flies to its
closest point (at MPC_XY_CRUISE, facing the centre), then circles with the speed ramped up at
MPC_ACC_HOR; a radial term (1/s) keeps it on the radius and the altitude is held at the
centre's.
"""

from __future__ import annotations

import math
from typing import Protocol

from pymavlink.dialects.v20 import common as mavlink

from sitl.commands import Command, CommandTable
from sitl.modes import FlightMode
from sitl.vehicle_state import Link, VehicleContext

_RADIUS_MIN_M = 1.0  # FlightTaskOrbit::_radius_min
_ACCELERATION_MAX_M_S2 = 2.0  # FlightTaskOrbit::_acceleration_max (centripetal)
_ON_CIRCLE_M = 2.0  # FlightTaskOrbit::_horizontal_acceptance_radius
_RADIAL_GAIN_1_S = 1.0
_YAW_GAIN_1_S = 2.0


class ModeSwitch(Protocol):
    """The commander's mode switch (see :meth:`sitl.commander.Commander.set_mode`)."""

    def __call__(self, mode: FlightMode, failsafe: bool = False) -> None: ...


class Orbit:
    """MAV_CMD_DO_ORBIT and the orbit flight task of one vehicle."""

    def __init__(self, vehicle: VehicleContext, *, set_mode: ModeSwitch) -> None:
        self._vehicle = vehicle
        self._set_mode = set_mode
        self._radius_m = _RADIUS_MIN_M
        self._velocity_m_s = 1.0  # signed: positive clockwise
        self._center_ned_m = [0.0, 0.0, 0.0]
        self._yaw_behaviour = mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_FRONT_TO_CIRCLE_CENTER
        self._initial_heading_rad = 0.0
        self._approaching = True
        self._failed = False
        self._orbiting = False
        self._speed_m_s = 0.0  # slew-rate limited |velocity|
        self._hold_ned_m = [0.0, 0.0, 0.0]  # where a failed or landed orbit stays

    # ---------------------------------------------------------------- state
    @property
    def radius_m(self) -> float:
        """Signed radius: positive clockwise (as ORBIT_EXECUTION_STATUS reports it)."""
        return math.copysign(self._radius_m, self._velocity_m_s)

    @property
    def velocity_m_s(self) -> float:
        return abs(self._velocity_m_s)

    @property
    def center_ned_m(self) -> list[float]:
        """Centre of the circle, world NED m."""
        return list(self._center_ned_m)

    # ---------------------------------------------------------------- task
    def activate(self) -> None:
        """ORBIT entered while armed: a fresh orbit around the current position."""
        self._reset()
        self.update(0.0)

    # ---------------------------------------------------------------- command
    def _cmd_do_orbit(self, cmd: Command, link: Link) -> int:
        vehicle = self._vehicle
        state = vehicle.state
        if not state.position_ok:
            vehicle.statustext(state.now_s, mavlink.MAV_SEVERITY_CRITICAL, "Orbit command rejected")
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        entering = state.mode is not FlightMode.ORBIT or self._failed
        if state.mode is not FlightMode.ORBIT:
            self._set_mode(FlightMode.ORBIT)
        if entering:
            self._reset()
        if not self._apply(cmd):
            # PX4's flight mode manager falls back to its failsafe task: hold, still in ORBIT.
            self._failed = True
            self._hold_ned_m = list(vehicle.position_ned())
            vehicle.statustext(
                state.now_s, mavlink.MAV_SEVERITY_CRITICAL, "Orbit radius limit exceeded\t"
            )
        if state.armed and state.mode is FlightMode.ORBIT:
            self.update(0.0)
        return mavlink.MAV_RESULT_ACCEPTED

    def _apply(self, cmd: Command) -> bool:
        """FlightTaskOrbit::applyCommandParameters; False if the radius is out of range."""
        vehicle = self._vehicle
        p = cmd.params
        params = vehicle.params
        clockwise = self._velocity_m_s > 0
        radius = self._radius_m
        speed = abs(self._velocity_m_s)
        if math.isfinite(p[0]):
            clockwise = p[0] > 0
            radius = abs(p[0])
        if math.isfinite(p[1]):
            speed = p[1]
        ok = _RADIUS_MIN_M <= radius <= params["MC_ORBIT_RAD_MAX"]
        if ok:
            velocity = math.copysign(speed, 1.0 if clockwise else -1.0)
            limit = abs(params["MPC_XY_VEL_MAX"])
            velocity = max(-limit, min(limit, velocity))
            if velocity * velocity >= _ACCELERATION_MAX_M_S2 * radius:
                velocity = math.copysign(math.sqrt(_ACCELERATION_MAX_M_S2 * radius), velocity)
            self._radius_m = radius
            self._velocity_m_s = velocity
        if math.isfinite(p[2]):
            behaviour = round(p[2])
            if behaviour == mavlink.ORBIT_YAW_BEHAVIOUR_UNCHANGED:
                if not self._orbiting:
                    self._yaw_behaviour = int(params["MC_ORBIT_YAW_MOD"])
            else:
                self._yaw_behaviour = behaviour
        self._initial_heading_rad = vehicle.attitude()[2]
        given = cmd.latitude_longitude()
        if given is not None and -90.0 <= given[0] <= 90.0 and -180.0 <= given[1] <= 180.0:
            self._center_ned_m[0], self._center_ned_m[1] = vehicle.projection.to_local(*given)
        if math.isfinite(p[6]):
            # PX4 reads param 7 as AMSL whatever the frame (MAVSDK sends AMSL in frame 3 too).
            self._center_ned_m[2] = vehicle.down_from_altitude(p[6], relative_to_home=False)
        if not self._on_circle() and not self._approaching:
            self._approaching = True
        return ok

    # ---------------------------------------------------------------- flying
    def _reset(self) -> None:
        vehicle = self._vehicle
        self._radius_m = _RADIUS_MIN_M
        self._velocity_m_s = 1.0
        self._center_ned_m = list(vehicle.position_ned())
        self._yaw_behaviour = mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_FRONT_TO_CIRCLE_CENTER
        self._initial_heading_rad = vehicle.attitude()[2]
        self._approaching = True
        self._failed = False
        self._orbiting = False
        self._speed_m_s = 0.0
        self._hold_ned_m = list(vehicle.position_ned())

    def _on_circle(self) -> bool:
        pos = self._vehicle.position_ned()
        c = self._center_ned_m
        distance = math.hypot(pos[0] - c[0], pos[1] - c[1])
        return (
            abs(distance - self._radius_m) < _ON_CIRCLE_M
            and abs(pos[2] - c[2]) < self._vehicle.params["NAV_MC_ALT_RAD"]
        )

    def update(self, dt: float) -> None:
        """One step of PX4's FlightTaskOrbit::update, ``dt`` after the last."""
        vehicle = self._vehicle
        pos = vehicle.position_ned()
        if self._failed or vehicle.state.landed:
            vehicle.fly_to(self._hold_ned_m)
            return
        self._orbiting = True
        c = self._center_ned_m
        dn, de = pos[0] - c[0], pos[1] - c[1]
        distance = math.hypot(dn, de)
        if self._approaching and self._on_circle():
            self._approaching = False
            self._speed_m_s = 0.0
        if self._approaching:
            # Fly to the closest point of the circle, facing the centre.
            scale = self._radius_m / distance if distance > 1e-6 else 0.0
            if distance <= 1e-6:
                dn, scale = 1.0, self._radius_m  # from the centre: start north of it
            target = [c[0] + dn * scale, c[1] + de * scale, c[2]]
            vehicle.fly_to(target, yaw_rad=math.atan2(-de, -dn) if distance > 0.5 else math.nan)
            return
        accel = vehicle.params["MPC_ACC_HOR"]
        speed = abs(self._velocity_m_s)
        step = accel * dt
        self._speed_m_s = max(self._speed_m_s - step, min(self._speed_m_s + step, speed))
        direction = 1.0 if self._velocity_m_s > 0 else -1.0
        un, ue = (dn / distance, de / distance) if distance > 1e-6 else (1.0, 0.0)
        tangential = direction * self._speed_m_s
        radial = _RADIAL_GAIN_1_S * (self._radius_m - distance)
        velocity = [
            -ue * tangential + un * radial,
            un * tangential + ue * radial,
            _RADIAL_GAIN_1_S * (c[2] - pos[2]),
        ]
        vehicle.fly_at(velocity, yaw_rate_rad_s=self._yaw_rate(un, ue, direction))

    def _yaw_rate(self, un: float, ue: float, direction: float) -> float:
        """FlightTaskOrbit::_generate_circle_yaw_setpoints as a yaw rate (rad/s), with the
        turn rate fed forward."""
        yaw = self._vehicle.attitude()[2]
        rate_ff = direction * self._speed_m_s / self._radius_m
        behaviour = self._yaw_behaviour
        if behaviour == mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_INITIAL_HEADING:
            target, rate_ff = self._initial_heading_rad, 0.0
        elif behaviour == mavlink.ORBIT_YAW_BEHAVIOUR_UNCONTROLLED:
            return 0.0
        elif behaviour == mavlink.ORBIT_YAW_BEHAVIOUR_HOLD_FRONT_TANGENT_TO_CIRCLE:
            target = math.atan2(direction * un, -direction * ue)
        elif behaviour == mavlink.ORBIT_YAW_BEHAVIOUR_RC_CONTROLLED:
            target, rate_ff = yaw, 0.0  # no pilot here: keep the heading
        else:
            target = math.atan2(-ue, -un)
        error = (target - yaw + math.pi) % (2.0 * math.pi) - math.pi
        return rate_ff + _YAW_GAIN_1_S * error


#: The command PX4 answers with its orbit mode (commander + flight mode manager).
ORBIT_COMMANDS: CommandTable[Orbit] = {mavlink.MAV_CMD_DO_ORBIT: Orbit._cmd_do_orbit}
