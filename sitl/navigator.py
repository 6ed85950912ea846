"""The navigator of one vehicle: what the vehicle flies to in the automatic modes.

As PX4's navigator module, :class:`Navigator` runs the AUTO modes once the commander
(:mod:`sitl.commander`) has chosen one: TAKEOFF (climb, then HOLD), HOLD (brake and loiter, or
fly to a DO_REPOSITION target), LAND, RTL (climb, return, descend, loiter, land) and MISSION
(item by item, with MISSION_ITEM_REACHED and MISSION_CURRENT). It owns the mission store
(:class:`sitl.mission.MissionTransfer`, the mission protocol) and steers the vehicle by writing
position setpoints and speed limits into its row of the shared physics. When a mode ends by
itself (take-off done, a mission's RTL item, an emptied mission) it asks the commander for the
next mode through ``set_mode``, as PX4's navigator sends the commander a vehicle command.
"""

from __future__ import annotations

import math
from typing import Protocol

from pymavlink.dialects.v20 import common as mavlink

from sitl.commands import Command, CommandTable
from sitl.mission import RELATIVE_ALT_FRAMES, MissionItem, MissionTransfer
from sitl.modes import FlightMode
from sitl.vehicle_state import Link, VehicleContext

# MISSION_CURRENT.mission_mode (a plain field, no MAVLink enum).
_MISSION_MODE_ACTIVE = 1
_MISSION_MODE_SUSPENDED = 2
# Mission items the vehicle flies to (position, possibly hold); the rest complete at once.
_FLOWN_ITEMS = frozenset(
    [
        mavlink.MAV_CMD_NAV_WAYPOINT,
        mavlink.MAV_CMD_NAV_LOITER_UNLIM,
        mavlink.MAV_CMD_NAV_LOITER_TIME,
        mavlink.MAV_CMD_NAV_TAKEOFF,
        mavlink.MAV_CMD_NAV_LAND,
    ]
)
_RTL_ARRIVED_M = 1.0
_LAND_ALT1_M, _LAND_ALT2_M = 10.0, 5.0  # PX4 MPC_LAND_ALT1 / MPC_LAND_ALT2 defaults
_NEXT_RTL_STAGE = {"climb": "return", "return": "descend", "descend": "loiter"}


class ModeSwitch(Protocol):
    """The commander's mode switch (see :meth:`sitl.commander.Commander.set_mode`)."""

    def __call__(self, mode: FlightMode, failsafe: bool = False) -> None: ...


class Navigator:
    """The AUTO modes of one vehicle."""

    def __init__(self, vehicle: VehicleContext, *, set_mode: ModeSwitch) -> None:
        self._vehicle = vehicle
        self._state = vehicle.state
        self._params = vehicle.params
        self._set_mode = set_mode
        self.mission = MissionTransfer(
            vehicle.sysid,
            vehicle.compid,
            on_uploaded=self._mission_uploaded,
            on_set_current=self.mission_set_current,
            send_current=self.broadcast_mission_current,
        )
        self._cruise_override_m_s: float | None = None
        self._takeoff_request_amsl_m = math.nan  # NAV_TAKEOFF's altitude, until the climb starts
        self._takeoff_requested = False
        self._takeoff_down_m = 0.0  # world NED down the climb ends at

        self._rtl_stage = ""
        self._rtl_altitude_m = 0.0
        self._rtl_loiter_until_s = 0.0

        self._mission_seq = 0
        self._mission_started = False
        self._mission_finished = False
        self._mission_phase = ""
        self._mission_hold_until_s = 0.0
        self._mission_warned: set[int] = set()

    # ================================================================ state
    @property
    def taking_off(self) -> bool:
        """Climbing to the take-off altitude (TAKEOFF mode, or a mission's first climb)."""
        return self._state.mode is FlightMode.TAKEOFF or self._mission_phase == "takeoff"

    @property
    def has_mission(self) -> bool:
        return bool(self.mission.items)

    def request_takeoff(self, altitude_amsl_m: float) -> None:
        """NAV_TAKEOFF's altitude (AMSL, NaN: MIS_TAKEOFF_ALT above the vehicle), kept until
        the next climb starts, as PX4's navigator keeps its takeoff triplet."""
        self._takeoff_request_amsl_m = altitude_amsl_m
        self._takeoff_requested = True

    def _start_takeoff(self) -> None:
        """PX4's Takeoff::set_takeoff_position, run when TAKEOFF starts armed: the requested
        altitude, else MIS_TAKEOFF_ALT above the vehicle; never down."""
        vehicle = self._vehicle
        pos = vehicle.position_ned()
        if not (self._takeoff_requested or self._state.landed):
            # Flying already (motors back after a failure): the climb goes on as it was.
            self._fly_to([pos[0], pos[1], self._takeoff_down_m], math.nan)
            return
        requested, self._takeoff_request_amsl_m = self._takeoff_request_amsl_m, math.nan
        self._takeoff_requested = False
        now = self._state.now_s
        if math.isfinite(requested):
            down = vehicle.down_from_altitude(requested, relative_to_home=False)
        else:
            default_m = self._params["MIS_TAKEOFF_ALT"]
            down = pos[2] - default_m
            text = f"Using default takeoff altitude: {default_m:.1f} m\t"
            vehicle.statustext(now, mavlink.MAV_SEVERITY_INFO, text)
        if down > pos[2]:
            down = pos[2]
            text = "Already higher than takeoff altitude\t"
            vehicle.statustext(now, mavlink.MAV_SEVERITY_CRITICAL, text)
        self._takeoff_down_m = down
        self._fly_to([pos[0], pos[1], down], math.nan)

    def mission_status(self) -> tuple[int, int, int, int]:
        """MISSION_CURRENT fields (seq, total, mission_state, mission_mode)."""
        total = len(self.mission.items)
        in_mission = self._state.mode is FlightMode.MISSION
        mission_mode = _MISSION_MODE_ACTIVE if in_mission else _MISSION_MODE_SUSPENDED
        if total == 0:
            return 0, 0, mavlink.MISSION_STATE_NO_MISSION, mission_mode
        seq = min(self._mission_seq, total - 1)
        if self._mission_finished:
            state = mavlink.MISSION_STATE_COMPLETE
        elif not self._mission_started:
            state = mavlink.MISSION_STATE_NOT_STARTED
        elif in_mission:
            state = mavlink.MISSION_STATE_ACTIVE
        else:
            state = mavlink.MISSION_STATE_PAUSED
        return seq, total, state, mission_mode

    # ================================================================ modes
    def mode_changed(self, previous: FlightMode) -> None:
        """The commander switched modes: drop what the old one was doing, set the limits."""
        if self._state.mode is FlightMode.MISSION and previous is not FlightMode.MISSION:
            self._mission_restart_if_finished()
        self._state.landing = False
        self._rtl_stage = ""
        self.apply_limits()

    def enter_mode(self) -> None:
        """Start flying the current AUTO mode (the vehicle is armed)."""
        mode = self._state.mode
        if mode is FlightMode.TAKEOFF:
            self._start_takeoff()
        elif mode is FlightMode.LAND:
            self._start_landing()
        elif mode is FlightMode.RTL:
            self._rtl_begin()
        elif mode is FlightMode.MISSION:
            self._mission_start_item()
        else:
            self._hold_here()

    def update(self, now_s: float) -> None:
        """Advance the current AUTO mode to ``now_s`` (called while armed)."""
        mode = self._state.mode
        if mode is FlightMode.TAKEOFF:
            target_down = self._takeoff_down_m
            pos = self._vehicle.position_ned()
            if pos[2] <= target_down + 0.1 and not self._state.landed:
                self._set_mode(FlightMode.HOLD)
                self._fly_to([pos[0], pos[1], target_down], math.nan)
        elif mode is FlightMode.RTL:
            self._rtl_update(now_s)
        elif mode is FlightMode.MISSION:
            self._mission_update(now_s)
        if self._state.landing:
            self._vehicle.physics.max_down_speed_m_s[self._vehicle.index] = self._landing_speed()

    def on_touchdown(self) -> None:
        """After touchdown keep the motors idle on the spot (until auto-disarm)."""
        self.apply_limits()
        mode = self._state.mode
        if mode in (FlightMode.LAND, FlightMode.RTL) or (
            mode is FlightMode.MISSION and self._mission_phase == "land"
        ):
            pos = self._vehicle.position_ned()
            self._fly_to([pos[0], pos[1], 0.0], math.nan)

    # ================================================================ limits
    def apply_limits(self) -> None:
        """Speed/acceleration limits of this vehicle for the current mode, from the params."""
        i = self._vehicle.index
        p = self._params
        phys = self._vehicle.physics
        phys.max_horizontal_speed_m_s[i] = p["MPC_XY_VEL_MAX"]
        phys.max_up_speed_m_s[i] = p["MPC_Z_VEL_MAX_UP"]
        phys.max_down_speed_m_s[i] = p["MPC_Z_VEL_MAX_DN"]
        phys.max_horizontal_accel_m_s2[i] = p["MPC_ACC_HOR"]
        phys.max_up_accel_m_s2[i] = p["MPC_ACC_UP_MAX"]
        phys.max_down_accel_m_s2[i] = p["MPC_ACC_DOWN_MAX"]
        phys.max_yaw_rate_rad_s[i] = math.radians(p["MPC_YAWRAUTO_MAX"])
        if self._state.mode is FlightMode.OFFBOARD:
            cruise = p["MPC_XY_VEL_MAX"]
        else:
            cruise = self._cruise_override_m_s or p["MPC_XY_CRUISE"]
        phys.cruise_speed_m_s[i] = min(cruise, p["MPC_XY_VEL_MAX"])
        if self.taking_off:
            phys.max_up_speed_m_s[i] = min(p["MPC_TKO_SPEED"], p["MPC_Z_VEL_MAX_UP"])
        if self._state.landing:
            phys.max_down_speed_m_s[i] = self._landing_speed()

    def _landing_speed(self) -> float:
        """PX4 descends fast high up and at MPC_LAND_SPEED close to the ground."""
        p = self._params
        vehicle = self._vehicle
        height = vehicle.height_above_ground_m() if vehicle.snapshot.position_ned_m else 0.0
        slow, fast = p["MPC_LAND_SPEED"], max(p["MPC_Z_VEL_MAX_DN"], p["MPC_LAND_SPEED"])
        high, low = _LAND_ALT1_M, _LAND_ALT2_M
        if height >= high:
            return fast
        if height <= low:
            return slow
        return slow + (fast - slow) * (height - low) / (high - low)

    # ============================================================== steering
    def _fly_to(self, target_ned_m: list[float], yaw_rad: float) -> None:
        self._vehicle.fly_to(target_ned_m, yaw_rad=yaw_rad)

    def _hold_here(self) -> None:
        """Brake and hold: target the stopping point of the current motion."""
        pos = self._vehicle.position_ned()
        if self._state.landed:
            self._fly_to([pos[0], pos[1], max(pos[2], 0.0)], math.nan)
            return
        vel = self._vehicle.velocity_ned()
        accel = max(self._params["MPC_ACC_HOR"], 0.1)
        speed = math.hypot(vel[0], vel[1])
        k = speed / (2.0 * accel)
        self._fly_to([pos[0] + vel[0] * k, pos[1] + vel[1] * k, pos[2]], math.nan)

    def _heading_to(self, target: list[float]) -> float:
        """Heading (rad) to ``target``; NaN (keep the heading) when closer than 2 m."""
        pos = self._vehicle.position_ned()
        dn, de = target[0] - pos[0], target[1] - pos[1]
        if math.hypot(dn, de) < 2.0:
            return math.nan
        return math.atan2(de, dn)

    def _start_landing(self) -> None:
        pos = self._vehicle.position_ned()
        self._state.landing = True
        self.apply_limits()
        # Aim below the ground: the descent is limited by the landing speed, the ground stops it.
        self._fly_to([pos[0], pos[1], 10.0], math.nan)

    def _physics_target(self) -> list[float]:
        return [
            float(v) for v in self._vehicle.physics.position_setpoint_ned_m[self._vehicle.index]
        ]

    def _reached(self, target: list[float], horizontal_m: float, vertical_m: float) -> bool:
        pos = self._vehicle.position_ned()
        vel = self._vehicle.velocity_ned()
        return (
            math.hypot(target[0] - pos[0], target[1] - pos[1]) <= horizontal_m
            and abs(target[2] - pos[2]) <= vertical_m
            and abs(vel[0]) + abs(vel[1]) + abs(vel[2]) < 1.5
        )

    # ============================================================== commands
    def _cmd_reposition(self, cmd: Command, link: Link) -> int:
        state = self._state
        vehicle = self._vehicle
        if not state.armed:
            return mavlink.MAV_RESULT_DENIED
        if state.landed:
            vehicle.statustext(
                state.now_s, mavlink.MAV_SEVERITY_CRITICAL, "Reposition denied: vehicle landed"
            )
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        p = cmd.params
        pos = vehicle.position_ned()
        target = list(pos)
        given = cmd.latitude_longitude()  # not given: keep the current position
        if given is not None:
            lat, lon = given
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
                return mavlink.MAV_RESULT_DENIED
            target[0], target[1] = vehicle.projection.to_local(lat, lon)
        alt = p[6]
        if math.isfinite(alt):
            relative = cmd.frame in RELATIVE_ALT_FRAMES
            target[2] = vehicle.down_from_altitude(alt, relative)
        speed = p[0]
        if math.isfinite(speed) and speed > 0:
            self._cruise_override_m_s = speed
        yaw = p[3] if math.isfinite(p[3]) else None
        if state.mode is not FlightMode.HOLD:
            # A goto is no new decision about a failsafe: its flag stays as it was.
            self._set_mode(FlightMode.HOLD, failsafe=state.failsafe_active)
        self._fly_to(target, yaw if yaw is not None else self._heading_to(target))
        self.apply_limits()
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_change_speed(self, cmd: Command, link: Link) -> int:
        speed = cmd.params[1]
        if not math.isfinite(speed):
            return mavlink.MAV_RESULT_DENIED
        self._cruise_override_m_s = speed if speed > 0 else None
        self.apply_limits()
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_set_mission_current(self, cmd: Command, link: Link) -> int:
        seq = cmd.params[0]
        if not math.isfinite(seq) or not self.mission_set_current(int(seq)):
            return mavlink.MAV_RESULT_DENIED
        self.broadcast_mission_current()
        return mavlink.MAV_RESULT_ACCEPTED

    # ==================================================================== RTL
    def _rtl_begin(self) -> None:
        if self._state.landed:
            self._rtl_stage = "done"
            self._hold_here()
            return
        altitude = self._vehicle.altitude_above_home_m()
        self._rtl_altitude_m = max(altitude, self._params["RTL_RETURN_ALT"])
        self._rtl_set_stage("climb")

    def _rtl_set_stage(self, stage: str) -> None:
        self._rtl_stage = stage
        pos = self._vehicle.position_ned()
        home = self._state.home_ned_m
        if stage == "climb":
            self._fly_to([pos[0], pos[1], home[2] - self._rtl_altitude_m], math.nan)
        elif stage == "return":
            target = [home[0], home[1], home[2] - self._rtl_altitude_m]
            self._fly_to(target, self._heading_to(target))
        elif stage == "descend":
            altitude = min(self._rtl_altitude_m, self._params["RTL_DESCEND_ALT"])
            self._fly_to([home[0], home[1], home[2] - altitude], math.nan)
        elif stage == "loiter":
            delay = self._params["RTL_LAND_DELAY"]
            self._rtl_loiter_until_s = math.inf if delay < 0 else self._state.now_s + delay
        elif stage == "land":
            self._start_landing()

    def _rtl_update(self, now_s: float) -> None:
        stage = self._rtl_stage
        if stage in ("", "done", "land"):
            return
        if stage == "loiter":
            if now_s >= self._rtl_loiter_until_s:
                self._rtl_set_stage("land")
            return
        if self._reached(self._physics_target(), _RTL_ARRIVED_M, self._params["NAV_MC_ALT_RAD"]):
            self._rtl_set_stage(_NEXT_RTL_STAGE[stage])

    # ================================================================ mission
    def _mission_uploaded(self, mission_type: int, items: list[MissionItem]) -> None:
        if mission_type != mavlink.MAV_MISSION_TYPE_MISSION:
            return
        self._mission_seq = 0
        self._mission_started = False
        self._mission_finished = False
        self._mission_phase = ""
        self._mission_warned.clear()
        if self._state.mode is FlightMode.MISSION:
            if items:
                self._mission_start_item()  # does nothing while disarmed
            else:
                self._set_mode(FlightMode.HOLD)
        self.broadcast_mission_current()

    def mission_set_current(self, seq: int) -> bool:
        """Make item ``seq`` the current one (flown at once in MISSION); False if none such."""
        if not 0 <= seq < len(self.mission.items):
            return False
        self._mission_seq = seq
        self._mission_finished = False
        if self._state.mode is FlightMode.MISSION and self._state.armed:
            self._mission_start_item()
        return True

    def _mission_restart_if_finished(self) -> None:
        if self._mission_finished:
            self._mission_seq = 0
            self._mission_finished = False

    def _mission_start_item(self) -> None:
        """Begin the current item; items that need no flying complete at once."""
        items = self.mission.items
        if not self._state.armed:
            return
        self._mission_started = True
        for _ in range(len(items) + 1):
            if self._mission_seq >= len(items):
                self._mission_complete()
                return
            item = items[self._mission_seq]
            command = item.command
            self._mission_phase = ""
            if command in _FLOWN_ITEMS:
                self._mission_fly_item(item)
                return
            if command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                # PX4 hands over to Return mode; MAVSDK expects no ITEM_REACHED for this item.
                self._mission_finished = True
                self.broadcast_mission_current()
                self._set_mode(FlightMode.RTL)
                return
            if command == mavlink.MAV_CMD_NAV_DELAY:
                self._mission_phase = "hold"
                delay = item.param1 if math.isfinite(item.param1) else 0.0
                self._mission_hold_until_s = self._state.now_s + max(delay, 0.0)
                self._hold_here()
                return
            if command == mavlink.MAV_CMD_DO_CHANGE_SPEED and math.isfinite(item.param2):
                self._cruise_override_m_s = item.param2 if item.param2 > 0 else None
                self.apply_limits()
            elif command < mavlink.MAV_CMD_NAV_ROI and command not in self._mission_warned:
                # A navigation item skipped changes the flight path: say so, once per command.
                self._mission_warned.add(command)
                self._vehicle.statustext(
                    self._state.now_s,
                    mavlink.MAV_SEVERITY_WARNING,
                    f"Mission item {command} not supported",
                )
            self._mission_item_reached(advance_only=True)
        self._mission_complete()

    def _mission_item_target(self, item: MissionItem) -> list[float]:
        vehicle = self._vehicle
        target = list(vehicle.position_ned())
        if item.x != 0 or item.y != 0:
            target[0], target[1] = vehicle.projection.to_local(
                item.latitude_deg, item.longitude_deg
            )
        if math.isfinite(item.z):
            target[2] = vehicle.down_from_altitude(item.z, item.frame in RELATIVE_ALT_FRAMES)
        return target

    def _mission_fly_item(self, item: MissionItem) -> None:
        target = self._mission_item_target(item)
        pos = self._vehicle.position_ned()
        home = self._state.home_ned_m
        if item.command == mavlink.MAV_CMD_NAV_LAND:
            if math.hypot(target[0] - pos[0], target[1] - pos[1]) > 1.0 and not self._state.landed:
                self._mission_phase = "go"
                self._fly_to([target[0], target[1], pos[2]], self._heading_to(target))
            else:
                self._mission_phase = "land"
                self._start_landing()
            return
        if item.command == mavlink.MAV_CMD_NAV_TAKEOFF:
            self._mission_phase = "takeoff"
            self.apply_limits()
            self._fly_to([pos[0], pos[1], min(target[2], pos[2])], math.nan)
            return
        if self._state.landed:
            # PX4 takes off vertically before flying to the first waypoint.
            altitude = max(home[2] - target[2], self._params["MIS_TAKEOFF_ALT"])
            self._mission_phase = "takeoff"
            self.apply_limits()
            self._fly_to([pos[0], pos[1], home[2] - altitude], math.nan)
            return
        self._mission_phase = "go"
        self.apply_limits()
        yaw = math.radians(item.param4) if math.isfinite(item.param4) else self._heading_to(target)
        self._fly_to(target, yaw)

    def _mission_update(self, now_s: float) -> None:
        phase = self._mission_phase
        if not self._state.armed or not phase or self._mission_finished:
            return
        items = self.mission.items
        if self._mission_seq >= len(items):
            return
        item = items[self._mission_seq]
        vertical = self._params["NAV_MC_ALT_RAD"]
        if phase == "takeoff":
            if self._reached(self._physics_target(), 1e9, vertical):
                if item.command == mavlink.MAV_CMD_NAV_TAKEOFF:
                    self._mission_phase = ""
                    self.apply_limits()
                    self._mission_item_reached()
                else:
                    self._mission_fly_item(item)
        elif phase == "go":
            radius = item.param2 if item.param2 > 0 else self._params["NAV_ACC_RAD"]
            if item.command == mavlink.MAV_CMD_NAV_LAND:
                radius = 1.0
            if not self._reached(self._physics_target(), radius, vertical):
                return
            if item.command == mavlink.MAV_CMD_NAV_LAND:
                self._mission_phase = "land"
                self._start_landing()
            elif item.command == mavlink.MAV_CMD_NAV_LOITER_UNLIM:
                self._mission_phase = "loiter"
            else:
                hold = item.param1 if math.isfinite(item.param1) and item.param1 > 0 else 0.0
                if hold > 0:
                    self._mission_phase = "hold"
                    self._mission_hold_until_s = now_s + hold
                else:
                    self._mission_item_reached()
        elif phase == "hold":
            if now_s >= self._mission_hold_until_s:
                self._mission_item_reached()
        elif phase == "land" and self._state.landed:
            self._mission_phase = ""
            self._mission_item_reached()

    def _mission_item_reached(self, advance_only: bool = False) -> None:
        self._vehicle.broadcast(mavlink.MAVLink_mission_item_reached_message(self._mission_seq))
        self._mission_seq += 1
        self._mission_phase = ""
        if self._mission_seq >= len(self.mission.items):
            self._mission_complete()
            return
        self.broadcast_mission_current()
        if not advance_only:
            self._mission_start_item()

    def _mission_complete(self) -> None:
        if self._mission_finished:
            return
        self._mission_finished = True
        self._mission_phase = ""
        self._mission_seq = max(len(self.mission.items) - 1, 0)
        self.broadcast_mission_current()
        if not self._state.landed:
            self._vehicle.statustext(
                self._state.now_s, mavlink.MAV_SEVERITY_INFO, "Mission finished, loitering"
            )
            self._hold_here()

    def broadcast_mission_current(self) -> None:
        seq, total, state, mode = self.mission_status()
        self._vehicle.broadcast(mavlink.MAVLink_mission_current_message(seq, total, state, mode))


#: The commands PX4's navigator answers (reposition, cruise speed, the current mission item).
NAVIGATOR_COMMANDS: CommandTable[Navigator] = {
    mavlink.MAV_CMD_DO_REPOSITION: Navigator._cmd_reposition,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: Navigator._cmd_change_speed,
    mavlink.MAV_CMD_DO_SET_MISSION_CURRENT: Navigator._cmd_set_mission_current,
}
