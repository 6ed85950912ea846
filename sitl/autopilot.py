"""PX4 behaviour of one emulated vehicle, as a synchronous state machine.

:class:`Px4Autopilot` is driven by two calls and never waits for anything:

- :meth:`Px4Autopilot.handle_message` with a decoded MAVLink message, the link it came on and
  the simulated time: commands, setpoints, parameter and mission protocol, heartbeats;
- :meth:`Px4Autopilot.update` once per physics step: mode logic (take-off done, landing
  detected, RTL stages, mission items), failsafes (offboard loss, data-link loss, position loss),
  auto-disarm.

It is the façade the emulator, the telemetry builder and the tests use; the behaviour lives in
parts split the way PX4 splits its modules, which share one
:class:`sitl.vehicle_state.VehicleContext`:

- :mod:`sitl.mavlink_receiver`: routes each message; parameters, PING, TIMESYNC, message requests;
- :mod:`sitl.commands`: COMMAND_LONG/INT -> handler tables -> COMMAND_ACK;
- :mod:`sitl.commander`: arming, mode switching, failsafes, auto-disarm;
- :mod:`sitl.navigator`: TAKEOFF, HOLD/reposition, LAND, RTL, MISSION;
- :mod:`sitl.offboard`: offboard setpoints and their timeout;
- :mod:`sitl.flight_mode_manager`: the flight tasks of the modes the navigator does not fly:
  the stick modes (:mod:`sitl.manual_control`, MANUAL_CONTROL input), ORBIT
  (:mod:`sitl.orbit`, MAV_CMD_DO_ORBIT), FOLLOW_TARGET (:mod:`sitl.follow_target`,
  FOLLOW_TARGET input);
- :mod:`sitl.failure_injection`: SYS_FAILURE_EN and MAV_CMD_INJECT_FAILURE, and the same
  failures for the emulator's fault API;
- :mod:`sitl.calibration`: MAV_CMD_PREFLIGHT_CALIBRATION and its "[cal]" progress texts;
- :mod:`sitl.land_detector`: landed / in air.

The parts steer the vehicle only by writing setpoints and limits into its row of the shared
:class:`sitl.physics.MulticopterPhysics` arrays, and read the vehicle's state from the per-step
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

from sitl import imu
from sitl import physics as ph
from sitl.calibration import CALIBRATION_COMMANDS, Calibration
from sitl.commander import Commander, DisarmInAir
from sitl.commands import bind
from sitl.config import FlightLogConfig
from sitl.failure_injection import FAILURE_COMMANDS, FailureInjector, LinkSwitch
from sitl.flight_log import FlightLogger, FlightLogStore
from sitl.flight_mode_manager import FlightModeManager
from sitl.follow_target import FollowTarget
from sitl.ftp import FileSystem, static_directory
from sitl.geo import MapProjection
from sitl.land_detector import LandDetector
from sitl.manual_control import ManualControl, StickFlight
from sitl.mavlink_receiver import MavlinkReceiver
from sitl.mission import MissionTransfer
from sitl.modes import FlightMode
from sitl.navigator import Navigator
from sitl.odometry import Odometry
from sitl.offboard import Offboard, OffboardSetpoint
from sitl.orbit import ORBIT_COMMANDS, Orbit
from sitl.params import ParamStore, pack_param_pck
from sitl.telemetry import TelemetryBuilder
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
    ``ftp_ardupilot_extensions`` adds what ArduPilot's FTP server does beyond PX4's
    (:class:`sitl.config.FtpConfig`); ``flight_logs`` says how to record the flight logs (None:
    not at all).
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
        ftp_ardupilot_extensions: bool = False,
        flight_logs: FlightLogConfig | None = None,
    ) -> None:
        self.index = index
        self.ground_amsl_m = ground_amsl_m
        self.unix_epoch_start_us = unix_epoch_start_us
        self._unix_time_us = unix_time_us
        self.boot_offset_s = float(boot_offset_s)
        self.params = ParamStore(param_overrides, on_change=self._param_changed)
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
        self.sysid = self._vehicle.sysid
        self.compid = self._vehicle.compid
        self.params.set_silently("MAV_SYS_ID", self.sysid)
        self.telemetry = TelemetryBuilder(self)
        self._init_battery_and_sensors(battery_drain_percent_per_min)
        self._init_flight_modes()
        self._init_commander(preflight_ready_after_s)
        self._init_flight_logs(flight_logs)
        self._init_mavlink(ftp_ardupilot_extensions)
        self._navigator.apply_limits()
        self._commander.command_physics()

    def _init_battery_and_sensors(self, battery_drain_percent_per_min: float) -> None:
        """The battery (drained by :meth:`update`), the magnetometer's earth field at home and
        the per-step cache of the global position."""
        self.battery_drain_percent_per_min = battery_drain_percent_per_min
        self._battery_pct = 100.0
        self._last_update_s = 0.0
        home_latitude_deg, _ = self._vehicle.projection.to_global(*self._state.home_ned_m[:2])
        self._earth_field_ned_gauss = imu.earth_field_ned_gauss(home_latitude_deg)
        self._cache_step = -1
        self._cache_global: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def _init_flight_modes(self) -> None:
        """What flies each mode: offboard, the navigator's modes (and its mission), the stick
        modes, orbit and follow target; the flight tasks pick the one of the mode in force."""
        vehicle = self._vehicle
        self._offboard = Offboard(vehicle)
        self._land_detector = LandDetector(vehicle)
        self._navigator = Navigator(vehicle, set_mode=self._set_mode)
        self.mission: MissionTransfer = self._navigator.mission
        self._manual_control = ManualControl(vehicle)
        stick_flight = StickFlight(vehicle, self._manual_control)
        self.orbit = Orbit(vehicle, set_mode=self._set_mode)
        self.follow_target = FollowTarget(vehicle)
        self._flight_tasks = FlightModeManager(
            vehicle,
            {
                FlightMode.POSCTL: stick_flight,
                FlightMode.ALTCTL: stick_flight,
                FlightMode.STABILIZED: stick_flight,
                FlightMode.MANUAL: stick_flight,
                FlightMode.ORBIT: self.orbit,
                FlightMode.FOLLOW_TARGET: self.follow_target,
            },
        )

    def _init_commander(self, preflight_ready_after_s: float) -> None:
        """The commander over the flight modes (arming, mode switches, failsafes), calibration
        and failure injection."""
        vehicle = self._vehicle
        self._commander = Commander(
            vehicle,
            navigator=self._navigator,
            offboard=self._offboard,
            manual_control=self._manual_control,
            flight_tasks=self._flight_tasks,
            land_detector=self._land_detector,
            preflight_ready_after_s=preflight_ready_after_s,
            on_home_changed=self._announce_home,
        )
        self._calibration = Calibration(vehicle)
        self._failures = FailureInjector(
            vehicle,
            set_sensor=self.set_sensor,
            manual_control=self._manual_control,
            on_motors=self._motors_changed,
        )

    def _init_flight_logs(self, flight_logs: FlightLogConfig | None) -> None:
        """The flight log store (listed over FTP) and its logger, if logs are recorded."""
        self.flight_logs = FlightLogStore(flight_logs.max_logs if flight_logs else 1)
        self._flight_logger = (
            FlightLogger(
                self,
                self.params,
                self.flight_logs,
                rate_hz=flight_logs.rate_hz,
                max_log_bytes=flight_logs.max_log_bytes,
            )
            if flight_logs is not None and flight_logs.enabled
            else None
        )

    def _init_mavlink(self, ftp_ardupilot_extensions: bool) -> None:
        """The MAVLink side: the receiver that routes every message to the part it is for, the
        STATUSTEXT observer, and the external vision received."""
        #: External vision (ODOMETRY) received: how many, and the last. PX4 hands it to EKF2 when
        #: EKF2_EV_CTRL asks; the emulator's odometry model does not fuse it (kept for checks).
        self.external_vision_received = 0
        self.external_vision: mavlink.MAVLink_odometry_message | None = None
        self._statustext_observer: Callable[[float, int, str], None] | None = None
        self._vehicle.on_statustext = self._on_statustext
        self._receiver = MavlinkReceiver(
            self._vehicle,
            commander=self._commander,
            navigator=self._navigator,
            offboard=self._offboard,
            telemetry=self.telemetry,
            boot_time_s=self.boot_time_s,
            files=self._file_system(ftp_ardupilot_extensions),
            ftp_echo_session=ftp_ardupilot_extensions,
            flight_logs=self.flight_logs,
            handlers={
                "MANUAL_CONTROL": self._manual_control.on_manual_control,
                "FOLLOW_TARGET": self.follow_target.on_follow_target,
                "ODOMETRY": self._on_external_vision,
            },
            command_tables=[
                bind(self.orbit, ORBIT_COMMANDS),
                bind(self._failures, FAILURE_COMMANDS),
                bind(self._calibration, CALIBRATION_COMMANDS),
            ],
        )
        self._receiver.shell.pxh.commands["failure"] = self._failures.shell_command

    # ================================================================ state
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
    def battery_remaining_pct(self) -> float:
        """State of charge, %: 0 while an injected battery failure lasts (PX4 SITL's battery
        simulator reads empty then)."""
        return 0.0 if self._state.battery_failed else self._battery_pct

    @battery_remaining_pct.setter
    def battery_remaining_pct(self, percent: float) -> None:
        self._battery_pct = percent

    @property
    def calibrating(self) -> bool:
        """A calibration runs (PX4: MAV_STATE_CALIBRATING, arming denied)."""
        return self._state.calibrating

    @property
    def motors_failed(self) -> bool:
        return self._state.motors_failed

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
    def param_sets_rejected(self) -> int:
        """PARAM_SETs refused so far (unknown name, value out of range)."""
        return self._receiver.param_rejections.count

    @property
    def accepted_setpoints(self) -> int:
        """Offboard setpoints taken so far (a client can tell when one has arrived)."""
        return self._offboard.accepted_setpoints

    def add_setpoint_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` after every offboard setpoint taken (from the datagram handler,
        synchronously: a client waiting for one sets its event there instead of polling)."""
        self._offboard.setpoint_listeners.append(listener)

    def remove_setpoint_listener(self, listener: Callable[[], None]) -> None:
        self._offboard.setpoint_listeners.remove(listener)

    @property
    def offboard_setpoint(self) -> OffboardSetpoint | None:
        """The latest offboard setpoint taken, in the vehicle's own units (simulated seconds)."""
        return self._offboard.setpoint

    @property
    def preflight_ready_after_s(self) -> float:
        return self._commander.preflight_ready_after_s

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
        return self._statustext_observer

    @on_statustext.setter
    def on_statustext(self, observer: Callable[[float, int, str], None] | None) -> None:
        self._statustext_observer = observer

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
        snapshot = self._vehicle.snapshot
        pos = snapshot.position_ned_m[self.index]
        errors = snapshot.gps_error_ned_m
        if errors is None:
            return pos
        err = errors[self.index]
        return [pos[0] + err[0], pos[1] + err[1], pos[2] + err[2]]

    def global_position(self) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude AMSL m) the vehicle reports: the true
        position plus the GPS/EKF error."""
        if self._cache_step != self._vehicle.snapshot.step_id:
            n, e, d = self.reported_position_ned()
            lat, lon = self._vehicle.projection.to_global(n, e)
            self._cache_global = (lat, lon, self.ground_amsl_m - d)
            self._cache_step = self._vehicle.snapshot.step_id
        return self._cache_global

    def true_global_position(self) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude AMSL m) of the true position."""
        n, e, d = self.position_ned()
        lat, lon = self._vehicle.projection.to_global(n, e)
        return lat, lon, self.ground_amsl_m - d

    def altitude_above_home_m(self) -> float:
        return self._vehicle.altitude_above_home_m()

    def reported_altitude_above_home_m(self) -> float:
        return self._state.home_ned_m[2] - self.reported_position_ned()[2]

    def truth_rates(self) -> tuple[float, float, float, list[float], list[float]]:
        """Body rates (roll, pitch, yaw; rad/s, FRD), NED acceleration (m/s^2) and the wind
        (NED m/s) of the true state, for the ground-truth stream."""
        i = self.index
        phys = self._vehicle.physics
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

    def inertial_frd(self) -> tuple[imu.Vector3, imu.Vector3, imu.Vector3]:
        """What the vehicle's IMU and magnetometer read: specific force (m/s^2), body rates
        (rad/s) and the earth's field (gauss), all in the body frame FRD (see :mod:`sitl.imu`)."""
        i = self.index
        s = self._vehicle.snapshot
        roll, pitch, yaw = s.roll_rad[i], s.pitch_rad[i], s.yaw_rad[i]
        an, ae, ad = s.acceleration_ned_m_s2[i]
        force = imu.specific_force_frd((an, ae, ad), roll, pitch, yaw)
        rates = imu.body_rates_frd(
            roll, pitch, s.roll_rate_rad_s[i], s.pitch_rate_rad_s[i], s.yaw_rate_rad_s[i]
        )
        field = imu.ned_to_frd(self._earth_field_ned_gauss, roll, pitch, yaw)
        return force, rates, field

    def height_above_ground_m(self) -> float:
        return self._vehicle.height_above_ground_m()

    def home_global(self) -> tuple[float, float, float]:
        n, e, d = self._state.home_ned_m
        lat, lon = self._vehicle.projection.to_global(n, e)
        return lat, lon, self.ground_amsl_m - d

    def home_local_ned(self) -> tuple[float, float, float]:
        origin = self._vehicle.odometry.origin_ned_m[self.index]
        n, e, d = self._state.home_ned_m
        return float(n - origin[0]), float(e - origin[1]), float(d - origin[2])

    def local_origin_global(self) -> tuple[float, float, float]:
        n, e, d = (float(v) for v in self._vehicle.odometry.origin_ned_m[self.index])
        lat, lon = self._vehicle.projection.to_global(n, e)
        return lat, lon, self.ground_amsl_m - d

    def odometry_sample(self) -> tuple[float, float, float, float, float, float]:
        i = self.index
        s = self._vehicle.snapshot
        return self._vehicle.odometry.sample(
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

    def pilot_takeover(self, mode: FlightMode, now_s: float) -> None:
        """A pilot flips the RC mode switch to ``mode``: PX4's commander switches at once,
        whatever a ground station or offboard computer was doing."""
        if not self._state.alive:
            return
        logger.info("vehicle %d: pilot takes over in %s at %.2f s", self.sysid, mode.name, now_s)
        self._commander.set_mode(mode)

    def ground_station_arm(self, *, arm: bool, force: bool, now_s: float) -> int:
        """Another ground station (or a pilot's radio) arms or disarms the vehicle as
        MAV_CMD_COMPONENT_ARM_DISARM would (``force``: param2 21196), through PX4's checks.
        Returns the MAV_RESULT it would have been answered with."""
        if not self._state.alive:
            return mavlink.MAV_RESULT_DENIED
        result = self._commander.arm_disarm(arm=arm, force=force)
        logger.info(
            "vehicle %d: %s%s by another ground station at %.2f s: result %d",
            self.sysid,
            "forced " if force else "",
            "arm" if arm else "disarm",
            now_s,
            result,
        )
        return result

    @property
    def disarms_in_air(self) -> list[DisarmInAir]:
        """Every disarm while not landed (truth, for scoring): time, height, PX4's reason."""
        return list(self._commander.disarms_in_air)

    def set_sensor(self, sensor: str, ok: bool, now_s: float) -> None:
        """Fail (``ok=False``) or restore the ``"flow"`` odometry or the ``"gps"`` receiver."""
        state = self._state
        severity = mavlink.MAV_SEVERITY_INFO if ok else mavlink.MAV_SEVERITY_WARNING
        if sensor == "flow":
            if state.flow_ok != ok:
                state.flow_ok = ok
                text = "Optical flow regained" if ok else "Optical flow lost"
                self._vehicle.statustext(now_s, severity, text)
        elif sensor == "gps":
            if state.gps_ok != ok:
                state.gps_ok = ok
                self._vehicle.statustext(now_s, severity, "GPS regained" if ok else "GPS lost")
        else:
            raise ValueError(f"unknown sensor {sensor!r}; use 'flow' or 'gps'")

    def inject_failure(self, unit: int, failure_type: int, instance: int = 0) -> bool:
        """Inject a PX4 failure (FAILURE_UNIT_*, FAILURE_TYPE_*; type OK ends it) as
        MAV_CMD_INJECT_FAILURE would, whatever SYS_FAILURE_EN; False if unsupported (see
        :mod:`sitl.failure_injection`)."""
        if not self._state.alive:
            return False
        return self._failures.inject(unit, failure_type, instance)

    def failure_supported(self, unit: int, failure_type: int, instance: int = 0) -> bool:
        return self._failures.supported(unit, failure_type, instance)

    @property
    def link_switch(self) -> LinkSwitch | None:
        """Turns every link of this vehicle on (True) or off, for the mavlink_signal failure;
        set by whoever owns the links."""
        return self._failures.link_switch

    @link_switch.setter
    def link_switch(self, switch: LinkSwitch | None) -> None:
        self._failures.link_switch = switch

    def deny_arming(self, count: int, text: str, retry_window_s: float) -> None:
        """Refuse the next ``count`` arm attempts with STATUSTEXT ``text`` (added to any
        refusals still pending); see :class:`sitl.config.DenyArmingFault`."""
        self._commander.deny_arming(count, text, retry_window_s)

    @property
    def arm_refusals_pending(self) -> int:
        return self._commander.arm_refusals_pending

    # ================================================================ driving
    def handle_message(self, msg: mavlink.MAVLink_message, link: Link, now_s: float) -> None:
        """React to one decoded message received on ``link``."""
        if not self._state.alive:
            return
        self._state.now_s = now_s
        self._receiver.handle(msg, link)

    def update(self, now_s: float) -> None:
        """Advance mode logic, failsafes and timers to ``now_s`` (call once per step)."""
        state = self._state
        if not state.alive:
            return
        state.now_s = now_s
        event = self._land_detector.update(now_s, taking_off=self._navigator.taking_off)
        if event is not None:
            self._commander.on_land_event(event, now_s)
        dt_s = max(now_s - self._last_update_s, 0.0)
        self._last_update_s = now_s
        if state.armed:
            self._battery_pct = max(
                0.0, self._battery_pct - self.battery_drain_percent_per_min * dt_s / 60.0
            )
            self._navigator.update(now_s)
            self._flight_tasks.update(now_s)
            self._commander.update(now_s)
        self.mission.update(now_s)
        self._calibration.update(now_s)
        if self._flight_logger is not None:
            self._flight_logger.update(now_s)
        self._receiver.pump()

    # ================================================================ wiring
    def _on_external_vision(self, msg: mavlink.MAVLink_message, _link: Link) -> None:
        self.external_vision_received += 1
        self.external_vision = msg

    def _on_statustext(self, now_s: float, severity: int, text: str) -> None:
        if self._flight_logger is not None:
            self._flight_logger.text(now_s, severity, text)
        if self._statustext_observer is not None:
            self._statustext_observer(now_s, severity, text)

    def _file_system(self, ardupilot_extensions: bool) -> FileSystem:
        """What MAVLink FTP serves: PX4's log directory with the flight logs and, with
        ArduPilot's extensions, the parameters in ArduPilot's packed file."""
        files = FileSystem(static_directory({"log": self.flight_logs.directory()}))
        if ardupilot_extensions:
            params = self.params

            def param_pck(query: str) -> bytes:
                return pack_param_pck(params, with_defaults="withdefaults=1" in query)

            files.special["@PARAM/param.pck"] = param_pck
        return files

    def _set_mode(self, mode: FlightMode, failsafe: bool = False) -> None:
        """The navigator's way to the commander's mode switch."""
        self._commander.set_mode(mode, failsafe)

    def _motors_changed(self) -> None:
        vehicle = self._vehicle
        vehicle.physics.motor_failure[vehicle.index] = self._state.motors_failed
        self._commander.command_physics()

    def _param_changed(self, name: str, value: float) -> None:
        self._navigator.apply_limits()

    def _announce_home(self) -> None:
        msg = self.telemetry.build(mavlink.MAVLINK_MSG_ID_HOME_POSITION, self._state.now_s)
        if msg is not None:
            self._vehicle.broadcast(msg)
