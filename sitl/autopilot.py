"""PX4 behaviour of one emulated vehicle, as a synchronous state machine.

:class:`Px4Autopilot` is driven by two calls and never waits for anything:

- :meth:`Px4Autopilot.handle_message` with a decoded MAVLink message, the link it came on and
  the simulated time: commands, setpoints, parameter and mission protocol, heartbeats;
- :meth:`Px4Autopilot.update` once per physics step: mode logic (take-off done, landing
  detected, RTL stages, mission items), failsafes (offboard loss, data-link loss, position loss),
  auto-disarm.

It steers the vehicle only by writing setpoints and limits into its row of the shared
:class:`sitl.physics.MulticopterPhysics` arrays, and reads the vehicle's state from the per-step
:class:`Snapshot`. Replies go to the link a request came on; events (STATUSTEXT, parameter
changes, mission progress) go to every link. Anything a client sends that does not make sense is
ignored, as PX4 does; nothing here raises on bad input.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

from sitl import physics as ph
from sitl.commander import COMMANDER_COMMANDS, Commander
from sitl.commands import Command, CommandDispatcher, CommandTable, bind
from sitl.geo import MapProjection
from sitl.land_detector import LandDetector
from sitl.mission import MissionTransfer
from sitl.modes import FlightMode
from sitl.navigator import NAVIGATOR_COMMANDS, Navigator
from sitl.odometry import Odometry
from sitl.offboard import Offboard
from sitl.params import ParamStore
from sitl.telemetry import BUILDABLE, TelemetryBuilder
from sitl.vehicle_state import Link, Snapshot, VehicleContext, VehicleState

__all__ = ["Link", "Px4Autopilot", "Snapshot"]

logger = logging.getLogger(__name__)


class Px4Autopilot:
    """PX4 as its clients see it, for vehicle ``index`` (system id ``index + 1``).

    ``physics``/``odometry``/``snapshot`` are shared by all vehicles; this object touches only
    row ``index``. ``projection`` maps world north/east to latitude/longitude and
    ``ground_amsl_m`` is the altitude of the flat ground. ``unix_epoch_start_us`` is the wall time
    that corresponds to simulated time 0 (for SYSTEM_TIME) unless ``unix_time_us`` gives the
    UNIX time for a simulated time. ``boot_offset_s`` is how long the autopilot had been running
    at simulated time 0: every timestamp it sends is on that boot clock.
    """

    def __init__(
        self,
        index: int,
        *,
        physics: ph.MulticopterPhysics,
        odometry: Odometry,
        snapshot: Snapshot,
        projection: MapProjection,
        ground_amsl_m: float,
        param_overrides: dict[str, float] | None = None,
        preflight_ready_after_s: float = 1.0,
        battery_drain_percent_per_min: float = 1.0,
        unix_epoch_start_us: int = 0,
        unix_time_us: Callable[[float], int] | None = None,
        boot_offset_s: float = 0.0,
    ) -> None:
        self.index = index
        self.sysid = index + 1
        self.compid = 1
        self._physics = physics
        self._odometry = odometry
        self._snap = snapshot
        self._projection = projection
        self.ground_amsl_m = ground_amsl_m
        self.battery_drain_percent_per_min = battery_drain_percent_per_min
        self.unix_epoch_start_us = unix_epoch_start_us
        self._unix_time_us = unix_time_us
        self.boot_offset_s = float(boot_offset_s)
        self.params = ParamStore(param_overrides, on_change=self._param_changed)
        self.params.set_silently("MAV_SYS_ID", self.sysid)
        self._state = VehicleState(home_ned_m=list(map(float, physics.position_ned_m[index])))
        self._vehicle = VehicleContext(
            index,
            state=self._state,
            params=self.params,
            physics=physics,
            odometry=odometry,
            snapshot=snapshot,
            projection=projection,
            ground_amsl_m=ground_amsl_m,
        )
        self.telemetry = TelemetryBuilder(self)
        self.battery_remaining_pct = 100.0

        self._last_update_s = 0.0

        self._cache_step = -1
        self._cache_global: tuple[float, float, float] = (0.0, 0.0, 0.0)

        self._offboard = Offboard(self._vehicle)
        self._land_detector = LandDetector(self._vehicle)
        self._navigator = Navigator(self._vehicle, set_mode=self._set_mode)
        self.mission: MissionTransfer = self._navigator.mission
        self._commander = Commander(
            self._vehicle,
            navigator=self._navigator,
            offboard=self._offboard,
            land_detector=self._land_detector,
            preflight_ready_after_s=preflight_ready_after_s,
            on_home_changed=self._announce_home,
        )

        self._commands = CommandDispatcher(
            self._vehicle,
            [
                bind(self._commander, COMMANDER_COMMANDS),
                bind(self._navigator, NAVIGATOR_COMMANDS),
                bind(self, AUTOPILOT_COMMANDS),
            ],
        )
        self._message_handlers: dict[str, Callable[[mavlink.MAVLink_message, Link], None]] = {
            "HEARTBEAT": self._commander.on_heartbeat,
            "COMMAND_LONG": self._commands.on_command_long,
            "COMMAND_INT": self._commands.on_command_int,
            "SET_MODE": self._commander.on_set_mode,
            "SET_POSITION_TARGET_LOCAL_NED": self._offboard.on_position_target_local,
            "SET_POSITION_TARGET_GLOBAL_INT": self._offboard.on_position_target_global,
            "SET_ATTITUDE_TARGET": self._offboard.on_attitude_target,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "PING": self._on_ping,
            "TIMESYNC": self._on_timesync,
        }
        for kind in (
            "MISSION_COUNT",
            "MISSION_ITEM_INT",
            "MISSION_ITEM",
            "MISSION_REQUEST_LIST",
            "MISSION_REQUEST_INT",
            "MISSION_REQUEST",
            "MISSION_CLEAR_ALL",
            "MISSION_SET_CURRENT",
            "MISSION_ACK",
        ):
            self._message_handlers[kind] = self._on_mission_message
        self._navigator.apply_limits()
        self._commander.command_physics()

    # ================================================================ state access
    @property
    def alive(self) -> bool:
        return self._state.alive

    @property
    def armed(self) -> bool:
        return self._state.armed

    @property
    def mode(self) -> FlightMode:
        return self._state.mode

    @property
    def landed(self) -> bool:
        return self._state.landed

    @property
    def landed_state(self) -> int:
        """MAV_LANDED_STATE as of the last :meth:`update`."""
        return self._state.landed_state

    @property
    def failsafe_active(self) -> bool:
        return self._state.failsafe_active

    @property
    def flow_ok(self) -> bool:
        return self._state.flow_ok

    @property
    def gps_ok(self) -> bool:
        return self._state.gps_ok

    @property
    def position_ok(self) -> bool:
        return self._state.position_ok

    @property
    def rejected_setpoints(self) -> int:
        """Offboard setpoints ignored as implausible so far."""
        return self._offboard.rejected_setpoints

    @property
    def links(self) -> list[Link]:
        """Where this vehicle's messages go (set by whoever owns the links)."""
        return self._vehicle.links

    @links.setter
    def links(self, links: list[Link]) -> None:
        self._vehicle.links = links

    @property
    def status_log(self) -> deque[tuple[float, str]]:
        """The latest STATUSTEXTs as (time_s, text), for observers (tests, a world module)."""
        return self._vehicle.status_log

    @property
    def on_statustext(self) -> Callable[[float, int, str], None] | None:
        """Called with (time_s, severity, text) for every STATUSTEXT."""
        return self._vehicle.on_statustext

    @on_statustext.setter
    def on_statustext(self, observer: Callable[[float, int, str], None] | None) -> None:
        self._vehicle.on_statustext = observer

    @property
    def preflight_ready_after_s(self) -> float:
        return self._commander.preflight_ready_after_s

    def ready(self, now_s: float) -> bool:
        """Preflight checks pass: estimator converged, a position source works, alive."""
        return self._commander.ready(now_s)

    def boot_time_s(self, now_s: float) -> float:
        """The autopilot's boot clock at simulated time ``now_s``."""
        return now_s + self.boot_offset_s

    def time_boot_ms(self, now_s: float) -> int:
        return int((now_s + self.boot_offset_s) * 1000.0) & 0xFFFFFFFF

    def time_usec(self, now_s: float) -> int:
        return int((now_s + self.boot_offset_s) * 1e6)

    def unix_time_us(self, now_s: float) -> int:
        if self._unix_time_us is not None:
            return self._unix_time_us(now_s)
        return self.unix_epoch_start_us + int(now_s * 1e6)

    def position_ned(self) -> list[float]:
        """True world NED position, m."""
        return self._vehicle.position_ned()

    def velocity_ned(self) -> list[float]:
        return self._vehicle.velocity_ned()

    def attitude(self) -> tuple[float, float, float, float]:
        """(roll, pitch, yaw, yaw rate), rad and rad/s."""
        return self._vehicle.attitude()

    def reported_position_ned(self) -> list[float]:
        """World NED position the vehicle reports as its own: the truth plus the GPS/EKF
        error (see :mod:`sitl.gnss`)."""
        pos = self._snap.position_ned_m[self.index]
        errors = self._snap.gps_error_ned_m
        if errors is None:
            return pos
        err = errors[self.index]
        return [pos[0] + err[0], pos[1] + err[1], pos[2] + err[2]]

    def global_position(self) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude AMSL m) the vehicle reports: the true
        position plus the GPS/EKF error."""
        if self._cache_step != self._snap.step_id:
            n, e, d = self.reported_position_ned()
            lat, lon = self._projection.to_global(n, e)
            self._cache_global = (lat, lon, self.ground_amsl_m - d)
            self._cache_step = self._snap.step_id
        return self._cache_global

    def true_global_position(self) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude AMSL m) of the true position."""
        n, e, d = self.position_ned()
        lat, lon = self._projection.to_global(n, e)
        return lat, lon, self.ground_amsl_m - d

    def altitude_above_home_m(self) -> float:
        return self._vehicle.altitude_above_home_m()

    def reported_altitude_above_home_m(self) -> float:
        return self._state.home_ned_m[2] - self.reported_position_ned()[2]

    def truth_rates(self) -> tuple[float, float, float, list[float], list[float]]:
        """Body rates (roll, pitch, yaw; rad/s, FRD), NED acceleration (m/s^2) and the wind
        (NED m/s) of the true state, for the ground-truth stream."""
        i = self.index
        phys = self._physics
        roll, pitch, _, yaw_rate = self.attitude()
        roll_rate = float(phys.roll_rate_rad_s[i])
        pitch_rate = float(phys.pitch_rate_rad_s[i])
        sr, cr = math.sin(roll), math.cos(roll)
        sp, cp = math.sin(pitch), math.cos(pitch)
        p = roll_rate - yaw_rate * sp
        q = pitch_rate * cr + yaw_rate * sr * cp
        r = -pitch_rate * sr + yaw_rate * cr * cp
        accel = [float(v) for v in phys.acceleration_ned_m_s2[i]]
        wind = phys.wind
        wind_ned = [0.0, 0.0, 0.0] if wind is None else [float(v) for v in wind.velocity_ned_m_s[i]]
        return p, q, r, accel, wind_ned

    def height_above_ground_m(self) -> float:
        return self._vehicle.height_above_ground_m()

    def home_global(self) -> tuple[float, float, float]:
        n, e, d = self._state.home_ned_m
        lat, lon = self._projection.to_global(n, e)
        return lat, lon, self.ground_amsl_m - d

    def home_local_ned(self) -> tuple[float, float, float]:
        origin = self._odometry.origin_ned_m[self.index]
        n, e, d = self._state.home_ned_m
        return float(n - origin[0]), float(e - origin[1]), float(d - origin[2])

    def local_origin_global(self) -> tuple[float, float, float]:
        n, e, d = (float(v) for v in self._odometry.origin_ned_m[self.index])
        lat, lon = self._projection.to_global(n, e)
        return lat, lon, self.ground_amsl_m - d

    def odometry_sample(self) -> tuple[float, float, float, float, float, float]:
        i = self.index
        s = self._snap
        return self._odometry.sample(
            i, s.position_ned_m[i], s.velocity_ned_m_s[i], s.drift_ned_m[i]
        )

    def battery_voltage_mv(self) -> int:
        cells = int(self.params["BAT1_N_CELLS"])
        per_cell = 3.5 + 0.7 * self.battery_remaining_pct / 100.0
        return round(per_cell * cells * 1000)

    def mission_status(self) -> tuple[int, int, int, int]:
        """MISSION_CURRENT fields (seq, total, mission_state, mission_mode)."""
        return self._navigator.mission_status()

    # ================================================================ faults
    def kill(self, now_s: float) -> None:
        """The autopilot dies: motors stop, nothing is sent or answered from now on."""
        if not self._state.alive:
            return
        self._state.alive = False
        self._vehicle.motors_off()
        logger.info("vehicle %d killed at %.2f s", self.sysid, now_s)

    def set_sensor(self, sensor: str, ok: bool, now_s: float) -> None:
        """Fail (``ok=False``) or restore the ``"flow"`` odometry or the ``"gps"`` receiver."""
        if sensor == "flow":
            if self._state.flow_ok != ok:
                self._state.flow_ok = ok
                self._vehicle.statustext(
                    now_s,
                    mavlink.MAV_SEVERITY_WARNING if not ok else mavlink.MAV_SEVERITY_INFO,
                    "Optical flow lost" if not ok else "Optical flow regained",
                )
        elif sensor == "gps":
            if self._state.gps_ok != ok:
                self._state.gps_ok = ok
                self._vehicle.statustext(
                    now_s,
                    mavlink.MAV_SEVERITY_WARNING if not ok else mavlink.MAV_SEVERITY_INFO,
                    "GPS lost" if not ok else "GPS regained",
                )
        else:
            raise ValueError(f"unknown sensor {sensor!r}; use 'flow' or 'gps'")

    def deny_arming(self, count: int, text: str, retry_window_s: float) -> None:
        """Refuse the next ``count`` arm attempts with STATUSTEXT ``text`` (added to any
        refusals still pending); see :class:`sitl.config.DenyArmingFault`."""
        self._commander.deny_arming(count, text, retry_window_s)

    @property
    def arm_refusals_pending(self) -> int:
        return self._commander.arm_refusals_pending

    # ================================================================ messages in
    def handle_message(self, msg: mavlink.MAVLink_message, link: Link, now_s: float) -> None:
        """React to one decoded message received on ``link``."""
        if not self._state.alive:
            return
        self._state.now_s = now_s
        handler = self._message_handlers.get(msg.get_type())
        if handler is not None:
            handler(msg, link)

    def _on_ping(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            link.send(
                mavlink.MAVLink_ping_message(
                    msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )

    def _on_timesync(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if msg.tc1 == 0:
            boot_ns = int(self.boot_time_s(self._state.now_s) * 1e9)
            link.send(mavlink.MAVLink_timesync_message(boot_ns, msg.ts1))

    def _on_mission_message(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        self.mission.handle(msg, link, self._state.now_s)

    # ---------------------------------------------------------------- params
    def _on_param_request_list(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if not self._vehicle.is_for_me(msg):
            return
        for name in self.params:
            link.send(self._param_value(name))

    def _on_param_request_read(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if not self._vehicle.is_for_me(msg):
            return
        names = self.params
        if msg.param_index >= 0:
            if msg.param_index >= len(names):
                return
            name = list(names)[msg.param_index]
        else:
            name = _param_name(msg.param_id)
            if name not in names:
                return  # PX4 stays silent about unknown names
        link.send(self._param_value(name))

    def _on_param_set(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if not self._vehicle.is_for_me(msg):
            return
        name = _param_name(msg.param_id)
        if name not in self.params:
            self._vehicle.statustext(
                self._state.now_s, mavlink.MAV_SEVERITY_WARNING, f"Unknown parameter {name[:24]}"
            )
            return
        if name in ("MAV_SYS_ID", "MAV_COMP_ID"):
            pass  # changing ids needs a reboot on PX4 too; echo the value in use
        else:
            try:
                value = self.params.decode_wire_value(name, msg.param_value, msg.param_type)
                self.params.set(name, value)
            except (ValueError, OverflowError) as exc:
                self._vehicle.statustext(
                    self._state.now_s, mavlink.MAV_SEVERITY_WARNING, f"Param {name} rejected"
                )
                logger.info("vehicle %d: PARAM_SET %s rejected: %s", self.sysid, name, exc)
        # PX4 announces the (possibly unchanged) value on every link.
        self._vehicle.broadcast(self._param_value(name))

    def _param_value(self, name: str) -> mavlink.MAVLink_message:
        value, mav_type = self.params.wire_value(name)
        return mavlink.MAVLink_param_value_message(
            name.encode(), value, mav_type, len(self.params), self.params.index_of(name)
        )

    def _param_changed(self, name: str, value: float) -> None:
        self._navigator.apply_limits()

    # -------------------------------------------------------------- commands
    def _cmd_get_home_position(self, cmd: Command, link: Link) -> int:
        self._commands.then(lambda: self._send_built(mavlink.MAVLINK_MSG_ID_HOME_POSITION, link))
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, cmd: Command, link: Link) -> int:
        msg_id = cmd.params[0]
        if not math.isfinite(msg_id) or not 0 <= msg_id < 2**24:
            return mavlink.MAV_RESULT_DENIED
        interval = link.streams.interval_us(int(msg_id)) if int(msg_id) in BUILDABLE else 0
        self._commands.then(
            lambda: link.send(mavlink.MAVLink_message_interval_message(int(msg_id), interval))
        )
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_set_message_interval(self, cmd: Command, link: Link) -> int:
        msg_id, interval_us = cmd.params[0], cmd.params[1]
        if not (math.isfinite(msg_id) and 0 <= msg_id < 2**24):
            return mavlink.MAV_RESULT_DENIED
        ok = link.streams.set_interval(int(msg_id), interval_us, self._state.now_s)
        return mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED

    def _cmd_request_message(self, cmd: Command, link: Link) -> int:
        msg_id = cmd.params[0]
        if not (math.isfinite(msg_id) and int(msg_id) in BUILDABLE):
            return mavlink.MAV_RESULT_DENIED
        msg = self.telemetry.build(int(msg_id), self._state.now_s)
        if msg is None:
            return mavlink.MAV_RESULT_FAILED
        self._commands.then(lambda: link.send(msg))
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_request_autopilot_capabilities(self, cmd: Command, link: Link) -> int:
        self._commands.then(
            lambda: self._send_built(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, link)
        )
        return mavlink.MAV_RESULT_ACCEPTED

    # ================================================================ per step
    def update(self, now_s: float) -> None:
        """Advance mode logic, failsafes and timers to ``now_s`` (call once per step)."""
        if not self._state.alive:
            return
        self._state.now_s = now_s
        event = self._land_detector.update(now_s, taking_off=self._navigator.taking_off)
        if event is not None:
            self._commander.on_land_event(event, now_s)
        dt_s = max(now_s - self._last_update_s, 0.0)
        self._last_update_s = now_s
        if self._state.armed:
            self.battery_remaining_pct = max(
                0.0, self.battery_remaining_pct - self.battery_drain_percent_per_min * dt_s / 60.0
            )
            self._navigator.update(now_s)
            self._commander.update(now_s)
        self.mission.update(now_s)

    # ================================================================ output
    def _set_mode(self, mode: FlightMode, failsafe: bool = False) -> None:
        """The navigator's way to the commander's mode switch."""
        self._commander.set_mode(mode, failsafe)

    def _announce_home(self) -> None:
        msg = self.telemetry.build(mavlink.MAVLINK_MSG_ID_HOME_POSITION, self._state.now_s)
        if msg is not None:
            self._vehicle.broadcast(msg)

    def _send_built(self, msg_id: int, link: Link) -> None:
        msg = self.telemetry.build(msg_id, self._state.now_s)
        if msg is not None:
            link.send(msg)


#: MAV_CMD -> the autopilot's handler.
AUTOPILOT_COMMANDS: CommandTable[Px4Autopilot] = {
    mavlink.MAV_CMD_GET_HOME_POSITION: Px4Autopilot._cmd_get_home_position,
    mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: Px4Autopilot._cmd_get_message_interval,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: Px4Autopilot._cmd_set_message_interval,
    mavlink.MAV_CMD_REQUEST_MESSAGE: Px4Autopilot._cmd_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: (
        Px4Autopilot._cmd_request_autopilot_capabilities
    ),
}


def _param_name(param_id: str | bytes) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", errors="replace")
    return param_id.split("\x00", 1)[0]
