"""The commander of one vehicle: arming, mode switching and failsafes.

As PX4's commander module, :class:`Commander` decides the vehicle's top-level state in the
shared :class:`sitl.vehicle_state.VehicleState`:

- arming and disarming, with PX4's pre-arm checks (estimator ready, a position source,
  an offboard signal for OFFBOARD), injected health refusals (:meth:`Commander.deny_arming`),
  forced arm/disarm and flight termination;
- mode requests from clients (DO_SET_MODE, SET_MODE, NAV_TAKEOFF/LAND/RETURN_TO_LAUNCH,
  MISSION_START, DO_PAUSE_CONTINUE) with PX4's acceptance rules, and home (DO_SET_HOME);
- once per step while armed: failsafes (offboard loss -> COM_OBL_RC_ACT, data-link loss ->
  NAV_DLL_ACT, manual-control loss -> NAV_RCL_ACT, empty battery -> COM_LOW_BAT_ACT, both
  position sources lost in flight -> LAND) and auto-disarm after landing (COM_DISARM_LAND) or
  when never taking off (COM_DISARM_PRFLT). Like PX4's failsafe framework, a Return or Land
  action for manual-control loss or an empty battery first holds for COM_FAIL_ACT_T seconds
  ("Failsafe activated: entering Hold for 5 seconds"); a mode the user picks meanwhile cancels
  it.

On every mode change it hands control to the part that flies the new mode: the navigator
(:mod:`sitl.navigator`) for the AUTO modes, offboard (:mod:`sitl.offboard`) for OFFBOARD, the
flight mode manager (:mod:`sitl.flight_mode_manager`) for ORBIT, FOLLOW_TARGET and the stick
modes, which need manual control input (:mod:`sitl.manual_control`) to be entered. The land
detector (:mod:`sitl.land_detector`) reports touchdowns and take-offs to it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from sitl.commands import Command, CommandTable
from sitl.config import PX4_ARMING_DENIED_TEXT
from sitl.flight_mode_manager import FlightModeManager
from sitl.land_detector import LandDetector, LandEvent
from sitl.manual_control import ManualControl
from sitl.modes import FlightMode
from sitl.navigator import Navigator
from sitl.offboard import Offboard
from sitl.vehicle_state import Link, VehicleContext

# MAV_CMD_COMPONENT_ARM_DISARM param2 that forces arming/disarming: a magic number of the
# MAVLink spec, with no constant in pymavlink.
_FORCE_ARM_DISARM = 21196
_ARM, _DISARM = 1.0, 0.0
# What PX4 does when setpoints stop in OFFBOARD, per COM_OBL_RC_ACT (a PX4 parameter, no MAVLink
# enum): 3 Return, 4 Land, 6 and 7 terminate (here: disarm); anything else holds.
_OFFBOARD_LOSS_ACTIONS: dict[int, FlightMode | None] = {
    3: FlightMode.RTL,
    4: FlightMode.LAND,
    6: None,
    7: None,
}
# ... and when the ground station's heartbeats stop, per NAV_DLL_ACT: 0 nothing, 1 Hold,
# 2 Return, 3 Land; any other value terminates (here: disarm).
_DATALINK_LOSS_NONE = 0
_DATALINK_LOSS_ACTIONS: dict[int, FlightMode] = {
    1: FlightMode.HOLD,
    2: FlightMode.RTL,
    3: FlightMode.LAND,
}
# NAV_RCL_ACT shares NAV_DLL_ACT's values.
_RC_LOSS_ACTIONS = _DATALINK_LOSS_ACTIONS
# COM_RCL_EXCEPT bits (PX4 LinkLossExceptionBits) and the modes each one spares.
_RCL_EXCEPT_MODES: dict[int, frozenset[FlightMode]] = {
    1 << 0: frozenset([FlightMode.MISSION]),
    1 << 1: frozenset(
        [
            FlightMode.HOLD,
            FlightMode.TAKEOFF,
            FlightMode.LAND,
            FlightMode.RTL,
            FlightMode.FOLLOW_TARGET,
            FlightMode.ORBIT,
        ]
    ),
    1 << 2: frozenset([FlightMode.OFFBOARD]),
}
# COM_LOW_BAT_ACT values that land when the battery is empty (2 Land, 3 Return then land).
_LOW_BATTERY_LANDS = frozenset([2, 3])
# Modes PX4 will not arm in (mode_req_prevent_arming); its health checks say so generically.
_NO_ARMING_MODES = frozenset([FlightMode.ORBIT, FlightMode.FOLLOW_TARGET])
# PX4's commander: throttle stick (zero-centred) above this is "above center" ...
_THROTTLE_ABOVE_CENTER = 0.2
# ... and below this "low".
_THROTTLE_LOW = -0.8


@dataclass(slots=True)
class _ArmRefusal:
    """Injected arm refusals still to come, and the attempt refused last (for retransmissions)."""

    remaining: int = 0
    text: str = PX4_ARMING_DENIED_TEXT
    retry_window_s: float = 2.0
    last_key: tuple[object, ...] | None = None
    last_at_s: float = -math.inf


@dataclass(frozen=True, slots=True)
class DisarmInAir:
    """A disarm while the vehicle was not landed: when [s], its height above the ground [m]
    and PX4's reason (the STATUSTEXT it sent)."""

    time_s: float
    height_m: float
    reason: str


class Commander:
    """Arming, modes and failsafes of one vehicle.

    ``preflight_ready_after_s`` is when the pre-arm checks first pass (estimator converged);
    ``on_home_changed`` is called after DO_SET_HOME moved home (to announce it).
    """

    def __init__(
        self,
        vehicle: VehicleContext,
        *,
        navigator: Navigator,
        offboard: Offboard,
        manual_control: ManualControl,
        flight_tasks: FlightModeManager,
        land_detector: LandDetector,
        preflight_ready_after_s: float,
        on_home_changed: Callable[[], None],
    ) -> None:
        self._vehicle = vehicle
        self._state = vehicle.state
        self._params = vehicle.params
        self._navigator = navigator
        self._offboard = offboard
        self._manual = manual_control
        self._flight_tasks = flight_tasks
        self._land_detector = land_detector
        self.preflight_ready_after_s = preflight_ready_after_s
        self._on_home_changed = on_home_changed
        self._arm_refusal = _ArmRefusal()
        self._armed_at_s = 0.0
        self._flown_since_arm = False
        self._gcs_last_heartbeat_s: float | None = None
        self._gcs_lost = False
        self._rc_lost = False
        self._rc_lost_at_arming = True  # manual control absent when armed: its loss is no news
        self._battery_empty = False
        self._delayed_action: tuple[FlightMode | None, float] | None = None
        #: Every disarm while not landed (forced, a failsafe's, a termination), in order.
        self.disarms_in_air: list[DisarmInAir] = []

    def ready(self, now_s: float) -> bool:
        """Preflight checks pass: estimator converged, a position source works, alive."""
        state = self._state
        return state.alive and now_s >= self.preflight_ready_after_s and state.position_ok

    # ================================================================ messages
    def on_heartbeat(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        """A ground station's or API client's heartbeat keeps the data link alive."""
        if (
            msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
            or msg.get_srcSystem() == self._vehicle.sysid
        ):
            return  # another vehicle, or our own echo: not a ground station / API client
        state = self._state
        self._gcs_last_heartbeat_s = state.now_s
        if self._gcs_lost:
            self._gcs_lost = False
            self._vehicle.statustext(state.now_s, mavlink.MAV_SEVERITY_INFO, "Data link regained")

    def on_set_mode(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if (
            msg.target_system != self._vehicle.sysid
            or not msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        ):
            return
        mode = FlightMode.from_custom_mode(msg.custom_mode)
        if mode is not None:
            self.request_mode(mode)

    # ================================================================ arming
    def deny_arming(self, count: int, text: str, retry_window_s: float) -> None:
        """Refuse the next ``count`` arm attempts with STATUSTEXT ``text`` (added to any
        refusals still pending); see :class:`sitl.config.DenyArmingFault`."""
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count!r}")
        refusal = self._arm_refusal
        refusal.remaining += count
        refusal.text = text
        refusal.retry_window_s = retry_window_s

    @property
    def arm_refusals_pending(self) -> int:
        return self._arm_refusal.remaining

    def _injected_arm_refusal(self, cmd: Command, link: Link, now_s: float) -> bool:
        """Whether an injected health failure refuses this arm command (uses up one refusal
        unless it retransmits the attempt refused last)."""
        refusal = self._arm_refusal
        force = cmd.params[1]
        key = (link.name, cmd.source, cmd.command, None if math.isnan(force) else force)
        window = refusal.retry_window_s
        if window > 0 and key == refusal.last_key and now_s - refusal.last_at_s < window:
            return True
        if refusal.remaining <= 0:
            return False
        refusal.remaining -= 1
        refusal.last_key = key
        refusal.last_at_s = now_s
        return True

    def _stick_arming_denial(self) -> str | None:
        """PX4's arming checks that concern the mode and the sticks (texts as PX4's, tab
        included); None when they pass."""
        mode = self._state.mode
        if mode in _NO_ARMING_MODES:
            return PX4_ARMING_DENIED_TEXT + "\t"
        if not (mode.stick_controlled and self._manual.signal_fresh()):
            return None
        throttle = self._manual.sticks.throttle
        if mode in (FlightMode.POSCTL, FlightMode.ALTCTL):
            if throttle > _THROTTLE_ABOVE_CENTER:
                return "Arming denied: throttle above center\t"
        elif throttle >= _THROTTLE_LOW:
            return "Arming denied: high throttle\t"
        return None

    def _arm(self, now_s: float, reason: str = "external command") -> None:
        self._state.armed = True
        self._armed_at_s = now_s
        self._flown_since_arm = False
        self._state.failsafe_active = False
        self._gcs_lost = False
        self._rc_lost_at_arming = not self._manual.signal_fresh()
        self._rc_lost = self._rc_lost_at_arming
        self._battery_empty = self._state.battery_failed
        self._delayed_action = None
        self._vehicle.statustext(now_s, mavlink.MAV_SEVERITY_INFO, f"Armed by {reason}")
        self.command_physics()

    def _disarm(self, now_s: float, reason: str) -> None:
        if not self._state.landed:
            # Truth, for scoring a flight: the vehicle falls from here.
            height_m = self._vehicle.height_above_ground_m()
            self.disarms_in_air.append(DisarmInAir(now_s, height_m, reason))
        self._state.armed = False
        self._state.landing = False
        self._vehicle.statustext(now_s, mavlink.MAV_SEVERITY_INFO, reason)
        self.command_physics()

    # ================================================================ modes
    def request_mode(self, mode: FlightMode) -> int:
        """A client asks for ``mode``: PX4's acceptance rules, then switch (a MAV_RESULT)."""
        state = self._state
        now = state.now_s
        if mode is state.mode:
            return mavlink.MAV_RESULT_ACCEPTED
        denial = None
        if mode.stick_controlled and not self._manual.signal_fresh():
            # PX4's printRejectMode (the tab marks texts that PX4 also sends as events).
            denial = f"Switching to {mode.display_name} is currently not available\t"
        elif mode is FlightMode.FOLLOW_TARGET and not state.position_ok:
            denial = f"Switching to {mode.display_name} is currently not available\t"
        elif mode is FlightMode.OFFBOARD and not self._offboard.signal_fresh():
            denial = "Switching to Offboard denied: no setpoints"
        elif mode is FlightMode.MISSION and not self._navigator.has_mission:
            denial = "Mission denied: no mission uploaded"
        if denial is not None:
            self._vehicle.statustext(now, mavlink.MAV_SEVERITY_CRITICAL, denial)
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if mode is FlightMode.TAKEOFF:
            self._navigator.request_takeoff(math.nan)
        self._delayed_action = None  # the user takes over from a failsafe's hold
        self.set_mode(mode)
        return mavlink.MAV_RESULT_ACCEPTED

    def set_mode(self, mode: FlightMode, failsafe: bool = False) -> None:
        """Switch to ``mode`` (``failsafe``: as a failsafe action) and start flying it."""
        state = self._state
        previous = state.mode
        state.mode = mode
        state.failsafe_active = failsafe
        self._navigator.mode_changed(previous)
        self.command_physics()

    def command_physics(self) -> None:
        """Hand this vehicle's physics row to whatever flies the current state."""
        state = self._state
        vehicle = self._vehicle
        if not state.alive or state.motors_failed:
            vehicle.motors_off()
            return
        if not state.armed:
            vehicle.motors_off()
            vehicle.physics.velocity_setpoint_ned_m_s[vehicle.index] = 0.0
            return
        if state.mode is FlightMode.OFFBOARD:
            self._offboard.apply()
        elif self._flight_tasks.flies(state.mode):
            self._flight_tasks.activate()
        else:
            self._navigator.enter_mode()

    # ================================================================ per step
    def on_land_event(self, event: LandEvent, now_s: float) -> None:
        """The land detector saw a touchdown or a take-off."""
        if event is LandEvent.TOUCHDOWN:
            if self._state.armed:
                self._vehicle.statustext(now_s, mavlink.MAV_SEVERITY_INFO, "Landing detected")
                self._navigator.on_touchdown()
        else:
            self._flown_since_arm = True
            self._vehicle.statustext(now_s, mavlink.MAV_SEVERITY_INFO, "Takeoff detected")

    def update(self, now_s: float) -> None:
        """Failsafes and auto-disarm at ``now_s`` (called while armed)."""
        self._check_failsafes(now_s)
        self._check_auto_disarm(now_s)

    def _check_failsafes(self, now_s: float) -> None:
        p = self._params
        state = self._state
        statustext = self._vehicle.statustext
        critical = mavlink.MAV_SEVERITY_CRITICAL
        if state.mode is FlightMode.OFFBOARD and not self._offboard.signal_fresh():
            statustext(now_s, critical, "Failsafe activated: offboard control lost")
            action = int(p["COM_OBL_RC_ACT"])
            self._failsafe(_OFFBOARD_LOSS_ACTIONS.get(action, FlightMode.HOLD))
        if (
            self._gcs_last_heartbeat_s is not None
            and not self._gcs_lost
            and now_s - self._gcs_last_heartbeat_s > p["COM_DL_LOSS_T"]
        ):
            self._gcs_lost = True
            statustext(now_s, critical, "Connection to ground station lost")
            action = int(p["NAV_DLL_ACT"])
            if action != _DATALINK_LOSS_NONE:
                self._failsafe(_DATALINK_LOSS_ACTIONS.get(action))
        self._check_manual_control_loss(now_s)
        self._check_battery(now_s)
        if not state.position_ok and not state.landed and state.mode is not FlightMode.LAND:
            statustext(now_s, critical, "Failsafe activated: no position, landing")
            self._failsafe(FlightMode.LAND)
        delayed = self._delayed_action
        if delayed is not None and now_s >= delayed[1]:
            self._delayed_action = None
            statustext(now_s, critical, "Failsafe activated\t")
            self._failsafe(delayed[0])

    def _check_manual_control_loss(self, now_s: float) -> None:
        """PX4: manual control lost for COM_RC_LOSS_T -> NAV_RCL_ACT, unless it was already
        missing at arming (then only once it has come and gone again) or COM_RCL_EXCEPT
        spares the mode."""
        p = self._params
        lost = not self._manual.signal_fresh()
        if not lost:
            self._rc_lost_at_arming = False
        was_lost, self._rc_lost = self._rc_lost, lost
        if not lost or was_lost or self._rc_lost_at_arming:
            return
        if int(p["COM_RC_IN_MODE"]) == 4:
            return
        exceptions = int(p["COM_RCL_EXCEPT"])
        mode = self._state.mode
        if any(exceptions & bit and mode in modes for bit, modes in _RCL_EXCEPT_MODES.items()):
            return
        action = int(p["NAV_RCL_ACT"])
        if action == _DATALINK_LOSS_NONE:
            return
        self._failsafe_after_hold(_RC_LOSS_ACTIONS.get(action), now_s)

    def _check_battery(self, now_s: float) -> None:
        """An empty battery (PX4 SITL: an injected battery failure) in flight lands, per
        COM_LOW_BAT_ACT, after PX4's warnings."""
        state = self._state
        if not state.battery_failed:
            self._battery_empty = False
            return
        if self._battery_empty or state.landed:
            return
        self._battery_empty = True
        statustext = self._vehicle.statustext
        statustext(now_s, mavlink.MAV_SEVERITY_CRITICAL, "Low battery\t")
        if int(self._params["COM_LOW_BAT_ACT"]) in _LOW_BATTERY_LANDS:
            self._failsafe_after_hold(FlightMode.LAND, now_s)
        statustext(now_s, mavlink.MAV_SEVERITY_EMERGENCY, "Emergency battery level\t")

    def _failsafe_after_hold(self, mode: FlightMode | None, now_s: float) -> None:
        """PX4's failsafe framework: a Return or Land action first holds for COM_FAIL_ACT_T
        seconds, in which the user may take over; Hold and Disarm act at once."""
        delay = self._params["COM_FAIL_ACT_T"]
        critical = mavlink.MAV_SEVERITY_CRITICAL
        if mode in (FlightMode.RTL, FlightMode.LAND) and delay > 0.1 and not self._state.landed:
            seconds = int(delay + 0.5)
            self._vehicle.statustext(
                now_s, critical, f"Failsafe activated: entering Hold for {seconds} seconds\t"
            )
            self._delayed_action = (mode, now_s + delay)
            self._failsafe(FlightMode.HOLD)
            return
        self._vehicle.statustext(now_s, critical, "Failsafe activated\t")
        self._failsafe(mode)

    def _failsafe(self, mode: FlightMode | None) -> None:
        """Switch to ``mode`` as a failsafe; None means terminate/disarm."""
        if mode is None:
            self._disarm(self._state.now_s, "Failsafe: disarmed")
            return
        if self._state.landed and mode is not FlightMode.HOLD:
            mode = FlightMode.HOLD
        self.set_mode(mode, failsafe=True)

    def _check_auto_disarm(self, now_s: float) -> None:
        if not self._state.landed:
            return
        p = self._params
        landed_at_s = self._land_detector.landed_at_s
        if self._flown_since_arm:
            timeout, since, reason = p["COM_DISARM_LAND"], landed_at_s, "Disarmed by landing"
        else:
            timeout = p["COM_DISARM_PRFLT"]
            since = max(self._armed_at_s, landed_at_s)
            reason = "Disarmed by auto preflight disarming"
        if timeout >= 0 and now_s - since >= timeout:
            self._disarm(now_s, reason)

    # ================================================================ commands
    def _cmd_arm_disarm(self, cmd: Command, link: Link) -> int:
        p1, p2 = cmd.params[0], cmd.params[1]
        if p1 not in (_ARM, _DISARM):
            return mavlink.MAV_RESULT_DENIED
        return self.arm_disarm(
            arm=p1 == _ARM,
            force=p2 == _FORCE_ARM_DISARM,
            injected_refusal=lambda now_s: self._injected_arm_refusal(cmd, link, now_s),
        )

    def arm_disarm(
        self,
        *,
        arm: bool,
        force: bool,
        injected_refusal: Callable[[float], bool] | None = None,
        reason: str = "external command",
    ) -> int:
        """Arm or disarm as MAV_CMD_COMPONENT_ARM_DISARM asks, with PX4's checks (a MAV_RESULT).
        ``injected_refusal(now_s)`` says whether an injected health failure refuses this arm."""
        state = self._state
        now = state.now_s
        statustext = self._vehicle.statustext
        critical = mavlink.MAV_SEVERITY_CRITICAL
        if arm:
            if state.armed:
                return mavlink.MAV_RESULT_ACCEPTED
            if state.calibrating:  # PX4 checks this before anything else, forced or not
                statustext(now, critical, "Arming denied: calibrating\t")
                return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            if not force:
                if not self.ready(now):
                    why = "estimator not ready" if state.position_ok else "no position"
                    statustext(now, critical, f"Arming denied: {why}")
                    return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                # PX4 arms into OFFBOARD (kept through a disarm) whenever setpoints stream.
                if state.mode is FlightMode.OFFBOARD and not self._offboard.signal_fresh():
                    statustext(now, critical, "Arming denied: no offboard signal")
                    return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                denial = self._stick_arming_denial()
                if denial is not None:
                    statustext(now, critical, denial)
                    return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            if injected_refusal is not None and injected_refusal(now):
                # PX4's commander: mavlink_log_critical(... "\t"), then TRANSITION_DENIED,
                # which the arm command answers with TEMPORARILY_REJECTED.
                statustext(now, critical, self._arm_refusal.text + "\t")
                return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            self._arm(now, reason)
            return mavlink.MAV_RESULT_ACCEPTED
        if not state.armed:
            return mavlink.MAV_RESULT_ACCEPTED
        if not (state.landed or force):
            statustext(now, critical, "Disarming denied: not landed")
            return mavlink.MAV_RESULT_DENIED
        self._disarm(now, f"Disarmed by {reason}")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, cmd: Command, link: Link) -> int:
        """PX4 (1.15 on) switches to TAKEOFF armed or not; the climb, to param 7 (AMSL) or
        MIS_TAKEOFF_ALT above the vehicle, is worked out when it starts armed."""
        self._navigator.request_takeoff(cmd.params[6])
        self.set_mode(FlightMode.TAKEOFF)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_land(self, cmd: Command, link: Link) -> int:
        self.set_mode(FlightMode.LAND)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_rtl(self, cmd: Command, link: Link) -> int:
        self.set_mode(FlightMode.RTL)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_set_mode(self, cmd: Command, link: Link) -> int:
        base, main, sub = cmd.params[0], cmd.params[1], cmd.params[2]
        if not (math.isfinite(base) and math.isfinite(main) and math.isfinite(sub)):
            return mavlink.MAV_RESULT_DENIED
        # Only the custom-mode flag of param 1 matters: its armed bit may lag the real state.
        if not int(base) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mavlink.MAV_RESULT_DENIED
        mode = FlightMode.from_main_sub(int(main), int(sub))
        if mode is None:
            return mavlink.MAV_RESULT_DENIED
        return self.request_mode(mode)

    def _cmd_set_home(self, cmd: Command, link: Link) -> int:
        vehicle = self._vehicle
        p = cmd.params
        if p[0] == 1.0:  # use the current position
            self._state.home_ned_m = list(vehicle.position_ned())
        else:
            if cmd.frame is None:
                lat, lon = p[4], p[5]
            else:
                lat, lon = cmd.x_int * 1e-7, cmd.y_int * 1e-7
            if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(p[6])):
                return mavlink.MAV_RESULT_DENIED
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
                return mavlink.MAV_RESULT_DENIED
            n, e = vehicle.projection.to_local(lat, lon)
            self._state.home_ned_m = [n, e, vehicle.ground_amsl_m - p[6]]
        self._on_home_changed()
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_flight_termination(self, cmd: Command, link: Link) -> int:
        if cmd.params[0] > 0.5:
            self._disarm(self._state.now_s, "Flight termination active")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_pause_continue(self, cmd: Command, link: Link) -> int:
        if cmd.params[0] == 0.0:
            return self.request_mode(FlightMode.HOLD)
        if cmd.params[0] == 1.0:
            return self.request_mode(FlightMode.MISSION)
        return mavlink.MAV_RESULT_DENIED

    def _cmd_mission_start(self, cmd: Command, link: Link) -> int:
        navigator = self._navigator
        if not navigator.has_mission:
            self._vehicle.statustext(
                self._state.now_s, mavlink.MAV_SEVERITY_CRITICAL, "Mission start denied: no mission"
            )
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        first = cmd.params[0]
        if math.isfinite(first) and 0 <= first < len(navigator.mission.items):
            navigator.mission_set_current(int(first))
        return self.request_mode(FlightMode.MISSION)


#: The commands PX4's commander answers (Commander::handle_command).
COMMANDER_COMMANDS: CommandTable[Commander] = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: Commander._cmd_arm_disarm,
    mavlink.MAV_CMD_NAV_TAKEOFF: Commander._cmd_takeoff,
    mavlink.MAV_CMD_NAV_LAND: Commander._cmd_land,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: Commander._cmd_rtl,
    mavlink.MAV_CMD_DO_SET_MODE: Commander._cmd_set_mode,
    mavlink.MAV_CMD_DO_SET_HOME: Commander._cmd_set_home,
    mavlink.MAV_CMD_DO_FLIGHTTERMINATION: Commander._cmd_flight_termination,
    mavlink.MAV_CMD_DO_PAUSE_CONTINUE: Commander._cmd_pause_continue,
    mavlink.MAV_CMD_MISSION_START: Commander._cmd_mission_start,
}
