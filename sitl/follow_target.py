"""Follow-me of one vehicle: FOLLOW_TARGET in, PX4's target estimator, and the follow flight task.

PX4 (flight_mode_manager/tasks/AutoFollowTarget) follows a target that a ground station or a
phone reports with FOLLOW_TARGET (position AMSL and velocity; MAVSDK's follow_me plugin sends
it). This module does the same in three stages, with PX4's constants:

1. :class:`TargetEstimator`: an alpha-beta-gamma filter whose gains come from FLW_TGT_RS
   ("responsiveness": lower values follow the target faster and smooth less), fusing a
   position at most every 0.5 s and a velocity every 0.1 s, and predicting in between; after
   3 s without a message the estimate stops moving.
2. :class:`FollowTarget` smooths the estimate with a second-order filter (1 rad/s, damping
   0.71), takes the target's course from its velocity (once faster than 1 m/s) and turns the
   vehicle's angle around the target towards course + FLW_TGT_FA (0 in front, 90 right, 180
   behind) no faster than FLW_TGT_MAX_VEL / FLW_TGT_DST and 2 m/s^2 / FLW_TGT_DST. PX4 limits
   the jerk of that turn too; the emulator does not.
3. The setpoint: FLW_TGT_DST from the target at that angle, FLW_TGT_HT above home (FLW_TGT_ALT_M
   0), the ground (1; the emulator's ground is flat) or the target (2), with the target's
   velocity and the turn fed forward, facing the target. More than 3 m off the height, the
   vehicle first climbs or descends on the spot.

Without any target message the vehicle holds where it is.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as mavlink

from sitl.vehicle_state import Link, VehicleContext

_MIN_POSITION_FUSION_S = 0.5  # TargetEstimator MINIMUM_TIME_BETWEEN_POS_FUSIONS_MS
_MIN_VELOCITY_FUSION_S = 0.1  # ... VEL_FUSIONS_MS
_STALE_S = 3.0  # GPS_MESSAGE_STALE_TIMEOUT_MS
_ACCELERATION_SATURATION_M_S2 = 20.0
_FILTER_NATURAL_FREQUENCY_RAD_S = 1.0  # TARGET_POS_VEL_FILTER_NATURAL_FREQUENCY
_FILTER_DAMPING = 0.7071
_COURSE_MIN_SPEED_M_S = 1.0  # TARGET_SPEED_DEADZONE_FOR_ORIENTATION_TRACKING
_ORBIT_MAX_ACCELERATION_M_S2 = 2.0  # ORBIT_TRAJECTORY_MAX_ACCELERATION
_ALTITUDE_ACCEPTANCE_M = 3.0  # ALT_ACCEPTANCE_THRESHOLD
_YAW_MIN_DISTANCE_M = 1.0  # MINIMUM_DISTANCE_TO_TARGET_FOR_YAW_CONTROL
_MINIMUM_SAFETY_ALTITUDE_M = 1.0  # below it above the ground: emergency ascent
_EMERGENCY_ASCENT_SPEED_M_S = 0.5


def _wrap_pi(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class TargetEstimator:
    """PX4's follow-target estimator: position, velocity, acceleration of the target, world NED.

    ``measure`` takes one FOLLOW_TARGET (converted to world NED); ``predict`` advances the
    estimate. Gains from the responsiveness r (FLW_TGT_RS, clamped to [0.1, 1]):
    beta = r^(1/3), position G = 1 - beta^3, H = 1.5 (1 - beta)^2 (1 + beta),
    K = 0.5 (1 - beta)^3; velocity (beta 0.9 beta) G = 1 - beta^2, H = (1 - beta)^2.
    """

    def __init__(self) -> None:
        self.position_ned_m: list[float] | None = None
        self.velocity_ned_m_s = [0.0, 0.0, 0.0]
        self.acceleration_ned_m_s2 = [0.0, 0.0, 0.0]
        self.last_measurement_s = -math.inf
        self._last_position_fusion_s = -math.inf
        self._last_velocity_fusion_s = -math.inf
        self._last_position: list[float] | None = None
        self._last_velocity: list[float] | None = None

    @property
    def valid(self) -> bool:
        return self.position_ned_m is not None

    def stale(self, now_s: float) -> bool:
        return now_s - self.last_measurement_s >= _STALE_S

    def predict(self, dt: float, now_s: float) -> None:
        pos = self.position_ned_m
        if pos is None:
            return
        vel, acc = self.velocity_ned_m_s, self.acceleration_ned_m_s2
        for k in range(3):
            pos[k] += dt * vel[k] + 0.5 * acc[k] * dt * dt
            vel[k] += dt * acc[k]
        if self.stale(now_s):
            # PX4 keeps the last position and stops moving it.
            self.velocity_ned_m_s = [0.0, 0.0, 0.0]
            self.acceleration_ned_m_s2 = [0.0, 0.0, 0.0]

    def measure(
        self,
        position_ned_m: list[float],
        velocity_ned_m_s: list[float],
        now_s: float,
        responsiveness: float,
    ) -> None:
        if self.position_ned_m is None:
            self.position_ned_m = list(position_ned_m)
            finite = all(math.isfinite(v) for v in velocity_ned_m_s)
            self.velocity_ned_m_s = list(velocity_ned_m_s) if finite else [0.0, 0.0, 0.0]
            self.acceleration_ned_m_s2 = [0.0, 0.0, 0.0]
            self._last_position = list(position_ned_m)
            self._last_velocity = list(velocity_ned_m_s)
        self.last_measurement_s = now_s
        beta_p = max(0.1, min(1.0, responsiveness)) ** (1.0 / 3.0)
        beta_v = 0.9 * beta_p
        pos, vel, acc = self.position_ned_m, self.velocity_ned_m_s, self.acceleration_ned_m_s2
        if self._fusable(
            position_ned_m, self._last_position, self._last_position_fusion_s, now_s, True
        ):
            dt = max(1e-3, min(20.0, now_s - self._last_position_fusion_s))
            self._last_position_fusion_s = now_s
            g = 1.0 - beta_p**3
            h = 1.5 * (1.0 - beta_p) ** 2 * (1.0 + beta_p)
            k = 0.5 * (1.0 - beta_p) ** 3
            for i in range(3):
                innovation = position_ned_m[i] - pos[i]
                pos[i] += g * innovation
                vel[i] += h / dt * innovation
                acc[i] += 2.0 * k / (dt * dt) * innovation
            self._last_position = list(position_ned_m)
        if self._fusable(
            velocity_ned_m_s, self._last_velocity, self._last_velocity_fusion_s, now_s, False
        ):
            dt = max(1e-3, min(20.0, now_s - self._last_velocity_fusion_s))
            self._last_velocity_fusion_s = now_s
            g = 1.0 - beta_v**2
            h = (1.0 - beta_v) ** 2
            for i in range(3):
                innovation = velocity_ned_m_s[i] - vel[i]
                vel[i] += g * innovation
                acc[i] += h / dt * innovation
            self._last_velocity = list(velocity_ned_m_s)
        norm = math.sqrt(sum(a * a for a in acc))
        if norm > _ACCELERATION_SATURATION_M_S2:
            self.acceleration_ned_m_s2 = [a * _ACCELERATION_SATURATION_M_S2 / norm for a in acc]

    @staticmethod
    def _fusable(
        value: list[float],
        previous: list[float] | None,
        last_fusion_s: float,
        now_s: float,
        position: bool,
    ) -> bool:
        """TargetEstimator::measurement_can_be_fused: finite, not too soon, and new (or the
        last fusion is twice the minimum interval old)."""
        interval = _MIN_POSITION_FUSION_S if position else _MIN_VELOCITY_FUSION_S
        if not all(math.isfinite(v) for v in value):
            return False
        changed = previous is None or any(
            abs(a - b) > 2.4e-7 for a, b in zip(value, previous, strict=True)
        )
        age = now_s - last_fusion_s
        return age > interval and (changed or age > 2.0 * interval)


class FollowTarget:
    """FOLLOW_TARGET handling and the follow-me flight task (AUTO_FOLLOW_TARGET) of one vehicle."""

    def __init__(self, vehicle: VehicleContext) -> None:
        self._vehicle = vehicle
        self.estimator = TargetEstimator()
        self._pending: tuple[list[float], list[float], float] | None = None
        self._filter_pos: list[float] | None = None
        self._filter_vel = [0.0, 0.0, 0.0]
        self._course_rad = 0.0
        self._orbit_angle_rad = 0.0
        self._orbit_rate_rad_s = 0.0
        self._hold_ned_m = [0.0, 0.0, 0.0]

    # ------------------------------------------------------------------ input
    def on_follow_target(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        """FOLLOW_TARGET has no target system: every vehicle that hears it takes it, as PX4."""
        vehicle = self._vehicle
        lat, lon, alt = msg.lat * 1e-7, msg.lon * 1e-7, msg.alt
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(alt)):
            return
        north, east = vehicle.projection.to_local(lat, lon)
        down = vehicle.down_from_altitude(alt, relative_to_home=False)
        velocity = [float(v) for v in msg.vel]
        self._pending = ([north, east, down], velocity, vehicle.state.now_s)

    # ------------------------------------------------------------------- task
    def activate(self) -> None:
        """AUTO_FOLLOW_TARGET entered (armed): PX4 restarts its estimator and filters."""
        self.estimator = TargetEstimator()
        self._filter_pos = None
        self._filter_vel = [0.0, 0.0, 0.0]
        self._course_rad = 0.0
        self._orbit_angle_rad = 0.0
        self._orbit_rate_rad_s = 0.0
        self._hold_ned_m = list(self._vehicle.position_ned())
        self.update(0.0)

    def update(self, dt: float) -> None:
        """One step of PX4's FlightTaskAutoFollowTarget::update."""
        vehicle = self._vehicle
        p = vehicle.params
        now = vehicle.state.now_s
        estimator = self.estimator
        estimator.predict(dt, now)
        pending = self._pending
        if pending is not None:
            self._pending = None
            estimator.measure(pending[0], pending[1], pending[2], p["FLW_TGT_RS"])
        target = estimator.position_ned_m
        if target is None:
            vehicle.fly_to(self._hold_ned_m)
            return
        self._filter(target, estimator.velocity_ned_m_s, dt)
        assert self._filter_pos is not None
        tgt, tgt_vel = self._filter_pos, self._filter_vel
        pos = vehicle.position_ned()
        to_target = (tgt[0] - pos[0], tgt[1] - pos[1])
        if (
            math.hypot(tgt_vel[0], tgt_vel[1]) >= _COURSE_MIN_SPEED_M_S
            and math.hypot(*estimator.velocity_ned_m_s[:2]) >= _COURSE_MIN_SPEED_M_S
        ):
            self._course_rad = math.atan2(tgt_vel[1], tgt_vel[0])
        distance = p["FLW_TGT_DST"]
        self._turn(self._course_rad + math.radians(p["FLW_TGT_FA"]), distance, dt)
        angle, rate = self._orbit_angle_rad, self._orbit_rate_rad_s
        desired = [tgt[0] + distance * math.cos(angle), tgt[1] + distance * math.sin(angle)]
        mode = int(p["FLW_TGT_ALT_M"])
        height = p["FLW_TGT_HT"]
        if mode == 2:
            down = tgt[2] - height
        elif mode == 1:
            down = -height  # flat ground at world down 0
        else:
            down = vehicle.state.home_ned_m[2] - height
        yaw = math.nan
        if math.hypot(*to_target) > _YAW_MIN_DISTANCE_M:
            yaw = math.atan2(to_target[1], to_target[0])
        if vehicle.height_above_ground_m() < _MINIMUM_SAFETY_ALTITUDE_M:
            # SIH's distance sensor measures the height; PX4 stops and climbs slowly.
            vehicle.fly_at(
                [0.0, 0.0, -_EMERGENCY_ASCENT_SPEED_M_S], yaw_rad=yaw, yaw_rate_rad_s=math.nan
            )
        elif abs(down - pos[2]) < _ALTITUDE_ACCEPTANCE_M:
            tangential = [-math.sin(angle) * rate * distance, math.cos(angle) * rate * distance]
            feedforward = [tangential[0] + tgt_vel[0], tangential[1] + tgt_vel[1], 0.0]
            vehicle.fly_to([desired[0], desired[1], down], feedforward, yaw_rad=yaw)
        else:
            vehicle.fly_to([pos[0], pos[1], down], yaw_rad=yaw)

    def _filter(self, target: list[float], velocity: list[float], dt: float) -> None:
        """PX4's second-order reference model of the target (position with rate feed-forward)."""
        if self._filter_pos is None or dt <= 0.0:
            if self._filter_pos is None:
                self._filter_pos = list(target)
                self._filter_vel = list(velocity)
            return
        w, z = _FILTER_NATURAL_FREQUENCY_RAD_S, _FILTER_DAMPING
        for k in range(3):
            acc = w * w * (target[k] - self._filter_pos[k]) + 2.0 * z * w * (
                velocity[k] - self._filter_vel[k]
            )
            self._filter_vel[k] += acc * dt
            self._filter_pos[k] += self._filter_vel[k] * dt

    def _turn(self, goal_rad: float, distance: float, dt: float) -> None:
        """Turn the angle around the target towards ``goal_rad`` (the shorter way), limited in
        rate (FLW_TGT_MAX_VEL / distance) and acceleration (2 m/s^2 / distance)."""
        max_rate = self._vehicle.params["FLW_TGT_MAX_VEL"] / distance
        max_acc = _ORBIT_MAX_ACCELERATION_M_S2 / distance
        remaining = _wrap_pi(goal_rad - self._orbit_angle_rad)
        wanted = math.copysign(min(max_rate, math.sqrt(2.0 * max_acc * abs(remaining))), remaining)
        step = max_acc * dt
        rate = self._orbit_rate_rad_s
        self._orbit_rate_rad_s = max(rate - step, min(rate + step, wanted))
        self._orbit_angle_rad = _wrap_pi(self._orbit_angle_rad + self._orbit_rate_rad_s * dt)
