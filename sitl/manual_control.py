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
        mode = vehicle.state.mode
        shaped = self._manual.shaped()
        raw = self._manual.raw()
        pos = vehicle.position_ned()
        yaw = vehicle.attitude()[2]
        if vehicle.state.landed and raw.throttle <= _TAKEOFF_THROTTLE:
            self._stay_landed(pos, yaw)
            return
        if mode is FlightMode.POSCTL:
            v_ne = self._horizontal_by_acceleration(shaped, pos, yaw, dt)
        else:
            v_ne = self._horizontal_by_tilt(raw, yaw, dt)
        if mode in (FlightMode.POSCTL, FlightMode.ALTCTL):
            v_down = self._vertical_by_climb_rate(
                shaped.throttle, pos[2], vehicle.velocity_ned()[2]
            )
        else:
            v_down = self._vertical_by_thrust(raw.throttle, dt)
        yaw_rate, yaw_sp = self._heading(shaped.yaw, yaw)
        self._write([v_ne[0], v_ne[1], v_down], yaw_rate, yaw_sp)

    def _stay_landed(self, pos: list[float], yaw: float) -> None:
        """PX4 keeps a landed vehicle on the ground until the throttle asks for a take-off."""
        self._velocity_sp_ne = [0.0, 0.0]
        self._velocity_sp_down = 0.0
        self._hold_ne = [pos[0], pos[1]]
        self._hold_down = pos[2]
        self._write([0.0, 0.0, 0.0], math.nan, yaw)

    def _horizontal_by_acceleration(
        self, shaped: Sticks, pos: list[float], yaw: float, dt: float
    ) -> list[float]:
        """POSCTL's north-east velocity [m/s]: the sticks accelerate against a drag; centred,
        they brake harder and then hold the position where the vehicle stopped."""
        p = self._vehicle.params
        c, s = math.cos(yaw), math.sin(yaw)
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
            return [_HOLD_GAIN_1_S * (self._hold_ne[k] - pos[k]) for k in range(2)]
        return list(vsp)

    def _horizontal_by_tilt(self, raw: Sticks, yaw: float, dt: float) -> list[float]:
        """ALTCTL's, STABILIZED's and MANUAL's north-east velocity [m/s]: the sticks tilt the
        vehicle (linearly, full stick MPC_MAN_TILT_MAX) and the air's drag limits the speed."""
        c, s = math.cos(yaw), math.sin(yaw)
        forward, right = raw.pitch, raw.roll
        norm = math.hypot(forward, right)
        if norm > 1.0:
            forward, right = forward / norm, right / norm
        tilt = math.radians(max(0.0, min(89.0, self._vehicle.params["MPC_MAN_TILT_MAX"])))
        acc_max = min(math.tan(tilt), 3.0) * ph.GRAVITY_M_S2
        acc = [acc_max * (forward * c - right * s), acc_max * (forward * s + right * c)]
        vsp = self._velocity_sp_ne
        for k in range(2):
            vsp[k] += (acc[k] - _AIR_DRAG_1_S * vsp[k]) * dt
        self._hold_ne = None
        return list(vsp)

    def _vertical_by_climb_rate(self, throttle: float, down_m: float, down_m_s: float) -> float:
        """POSCTL's and ALTCTL's down velocity [m/s]: the throttle stick commands the climb
        rate; centred, the altitude where a braking vehicle comes to rest is held."""
        p = self._vehicle.params
        if throttle != 0.0:
            limit = p["MPC_Z_VEL_MAX_UP"] if throttle > 0 else p["MPC_Z_VEL_MAX_DN"]
            self._hold_down = None
            return -throttle * limit
        if self._hold_down is None:
            accel = max(p["MPC_ACC_UP_MAX"], p["MPC_ACC_DOWN_MAX"], 0.1)
            self._hold_down = down_m + down_m_s * abs(down_m_s) / (2.0 * accel)
        return _HOLD_GAIN_1_S * (self._hold_down - down_m)

    def _vertical_by_thrust(self, throttle: float, dt: float) -> float:
        """STABILIZED's and MANUAL's down velocity [m/s]: the throttle is thrust around hover
        (up to 1 g of vertical acceleration), against the air's drag."""
        self._velocity_sp_down += (
            -throttle * ph.GRAVITY_M_S2 - _AIR_DRAG_1_S * self._velocity_sp_down
        ) * dt
        return self._velocity_sp_down

    def _heading(self, yaw_stick: float, yaw: float) -> tuple[float, float]:
        """The yaw stick turns, centred it holds the heading: (yaw rate [rad/s], yaw [rad]),
        NaN for the one not commanded."""
        yaw_rate = yaw_stick * math.radians(self._vehicle.params["MPC_MAN_Y_MAX"])
        if yaw_rate != 0.0:
            self._hold_yaw = math.nan
            return yaw_rate, math.nan
        if math.isnan(self._hold_yaw):
            self._hold_yaw = yaw
        return math.nan, self._hold_yaw

    def _write(self, velocity_ned: list[float], yaw_rate: float, yaw: float) -> None:
        vehicle = self._vehicle
        # The automatic modes' yaw-rate limit (MPC_YAWRAUTO_MAX) does not bind the yaw stick.
        limit = math.radians(vehicle.params["MPC_MAN_Y_MAX"])
        vehicle.physics.max_yaw_rate_rad_s[vehicle.index] = limit
        vehicle.fly_at(velocity_ned, yaw_rad=yaw, yaw_rate_rad_s=yaw_rate)
