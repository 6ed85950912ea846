"""Stick input of one vehicle, and the modes the sticks fly: Position, Altitude, Stabilized, Manual.

Two PX4 parts in one module, because nothing else uses either:

- PX4's manual_control module: :class:`ManualControl` takes MANUAL_CONTROL (a joystick or
  gamepad through MAVSDK's manual_control plugin or QGroundControl), scales it the way PX4's
  MAVLink receiver does (x pitch, y roll, r yaw in [-1000, 1000]; z throttle in [0, 1000], 500
  centred) and says whether it still comes (COM_RC_LOSS_T). COM_RC_IN_MODE 0 (RC only) or 4
  (disabled) ignores it, as does an injected RC-signal failure.
- The flight tasks PX4's flight mode manager runs for those modes (:class:`StickFlight`):

  ``POSCTL`` (ManualAcceleration): the pitch/roll sticks command an acceleration of up to
  2 x MPC_ACC_HOR against a drag that makes full stick settle at MPC_VEL_MANUAL (time
  constant MPC_VEL_MANUAL / (2 MPC_ACC_HOR), 1.7 s by default); centred sticks brake harder
  and then hold the position. ``ALTCTL``: the sticks tilt the vehicle (full stick:
  MPC_MAN_TILT_MAX), and the air's drag (1/s, as SIH's quadrotor shows) limits the speed;
  nothing holds the position. In both the throttle stick commands the climb rate (full stick:
  MPC_Z_VEL_MAX_UP up, MPC_Z_VEL_MAX_DN down), centred it holds the altitude, and the yaw stick
  the yaw rate (full stick: MPC_MAN_Y_MAX). ``STABILIZED`` / ``MANUAL``: tilt as ALTCTL; the
  throttle is thrust around hover, approximated as a vertical acceleration of up to 1 g.

  The sticks go through PX4's deadzone (MAN_DEADZONE) and expo (0.6, fixed in PX4) except
  for the tilt of ALTCTL/STABILIZED, which is linear as in PX4. On the ground the vehicle
  stays put until the throttle is above 65 % (PX4's take-off threshold in stick modes).

The commander (:mod:`sitl.commander`) asks :meth:`ManualControl.signal_fresh` before it enters a
stick mode and fails safe (NAV_RCL_ACT) when the input stops.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from sitl import physics as ph
from sitl.modes import FlightMode
from sitl.vehicle_state import Link, VehicleContext

# PX4 (lib/sticks/Sticks.hpp) fixes the expo of every stick at 0.6.
STICK_EXPO = 0.6
# FlightTaskManualAltitude::_checkTakeoff: a zero-centred throttle above 0.3 takes off.
_TAKEOFF_THROTTLE = 0.3
# What SIH's quadrotor settles at in Altitude mode: 3.4 m/s at 19 deg of tilt (3.4 m/s^2).
_AIR_DRAG_1_S = 1.0
_LOCK_SPEED_M_S = 0.1  # below this a braking vehicle holds its position
_HOLD_GAIN_1_S = 1.0  # position hold of a locked axis
# COM_RC_IN_MODE values that take no MAVLink MANUAL_CONTROL: RC only, disabled.
_RC_IN_MODES_WITHOUT_MAVLINK = frozenset([0, 4])
_MAX_STICK = 1000


def deadzone(value: float, zone: float) -> float:
    """PX4's ``math::deadzone``: 0 inside ``zone``, rescaled to [-1, 1] outside it."""
    value = max(-1.0, min(1.0, value))
    zone = max(0.0, min(0.99, zone))
    if abs(value) <= zone:
        return 0.0
    return (value - math.copysign(zone, value)) / (1.0 - zone)


def expo(value: float, e: float = STICK_EXPO) -> float:
    """PX4's ``math::expo``: (1 - e) x + e x^3 on [-1, 1]."""
    x = max(-1.0, min(1.0, value))
    return (1.0 - e) * x + e * x * x * x


@dataclass(slots=True)
class Sticks:
    """One MANUAL_CONTROL as PX4 stores it: every axis in [-1, 1], throttle centred at 0."""

    pitch: float = 0.0  # forward positive
    roll: float = 0.0  # right positive
    yaw: float = 0.0  # clockwise positive
    throttle: float = 0.0  # up positive


class ManualControl:
    """The MANUAL_CONTROL input of one vehicle (PX4's manual_control module)."""

    def __init__(self, vehicle: VehicleContext) -> None:
        self._vehicle = vehicle
        self.sticks = Sticks()
        self._last_input_s = -math.inf
        self.signal_blocked = False
        """An injected RC-signal failure: input is ignored while set."""

    def on_manual_control(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        vehicle = self._vehicle
        if msg.target not in (0, vehicle.sysid) or self.signal_blocked:
            return
        if int(vehicle.params["COM_RC_IN_MODE"]) in _RC_IN_MODES_WITHOUT_MAVLINK:
            return
        # PX4's MAVLink receiver: an axis out of range reads as centred.
        sticks = Sticks()
        if abs(msg.x) <= _MAX_STICK:
            sticks.pitch = msg.x / 1000.0
        if abs(msg.y) <= _MAX_STICK:
            sticks.roll = msg.y / 1000.0
        if abs(msg.r) <= _MAX_STICK:
            sticks.yaw = msg.r / 1000.0
        if 0 <= msg.z <= _MAX_STICK:
            sticks.throttle = msg.z / 500.0 - 1.0
        self.sticks = sticks
        self._last_input_s = vehicle.state.now_s

    def signal_fresh(self) -> bool:
        """Manual control input arrived within the last COM_RC_LOSS_T seconds."""
        if self.signal_blocked or self._last_input_s == -math.inf:
            return False  # the common case of no joystick at all: no parameter lookup
        vehicle = self._vehicle
        return vehicle.state.now_s - self._last_input_s <= vehicle.params["COM_RC_LOSS_T"]

    def shaped(self) -> Sticks:
        """The sticks after PX4's deadzone and expo; centred while the input is lost."""
        if not self.signal_fresh():
            return Sticks()
        zone = self._vehicle.params["MAN_DEADZONE"]
        s = self.sticks
        return Sticks(
            expo(deadzone(s.pitch, zone)),
            expo(deadzone(s.roll, zone)),
            expo(deadzone(s.yaw, zone)),
            expo(deadzone(s.throttle, zone)),
        )

    def raw(self) -> Sticks:
        """The sticks as received; centred while the input is lost."""
        return self.sticks if self.signal_fresh() else Sticks()


class StickFlight:
    """The flight task of the stick modes (POSCTL, ALTCTL, STABILIZED, MANUAL) of one vehicle.

    It integrates its own horizontal velocity setpoint, as PX4's stick tasks do, and hands the
    kinematic model a velocity (and a yaw rate) each autopilot step.
    """

    def __init__(self, vehicle: VehicleContext, manual: ManualControl) -> None:
        self._vehicle = vehicle
        self._manual = manual
        self._velocity_sp_ne = [0.0, 0.0]
        self._velocity_sp_down = 0.0
        self._hold_ne: list[float] | None = None
        self._hold_down: float | None = None
        self._hold_yaw = math.nan

    def activate(self) -> None:
        """The mode was entered (armed): carry on from the current motion."""
        vel = self._vehicle.velocity_ned()
        self._velocity_sp_ne = [vel[0], vel[1]]
        self._velocity_sp_down = vel[2]
        self._hold_ne = None
        self._hold_down = None
        self._hold_yaw = math.nan
        self.update(0.0)

    def update(self, dt: float) -> None:
        """Fly one autopilot step of the current stick mode, ``dt`` after the last."""
        vehicle = self._vehicle
        p = vehicle.params
        mode = vehicle.state.mode
        shaped = self._manual.shaped()
        raw = self._manual.raw()
        pos = vehicle.position_ned()
        vel = vehicle.velocity_ned()
        yaw = vehicle.attitude()[2]
        c, s = math.cos(yaw), math.sin(yaw)

        if vehicle.state.landed and raw.throttle <= _TAKEOFF_THROTTLE:
            # PX4 keeps a landed vehicle on the ground until the throttle asks for a take-off.
            self._velocity_sp_ne = [0.0, 0.0]
            self._velocity_sp_down = 0.0
            self._hold_ne = [pos[0], pos[1]]
            self._hold_down = pos[2]
            self._write([0.0, 0.0, 0.0], math.nan, yaw)
            return

        # Horizontal.
        if mode is FlightMode.POSCTL:
            forward, right = shaped.pitch, shaped.roll
            norm = math.hypot(forward, right)
            if norm > 1.0:
                forward, right = forward / norm, right / norm
            acc_scale = 2.0 * p["MPC_ACC_HOR"]
            drag = acc_scale / p["MPC_VEL_MANUAL"]
            centred = norm == 0.0
            if centred:
                drag *= max(2.0, math.sqrt(p["MPC_VEL_MANUAL"]))  # PX4's brake boost
            acc = [acc_scale * (forward * c - right * s), acc_scale * (forward * s + right * c)]
            vsp = self._velocity_sp_ne
            for k in range(2):
                vsp[k] += (acc[k] - drag * vsp[k]) * dt
            if centred and math.hypot(*vsp) < _LOCK_SPEED_M_S:
                vsp[0] = vsp[1] = 0.0
                if self._hold_ne is None:
                    self._hold_ne = [pos[0], pos[1]]
            elif not centred:
                self._hold_ne = None
            if self._hold_ne is not None:
                v_ne = [_HOLD_GAIN_1_S * (self._hold_ne[k] - pos[k]) for k in range(2)]
            else:
                v_ne = list(vsp)
        else:
            forward, right = raw.pitch, raw.roll
            norm = math.hypot(forward, right)
            if norm > 1.0:
                forward, right = forward / norm, right / norm
            tilt = math.radians(max(0.0, min(89.0, p["MPC_MAN_TILT_MAX"])))
            acc_max = min(math.tan(tilt), 3.0) * ph.GRAVITY_M_S2
            acc = [acc_max * (forward * c - right * s), acc_max * (forward * s + right * c)]
            vsp = self._velocity_sp_ne
            for k in range(2):
                vsp[k] += (acc[k] - _AIR_DRAG_1_S * vsp[k]) * dt
            self._hold_ne = None
            v_ne = list(vsp)

        # Vertical (down positive).
        if mode in (FlightMode.POSCTL, FlightMode.ALTCTL):
            throttle = shaped.throttle
            if throttle != 0.0:
                limit = p["MPC_Z_VEL_MAX_UP"] if throttle > 0 else p["MPC_Z_VEL_MAX_DN"]
                v_down = -throttle * limit
                self._hold_down = None
            else:
                if self._hold_down is None:
                    # Lock where a braking vehicle comes to rest.
                    accel = max(p["MPC_ACC_UP_MAX"], p["MPC_ACC_DOWN_MAX"], 0.1)
                    self._hold_down = pos[2] + vel[2] * abs(vel[2]) / (2.0 * accel)
                v_down = _HOLD_GAIN_1_S * (self._hold_down - pos[2])
        else:
            self._velocity_sp_down += (
                -raw.throttle * ph.GRAVITY_M_S2 - _AIR_DRAG_1_S * self._velocity_sp_down
            ) * dt
            v_down = self._velocity_sp_down

        # Heading: the yaw stick turns, centred it holds.
        yaw_rate = shaped.yaw * math.radians(p["MPC_MAN_Y_MAX"])
        if yaw_rate != 0.0:
            self._hold_yaw = math.nan
            self._write([v_ne[0], v_ne[1], v_down], yaw_rate, math.nan)
            return
        if math.isnan(self._hold_yaw):
            self._hold_yaw = yaw
        self._write([v_ne[0], v_ne[1], v_down], math.nan, self._hold_yaw)

    def _write(self, velocity_ned: list[float], yaw_rate: float, yaw: float) -> None:
        vehicle = self._vehicle
        # The automatic modes' yaw-rate limit (MPC_YAWRAUTO_MAX) does not bind the yaw stick.
        limit = math.radians(vehicle.params["MPC_MAN_Y_MAX"])
        vehicle.physics.max_yaw_rate_rad_s[vehicle.index] = limit
        vehicle.fly_at(velocity_ned, yaw_rad=yaw, yaw_rate_rad_s=yaw_rate)
