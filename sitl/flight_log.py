"""The flight logs a vehicle records, as PX4's logger does: one ULog file per flight.

:class:`FlightLogger` starts a log when SDLOG_MODE says so (1, PX4 SITL's default: from boot to
the first disarm, then per flight; 0: from arming to disarming; 2: from boot and 4: from the first
arming until the emulator stops; 3 never, as there is no RC AUX1 switch)
and samples the vehicle at ``rate_hz`` into a few of PX4's topics under their PX4 names and
fields (vehicle_status, vehicle_local_position, vehicle_global_position, vehicle_attitude,
sensor_combined, battery_status), with the parameters and the vehicle's STATUSTEXTs as logged
strings (:mod:`sitl.ulog`). The logs stay in memory in a :class:`FlightLogStore`, named like
PX4's ``log/YYYY-MM-DD/HH_MM_SS.ulg`` (UTC), oldest first: the MAVLink log protocol
(:mod:`sitl.log_handler`) and FTP (:mod:`sitl.ftp`) serve them from there. A log stops growing
at ``max_log_bytes``; beyond ``max_logs`` the oldest is dropped.
"""

from __future__ import annotations

import datetime
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from sitl.ftp import Directory, File
from sitl.params import PARAM_TABLE, ParamStore
from sitl.telemetry import euler_to_quaternion
from sitl.ulog import Topic, ULogWriter

if TYPE_CHECKING:
    from sitl import imu
    from sitl.modes import FlightMode

logger = logging.getLogger(__name__)

#: The topics logged, with PX4's names and a subset of PX4's fields.
TOPICS: tuple[Topic, ...] = (
    Topic(
        "vehicle_status",
        (
            ("uint64_t", "timestamp"),
            ("uint8_t", "arming_state"),
            ("uint8_t", "nav_state"),
            ("bool", "failsafe"),
        ),
    ),
    Topic(
        "vehicle_local_position",
        (("uint64_t", "timestamp"), *(("float", c) for c in ("x", "y", "z", "vx", "vy", "vz"))),
    ),
    Topic(
        "vehicle_global_position",
        (("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"), ("float", "alt")),
    ),
    Topic("vehicle_attitude", (("uint64_t", "timestamp"), ("float[4]", "q"))),
    Topic(
        "sensor_combined",
        (("uint64_t", "timestamp"), ("float[3]", "gyro_rad"), ("float[3]", "accelerometer_m_s2")),
    ),
    Topic(
        "battery_status",
        (("uint64_t", "timestamp"), ("float", "voltage_v"), ("float", "remaining")),
    ),
)

#: SDLOG_MODE values. 3 (while RC AUX1 is high) never logs here: there is no RC.
_WHEN_ARMED = 0
_FROM_BOOT_UNTIL_DISARM = 1
_FROM_BOOT_UNTIL_SHUTDOWN = 2
_FROM_FIRST_ARMING_UNTIL_SHUTDOWN = 4
_START_WHEN_ARMED = (_WHEN_ARMED, _FROM_BOOT_UNTIL_DISARM, _FROM_FIRST_ARMING_UNTIL_SHUTDOWN)
_STOP_WHEN_DISARMED = (_WHEN_ARMED, _FROM_BOOT_UNTIL_DISARM)

#: vehicle_status.arming_state
ARMING_STATE_DISARMED = 1
ARMING_STATE_ARMED = 2
#: vehicle_status.nav_state by PX4 (main mode, sub mode); POSCTL's sub mode 1 is orbit.
_NAV_STATES: Mapping[tuple[int, int], int] = {
    (1, 0): 0,  # manual
    (2, 0): 1,  # altitude
    (3, 0): 2,  # position
    (3, 1): 21,  # orbit
    (4, 2): 17,  # takeoff
    (4, 3): 4,  # loiter (hold)
    (4, 4): 3,  # mission
    (4, 5): 5,  # return
    (4, 6): 18,  # land
    (4, 8): 19,  # follow target
    (4, 9): 20,  # precision land
    (5, 0): 10,  # acro
    (6, 0): 14,  # offboard
    (7, 0): 15,  # stabilized
}


def nav_state(custom_mode: int) -> int:
    """PX4's vehicle_status.nav_state for a HEARTBEAT custom_mode (loiter if unknown)."""
    return _NAV_STATES.get(((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF), 4)


@dataclass(slots=True, eq=False)
class FlightLog:
    """One ULog file: ``name`` is its path under PX4's log directory."""

    name: str
    data: bytearray
    time_utc_s: int
    """When it was last written to, UNIX seconds (PX4 lists a log's modification time)."""
    recording: bool = True

    @property
    def size(self) -> int:
        return len(self.data)


@dataclass(slots=True)
class FlightLogStore:
    """The logs of one vehicle, oldest first, bounded to ``max_logs``."""

    max_logs: int = 20
    logs: list[FlightLog] = field(default_factory=list)

    def add(self, log: FlightLog) -> None:
        names = {existing.name for existing in self.logs}
        stem, suffix = log.name.removesuffix(".ulg"), 1
        while log.name in names:  # two logs within one second (fast clocks)
            log.name, suffix = f"{stem}_{suffix}.ulg", suffix + 1
        self.logs.append(log)
        del self.logs[: max(0, len(self.logs) - self.max_logs)]

    def erase(self) -> None:
        """LOG_ERASE: every log goes, the one being written included (PX4 unlinks it)."""
        self.logs.clear()

    def directory(self) -> Directory:
        """PX4's ``log`` directory for FTP: one directory per day, the day's logs in it."""

        def days() -> Mapping[str, File | Directory]:
            by_day: dict[str, dict[str, File | Directory]] = {}
            for log in list(self.logs):
                day, _, file_name = log.name.partition("/")
                by_day.setdefault(day, {})[file_name] = File(_content_of(log))
            return {day: Directory(_entries_of(files)) for day, files in by_day.items()}

        return Directory(days)


def _content_of(log: FlightLog) -> Callable[[], bytes]:
    return lambda: bytes(log.data)


def _entries_of(
    files: Mapping[str, File | Directory],
) -> Callable[[], Mapping[str, File | Directory]]:
    return lambda: files


class LoggedVehicle(Protocol):
    """What a flight log samples of a vehicle (:class:`sitl.autopilot.Px4Autopilot` has it)."""

    @property
    def armed(self) -> bool: ...
    def attitude(self) -> tuple[float, float, float, float]: ...
    @property
    def battery_remaining_pct(self) -> float: ...
    def battery_voltage_mv(self) -> int: ...
    @property
    def failsafe_active(self) -> bool: ...
    def global_position(self) -> tuple[float, float, float]: ...
    def inertial_frd(self) -> tuple[imu.Vector3, imu.Vector3, imu.Vector3]: ...
    @property
    def mode(self) -> FlightMode: ...
    def odometry_sample(self) -> tuple[float, float, float, float, float, float]: ...
    def time_usec(self, now_s: float) -> int: ...
    def unix_time_us(self, now_s: float) -> int: ...


class FlightLogger:
    """Records ``vehicle``'s flights into ``store`` as SDLOG_MODE of ``params`` says."""

    def __init__(
        self,
        vehicle: LoggedVehicle,
        params: ParamStore,
        store: FlightLogStore,
        *,
        rate_hz: float = 10.0,
        max_log_bytes: int = 16 * 1024 * 1024,
    ) -> None:
        self._vehicle = vehicle
        self._params = params
        self.store = store
        self._period_s = 1.0 / rate_hz
        self._max_log_bytes = max_log_bytes
        self._log: FlightLog | None = None
        self._writer: ULogWriter | None = None
        self._next_sample_s = 0.0
        self._was_armed = False
        self._started = False

    @property
    def recording(self) -> bool:
        return self._log is not None

    def update(self, now_s: float) -> None:
        """Start, sample or stop the log at simulated time ``now_s`` (every autopilot step)."""
        armed = self._vehicle.armed
        mode = int(self._params["SDLOG_MODE"])
        if not self._started:
            self._started = True
            if mode in (_FROM_BOOT_UNTIL_DISARM, _FROM_BOOT_UNTIL_SHUTDOWN):
                self._start(now_s)
        if armed and not self._was_armed:
            if self._log is None and mode in _START_WHEN_ARMED:
                self._start(now_s)
        elif self._was_armed and not armed and mode in _STOP_WHEN_DISARMED:
            self._stop(now_s)
        self._was_armed = armed
        if self._log is not None and now_s >= self._next_sample_s - 1e-9:
            self._next_sample_s = max(self._next_sample_s + self._period_s, now_s)
            self._sample(now_s)

    def text(self, now_s: float, severity: int, text: str) -> None:
        """A STATUSTEXT the vehicle sent: a logged string in the running log."""
        if self._writer is not None and self._room():
            self._writer.log(min(max(severity, 0), 7), self._vehicle.time_usec(now_s), text)

    def close(self, now_s: float) -> None:
        """The emulator stops: the running log ends (modes 2 and 4 log until shutdown)."""
        self._stop(now_s)

    # ------------------------------------------------------------------ internals
    def _start(self, now_s: float) -> None:
        vehicle = self._vehicle
        start_us = vehicle.time_usec(now_s)
        utc_s = vehicle.unix_time_us(now_s) / 1e6
        when = datetime.datetime.fromtimestamp(utc_s, tz=datetime.UTC)
        writer = ULogWriter(start_us)
        writer.info("sys_name", "PX4")
        writer.info("ver_hw", "PX4_SITL")
        writer.info("sys_toolchain", "sitl emulator")
        writer.info("time_ref_utc", 0)
        for topic in TOPICS:
            writer.format(topic)
        for name in self._params:
            writer.parameter(name, self._params[name], PARAM_TABLE[name].type == "INT32")
        for topic in TOPICS:
            writer.subscribe(topic.name)
        self._writer = writer
        self._log = FlightLog(
            when.strftime("%Y-%m-%d/%H_%M_%S.ulg"), writer.data, math.floor(utc_s)
        )
        self.store.add(self._log)
        self._next_sample_s = now_s
        logger.debug("flight log %s started", self._log.name)

    def _stop(self, now_s: float) -> None:
        if self._log is None:
            return
        if self._writer is not None:
            self._sample(now_s)
            self._writer.sync()
        self._log.recording = False
        self._log.time_utc_s = math.floor(self._vehicle.unix_time_us(now_s) / 1e6)
        logger.debug("flight log %s: %d bytes", self._log.name, self._log.size)
        self._log = None
        self._writer = None

    def _room(self) -> bool:
        return self._log is not None and self._log.size < self._max_log_bytes

    def _sample(self, now_s: float) -> None:
        writer, log = self._writer, self._log
        if writer is None or log is None or not self._room():
            return
        vehicle = self._vehicle
        t = vehicle.time_usec(now_s)
        armed = ARMING_STATE_ARMED if vehicle.armed else ARMING_STATE_DISARMED
        writer.write(
            "vehicle_status",
            (t, armed, nav_state(vehicle.mode.custom_mode), vehicle.failsafe_active),
        )
        writer.write("vehicle_local_position", (t, *vehicle.odometry_sample()))
        writer.write("vehicle_global_position", (t, *vehicle.global_position()))
        roll, pitch, yaw, _ = vehicle.attitude()
        writer.write("vehicle_attitude", (t, *euler_to_quaternion(roll, pitch, yaw)))
        force, rates, _ = vehicle.inertial_frd()
        writer.write("sensor_combined", (t, *rates, *force))
        writer.write(
            "battery_status",
            (t, vehicle.battery_voltage_mv() / 1000.0, vehicle.battery_remaining_pct / 100.0),
        )
        log.time_utc_s = math.floor(vehicle.unix_time_us(now_s) / 1e6)
