"""Kinematic multicopter model for many vehicles at once: plain synchronous ``step(dt)``.

All state is numpy arrays over vehicles, in a shared world NED frame (metres, origin at the
configured home, ground at down = 0). Nothing here knows about MAVLink, modes or time keeping;
the autopilot state machine writes setpoints into the arrays and the emulator calls
:meth:`MulticopterPhysics.step`.

Control modes per vehicle (``control_mode``):

``MOTORS_OFF``
    disarmed or dead: no thrust; in the air the vehicle falls, on the ground it stays. A vehicle
    whose ``motor_failure`` is set flies as if in this mode, whatever its setpoints.
``VELOCITY``
    tracks ``velocity_setpoint_ned_m_s``.
``POSITION``
    flies to ``position_setpoint_ned_m`` (velocity command from a P-gain, bounded by
    ``cruise_speed_m_s``, the vertical limits and a braking profile sqrt(2 a d)), plus
    ``velocity_feedforward_ned_m_s``.
``ACCELERATION``
    commands ``acceleration_setpoint_ned_m_s2`` directly (attitude setpoints map to this).

In every mode the velocity command is limited to the speed limits, the velocity follows it with
a first-order lag (``time_constant_s``) and acceleration limits. Wind pushes a flying vehicle by
``drag_1_s`` x (wind - what the controller has learnt of it); the learnt part follows the wind
with ``wind_rejection_time_s``. Roll and pitch are the tilt that produces the horizontal
acceleration; yaw follows ``yaw_rate_setpoint_rad_s`` if finite, else turns towards
``yaw_setpoint_rad`` (if finite) at ``max_yaw_rate_rad_s``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

GRAVITY_M_S2 = 9.80665

MOTORS_OFF = 0
VELOCITY = 1
POSITION = 2
ACCELERATION = 3

FloatArray = npt.NDArray[np.float64]


class Wind:
    """Mean wind plus per-vehicle Ornstein-Uhlenbeck gusts (horizontal), seeded.

    ``velocity_ned_m_s`` has shape (n, 3); :meth:`step` advances the gusts.
    """

    def __init__(
        self,
        n: int,
        mean_ned_m_s: npt.ArrayLike = (0.0, 0.0, 0.0),
        gust_std_m_s: float = 0.0,
        gust_time_constant_s: float = 3.0,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.mean_ned_m_s = np.asarray(mean_ned_m_s, dtype=float).reshape(3)
        self.gust_std_m_s = float(gust_std_m_s)
        self.gust_time_constant_s = float(gust_time_constant_s)
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self.gust_ned_m_s = np.zeros((n, 3))
        if self.gust_std_m_s > 0:
            self.gust_ned_m_s[:, :2] = self._rng.normal(0.0, self.gust_std_m_s, size=(n, 2))
        self.velocity_ned_m_s = self.mean_ned_m_s + self.gust_ned_m_s

    @property
    def active(self) -> bool:
        return self.gust_std_m_s > 0 or bool(np.any(self.mean_ned_m_s))

    def step(self, dt: float) -> None:
        if self.gust_std_m_s > 0:
            # Exact discretisation of the OU process keeps the variance right for any dt.
            decay = np.exp(-dt / self.gust_time_constant_s)
            noise_std = self.gust_std_m_s * np.sqrt(1.0 - decay * decay)
            n = self.gust_ned_m_s.shape[0]
            self.gust_ned_m_s[:, :2] *= decay
            self.gust_ned_m_s[:, :2] += self._rng.normal(0.0, noise_std, size=(n, 2))
        np.add(self.mean_ned_m_s, self.gust_ned_m_s, out=self.velocity_ned_m_s)


class MulticopterPhysics:
    """State and setpoints of ``n`` kinematic multicopters.

    Arrays (all float64 unless noted):

    - ``position_ned_m`` (n, 3), ``velocity_ned_m_s`` (n, 3), ``acceleration_ned_m_s2`` (n, 3)
    - ``yaw_rad`` (n,), ``roll_rad`` (n,), ``pitch_rad`` (n,), ``yaw_rate_rad_s`` (n,),
      ``roll_rate_rad_s`` (n,), ``pitch_rate_rad_s`` (n,) (Euler angle rates)
    - ``motor_failure`` (n,) bool: the motors give no thrust (an injected failure)
    - setpoints: ``control_mode`` (n,) int8, ``velocity_setpoint_ned_m_s`` (n, 3),
      ``position_setpoint_ned_m`` (n, 3), ``velocity_feedforward_ned_m_s`` (n, 3),
      ``acceleration_setpoint_ned_m_s2`` (n, 3), ``yaw_setpoint_rad`` (n,) NaN = keep,
      ``yaw_rate_setpoint_rad_s`` (n,) NaN = none
    - limits: ``max_horizontal_speed_m_s``, ``max_up_speed_m_s``, ``max_down_speed_m_s``,
      ``cruise_speed_m_s`` (position mode horizontal speed), ``max_horizontal_accel_m_s2``,
      ``max_up_accel_m_s2``, ``max_down_accel_m_s2``, ``max_yaw_rate_rad_s`` (all (n,))
    """

    def __init__(
        self,
        initial_position_ned_m: npt.ArrayLike,
        initial_yaw_rad: npt.ArrayLike | None = None,
        *,
        time_constant_s: float = 0.15,
        position_gain_1_s: float = 1.0,
        wind: Wind | None = None,
        wind_rejection_time_s: float = 1.5,
        drag_1_s: float = 0.3,
        airspeed_drag_1_s: float = 0.0,
        velocity_integral_gain_1_s2: float = 0.0,
        tilt_time_constant_s: float = 0.0,
    ) -> None:
        pos = np.array(initial_position_ned_m, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"initial positions must have shape (n, 3), got {pos.shape}")
        n = pos.shape[0]
        self.n: int = n
        self.position_ned_m: FloatArray = pos
        self.velocity_ned_m_s: FloatArray = np.zeros((n, 3))
        self.acceleration_ned_m_s2: FloatArray = np.zeros((n, 3))
        yaw = np.zeros(n) if initial_yaw_rad is None else np.array(initial_yaw_rad, dtype=float)
        self.yaw_rad: FloatArray = yaw.reshape(n)
        self.roll_rad: FloatArray = np.zeros(n)
        self.pitch_rad: FloatArray = np.zeros(n)
        self.yaw_rate_rad_s: FloatArray = np.zeros(n)
        self.roll_rate_rad_s: FloatArray = np.zeros(n)
        self.pitch_rate_rad_s: FloatArray = np.zeros(n)

        self.control_mode = np.full(n, MOTORS_OFF, dtype=np.int8)
        self.motor_failure = np.zeros(n, dtype=bool)
        self.velocity_setpoint_ned_m_s: FloatArray = np.zeros((n, 3))
        self.position_setpoint_ned_m: FloatArray = pos.copy()
        self.velocity_feedforward_ned_m_s: FloatArray = np.zeros((n, 3))
        self.acceleration_setpoint_ned_m_s2: FloatArray = np.zeros((n, 3))
        self.yaw_setpoint_rad: FloatArray = np.full(n, np.nan)
        self.yaw_rate_setpoint_rad_s: FloatArray = np.full(n, np.nan)

        self.max_horizontal_speed_m_s: FloatArray = np.full(n, 12.0)
        self.max_up_speed_m_s: FloatArray = np.full(n, 3.0)
        self.max_down_speed_m_s: FloatArray = np.full(n, 1.5)
        self.cruise_speed_m_s: FloatArray = np.full(n, 5.0)
        self.max_horizontal_accel_m_s2: FloatArray = np.full(n, 3.0)
        self.max_up_accel_m_s2: FloatArray = np.full(n, 4.0)
        self.max_down_accel_m_s2: FloatArray = np.full(n, 3.0)
        self.max_yaw_rate_rad_s: FloatArray = np.full(n, np.deg2rad(45.0))

        self.time_constant_s = float(time_constant_s)
        self.position_gain_1_s = float(position_gain_1_s)
        self.wind = wind
        self.wind_rejection_time_s = float(wind_rejection_time_s)
        self.drag_1_s = float(drag_1_s)
        self.airspeed_drag_1_s = float(airspeed_drag_1_s)
        self.velocity_integral_gain_1_s2 = float(velocity_integral_gain_1_s2)
        self.velocity_integral_ned_m_s2: FloatArray = np.zeros((n, 3))
        self.tilt_time_constant_s = float(tilt_time_constant_s)
        self.horizontal_accel_ned_m_s2: FloatArray = np.zeros((n, 3))
        self.wind_learnt_ned_m_s: FloatArray = np.zeros((n, 3))
        if wind is not None:
            self.wind_learnt_ned_m_s[:] = wind.velocity_ned_m_s

    # ------------------------------------------------------------------ queries
    def on_ground(self) -> npt.NDArray[np.bool_]:
        """(n,) bool: touching the ground (down >= -1 cm)."""
        return self.position_ned_m[:, 2] >= -0.01

    # --------------------------------------------------------------------- step
    def step(self, dt: float) -> None:
        """Advance every vehicle by ``dt`` seconds."""
        if dt <= 0:
            raise ValueError(f"dt must be > 0, got {dt!r}")
        # The modes as a list, to test for a mode without a numpy reduction each: this runs
        # at the physics rate for every vehicle set, and numpy's per-call overhead is its cost.
        mode = self.control_mode
        if _any(self.motor_failure):
            mode = np.where(self.motor_failure, np.int8(MOTORS_OFF), mode)
        modes = mode.tolist()
        v_cmd = self._velocity_command(mode, modes)
        accel = self._acceleration(v_cmd, mode, modes, dt)
        wind = self.wind
        if wind is not None and wind.active:
            self._push_by_wind(wind, accel, dt)
        self._hold_on_ground(v_cmd, accel, mode)
        self._integrate(accel, dt)
        self._attitude(accel, dt, mode, modes)

    # ------------------------------------------------------------ step's stages
    def _velocity_command(self, mode: npt.NDArray[np.int8], modes: list[int]) -> FloatArray:
        """1. The velocity command (n, 3) per control mode, within the speed limits."""
        if modes.count(VELOCITY) == self.n:
            v_cmd = self.velocity_setpoint_ned_m_s.copy()
        else:
            v_cmd = np.where(
                (mode == VELOCITY)[:, None], self.velocity_setpoint_ned_m_s, self.velocity_ned_m_s
            )
        if POSITION in modes:
            positional = mode == POSITION
            v_cmd[positional] = self._position_controller(positional)
        return self._limit_velocity(v_cmd)

    def _acceleration(
        self, v_cmd: FloatArray, mode: npt.NDArray[np.int8], modes: list[int], dt: float
    ) -> FloatArray:
        """2. Acceleration (n, 3): first-order lag towards the command, then the limits; the
        setpoint where one is commanded, gravity alone where the motors are off."""
        accel = (v_cmd - self.velocity_ned_m_s) * _lag_gain(self.time_constant_s, dt)
        if self.airspeed_drag_1_s > 0 or self.velocity_integral_gain_1_s2 > 0:
            self._velocity_loop(accel, v_cmd, mode, dt)
        if self.tilt_time_constant_s > 0:
            # The horizontal acceleration comes from tilting, which takes time (PX4 SIH: a
            # velocity step starts to show ~0.2 s later).
            blend = _lag_gain(self.tilt_time_constant_s, dt) * dt
            self.horizontal_accel_ned_m_s2[:, :2] += blend * (
                accel[:, :2] - self.horizontal_accel_ned_m_s2[:, :2]
            )
            accel[:, :2] = self.horizontal_accel_ned_m_s2[:, :2]
        if ACCELERATION in modes:
            accelerating = mode == ACCELERATION
            accel[accelerating] = self.acceleration_setpoint_ned_m_s2[accelerating]
        accel = self._limit_acceleration(accel)
        if MOTORS_OFF in modes:
            accel[mode == MOTORS_OFF] = (0.0, 0.0, GRAVITY_M_S2)
        return accel

    def _velocity_loop(
        self, accel: FloatArray, v_cmd: FloatArray, mode: npt.NDArray[np.int8], dt: float
    ) -> None:
        """The optional PX4-like velocity loop, added to ``accel`` in place: an integral term
        fighting horizontal airspeed drag. PX4 SIH (velocity P 1.8, I 0.4, drag ~1/s) reaches
        only ~65 % of a commanded speed for seconds."""
        vel = self.velocity_ned_m_s
        flying = (mode == VELOCITY) | (mode == POSITION)
        error = np.where(flying[:, None], v_cmd - vel, 0.0)
        error[:, 2] = 0.0
        self.velocity_integral_ned_m_s2 += self.velocity_integral_gain_1_s2 * error * dt
        self.velocity_integral_ned_m_s2[~flying] = 0.0
        accel += self.velocity_integral_ned_m_s2
        drag = self.airspeed_drag_1_s * vel
        drag[:, 2] = 0.0
        accel[flying] -= drag[flying]

    def _push_by_wind(self, wind: Wind, accel: FloatArray, dt: float) -> None:
        """3. Wind pushes flying vehicles by the part the controller has not learnt yet (added
        to ``accel`` in place)."""
        wind.step(dt)
        learn = _lag_gain(self.wind_rejection_time_s, dt) * dt
        self.wind_learnt_ned_m_s += learn * (wind.velocity_ned_m_s - self.wind_learnt_ned_m_s)
        push = self.drag_1_s * (wind.velocity_ned_m_s - self.wind_learnt_ned_m_s)
        push[:, 2] = 0.0
        airborne = ~self.on_ground()
        accel[airborne] += push[airborne]

    def _hold_on_ground(
        self, v_cmd: FloatArray, accel: FloatArray, mode: npt.NDArray[np.int8]
    ) -> None:
        """4. Skids do not slide: a vehicle resting on the ground stays put unless told to
        climb (its velocity and ``accel`` zeroed in place)."""
        resting = self.position_ned_m[:, 2] >= 0.0
        if _any(resting):
            climbing = (mode != MOTORS_OFF) & (v_cmd[:, 2] < -0.05)
            climbing |= (mode == ACCELERATION) & (accel[:, 2] < 0.0)
            held = resting & ~climbing
            self.velocity_ned_m_s[held] = 0.0
            accel[held] = 0.0

    def _integrate(self, accel: FloatArray, dt: float) -> None:
        """5. Integrate (semi-implicit Euler) and keep everything above the ground."""
        pos = self.position_ned_m
        vel = self.velocity_ned_m_s
        vel += accel * dt
        pos += vel * dt
        grounded = pos[:, 2] >= 0.0
        if _any(grounded):
            pos[grounded, 2] = 0.0
            vel[grounded, 2] = np.minimum(vel[grounded, 2], 0.0)
        self.acceleration_ned_m_s2[:] = accel

    # ---------------------------------------------------------------- internals
    def _position_controller(self, mask: npt.NDArray[np.bool_]) -> FloatArray:
        error = self.position_setpoint_ned_m[mask] - self.position_ned_m[mask]
        gain = self.position_gain_1_s
        # Horizontal: P command, capped by cruise speed and by the speed from which the vehicle
        # can still brake to a stop at the target.
        err_xy = error[:, :2]
        dist_xy = np.hypot(err_xy[:, 0], err_xy[:, 1])
        brake_xy = np.sqrt(2.0 * self.max_horizontal_accel_m_s2[mask] * dist_xy)
        speed_xy = np.minimum(gain * dist_xy, np.minimum(self.cruise_speed_m_s[mask], brake_xy))
        scale = speed_xy / np.maximum(dist_xy, 1e-9)  # speed_xy <= gain * dist_xy: no blow-up
        v = np.empty_like(error)
        v[:, :2] = err_xy * scale[:, None]
        # Vertical: down positive; climb limited by up speed, descent by down speed.
        err_z = error[:, 2]
        brake_up = np.sqrt(2.0 * self.max_down_accel_m_s2[mask] * np.abs(err_z))
        brake_down = np.sqrt(2.0 * self.max_up_accel_m_s2[mask] * np.abs(err_z))
        vz = gain * err_z
        vz = np.where(err_z < 0, -np.minimum(-vz, brake_up), np.minimum(vz, brake_down))
        v[:, 2] = vz
        return v + self.velocity_feedforward_ned_m_s[mask]

    def _limit_velocity(self, v: FloatArray) -> FloatArray:
        limit = self.max_horizontal_speed_m_s
        v[:, :2] *= _shrink(np.hypot(v[:, 0], v[:, 1]), limit)[:, None]
        _clip(v[:, 2], -self.max_up_speed_m_s, self.max_down_speed_m_s)
        return v

    def _limit_acceleration(self, a: FloatArray) -> FloatArray:
        limit = self.max_horizontal_accel_m_s2
        a[:, :2] *= _shrink(np.hypot(a[:, 0], a[:, 1]), limit)[:, None]
        _clip(a[:, 2], -self.max_up_accel_m_s2, self.max_down_accel_m_s2)
        return a

    def _attitude(
        self, accel: FloatArray, dt: float, mode: npt.NDArray[np.int8], modes: list[int]
    ) -> None:
        yaw = self.yaw_rad
        rate_cmd = self.yaw_rate_setpoint_rad_s
        has_rate = np.isfinite(rate_cmd)
        yaw_sp = self.yaw_setpoint_rad
        error = _wrap(np.where(np.isfinite(yaw_sp), yaw_sp, yaw) - yaw)
        # Turn towards the yaw setpoint: P-gain 2/s, capped at the yaw rate limit.
        rate = np.where(has_rate, rate_cmd, 2.0 * error) if _any(has_rate) else 2.0 * error
        max_rate = self.max_yaw_rate_rad_s
        rate = _clip(rate, -max_rate, max_rate)
        # Do not overshoot the yaw setpoint within one step.
        rate = np.where(~has_rate & (np.abs(rate * dt) > np.abs(error)), error / dt, rate)
        turning = ~self.on_ground()
        if MOTORS_OFF in modes:
            turning &= mode != MOTORS_OFF
        rate *= turning
        # In place, so that references to these arrays stay valid.
        self.yaw_rate_rad_s[:] = rate
        self.yaw_rad[:] = _wrap(yaw + rate * dt)
        cos_y = np.cos(self.yaw_rad)
        sin_y = np.sin(self.yaw_rad)
        forward = accel[:, 0] * cos_y + accel[:, 1] * sin_y
        right = accel[:, 1] * cos_y - accel[:, 0] * sin_y
        # Motors off: no thrust to tilt with (accel is gravity only, so the atan2 give 0 there).
        pitch = -np.arctan2(forward, GRAVITY_M_S2)
        roll = np.arctan2(right, GRAVITY_M_S2)
        np.subtract(pitch, self.pitch_rad, out=self.pitch_rate_rad_s)
        self.pitch_rate_rad_s /= dt
        np.subtract(roll, self.roll_rad, out=self.roll_rate_rad_s)
        self.roll_rate_rad_s /= dt
        self.pitch_rad[:] = pitch
        self.roll_rad[:] = roll


def _lag_gain(time_constant_s: float, dt: float) -> float:
    """The gain (1/s) that makes one step of ``dt`` move a first-order lag exactly as far towards
    a held input as the continuous lag does, (1 - exp(-dt/tau)) / dt: the motion does not depend
    on the physics rate (the forward-Euler 1/tau moved 5 % further per 5 ms step at tau = 0.1 s,
    and overshoots once dt > tau). tau = 0: the input is reached in one step."""
    if time_constant_s <= 0.0:
        return 1.0 / dt
    return -math.expm1(-dt / time_constant_s) / dt


def _any(mask: npt.NDArray[np.bool_]) -> bool:
    """``mask.any()`` for the few vehicles of an emulator, without numpy's reduction overhead."""
    return True in mask.tolist()


def _clip(values: FloatArray, low: FloatArray, high: FloatArray) -> FloatArray:
    """``np.clip(values, low, high, out=values)`` (NaN stays NaN) as two ufuncs, which cost a
    fraction of ``np.clip``'s Python-level dispatch."""
    np.maximum(values, low, out=values)
    return np.minimum(values, high, out=values)


def _shrink(magnitude: FloatArray, limit: FloatArray) -> FloatArray:
    """Factor that scales vectors of ``magnitude`` down to at most ``limit`` (1 below it)."""
    return limit / np.maximum(np.maximum(magnitude, limit), 1e-12)


def _wrap(angle_rad: FloatArray) -> FloatArray:
    """Wrap to [-pi, pi)."""
    return (angle_rad + np.pi) % (2.0 * np.pi) - np.pi
