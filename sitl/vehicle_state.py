"""What the parts of one emulated vehicle's autopilot share.

PX4's modules (commander, navigator, land detector, the MAVLink receiver) tell each other about
the vehicle over uORB topics: vehicle_status, vehicle_land_detected, home_position, the local
position estimate. Here they share two objects per vehicle instead:

- :class:`VehicleState`, the flags those topics carry (armed, mode, landed, failsafe, home ...);
- :class:`VehicleContext`, the state plus what every part reads or writes: the parameters, this
  vehicle's row of the shared physics and :class:`Snapshot`, the map projection, and the outbox
  (STATUSTEXT and broadcasts to every link).

:class:`sitl.autopilot.Px4Autopilot` creates both and hands the context to each part
(:mod:`sitl.commander`, :mod:`sitl.navigator`, :mod:`sitl.offboard`, :mod:`sitl.land_detector`,
:mod:`sitl.mavlink_receiver`). Nothing here decides anything.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from pymavlink.dialects.v20 import common as mavlink

from sitl import physics as ph
from sitl.geo import MapProjection
from sitl.gnss import GnssError
from sitl.modes import FlightMode
from sitl.odometry import Odometry
from sitl.params import ParamStore
from sitl.telemetry import StreamScheduler

logger = logging.getLogger(__name__)

STATUS_LOG_LENGTH = 256
_STATUSTEXT_CHUNK_BYTES = 50  # STATUSTEXT.text is char[50]


class Link(Protocol):
    """Where the autopilot's messages go: one MAVLink link (API or GCS) of this vehicle."""

    name: str
    streams: StreamScheduler

    def send(self, msg: mavlink.MAVLink_message) -> None: ...


@dataclass(slots=True)
class Snapshot:
    """Python-list copies of the physics state, refreshed once per step for cheap scalar reads.

    ``position_ned_m[i]`` etc. are lists of 3 floats (world NED); ``step_id`` increments on every
    refresh so per-vehicle caches know when they are stale.
    """

    position_ned_m: list[list[float]] = field(default_factory=list)
    velocity_ned_m_s: list[list[float]] = field(default_factory=list)
    roll_rad: list[float] = field(default_factory=list)
    pitch_rad: list[float] = field(default_factory=list)
    yaw_rad: list[float] = field(default_factory=list)
    yaw_rate_rad_s: list[float] = field(default_factory=list)
    roll_rate_rad_s: list[float] = field(default_factory=list)
    pitch_rate_rad_s: list[float] = field(default_factory=list)
    acceleration_ned_m_s2: list[list[float]] = field(default_factory=list)
    drift_ned_m: list[list[float]] = field(default_factory=list)
    gps_error_ned_m: list[list[float]] | None = None
    """Error of the reported global position (world NED m), None while there is none."""
    step_id: int = 0

    def refresh(
        self,
        physics: ph.MulticopterPhysics,
        odometry: Odometry,
        gnss: GnssError | None = None,
    ) -> None:
        self.position_ned_m = physics.position_ned_m.tolist()
        self.velocity_ned_m_s = physics.velocity_ned_m_s.tolist()
        self.roll_rad = physics.roll_rad.tolist()
        self.pitch_rad = physics.pitch_rad.tolist()
        self.yaw_rad = physics.yaw_rad.tolist()
        self.yaw_rate_rad_s = physics.yaw_rate_rad_s.tolist()
        self.roll_rate_rad_s = physics.roll_rate_rad_s.tolist()
        self.pitch_rate_rad_s = physics.pitch_rate_rad_s.tolist()
        self.acceleration_ned_m_s2 = physics.acceleration_ned_m_s2.tolist()
        self.drift_ned_m = odometry.drift_ned_m.tolist()
        if gnss is not None and gnss.active:
            self.gps_error_ned_m = gnss.error_ned_m.tolist()
        else:
            self.gps_error_ned_m = None
        self.step_id += 1


@dataclass(slots=True)
class VehicleState:
    """The flags the parts of one autopilot publish to each other.

    ``home_ned_m`` is the home position in the world NED frame (m); ``now_s`` the simulated time
    of the message or step being handled. ``landed_state`` is a ``MAV_LANDED_STATE``;
    ``landing`` says a descent to land is under way, in whatever mode.
    """

    home_ned_m: list[float]
    now_s: float = 0.0
    alive: bool = True
    armed: bool = False
    mode: FlightMode = FlightMode.HOLD
    failsafe_active: bool = False
    landed: bool = True
    landed_state: int = mavlink.MAV_LANDED_STATE_ON_GROUND
    landing: bool = False
    flow_ok: bool = True
    gps_ok: bool = True
    motors_failed: bool = False
    """An injected motor failure: the vehicle cannot fly."""
    battery_failed: bool = False
    """An injected battery failure: the battery reads empty."""
    calibrating: bool = False
    """A sensor or RC calibration is under way."""

    @property
    def position_ok(self) -> bool:
        """At least one position source (optical flow or GPS) works."""
        return self.gps_ok or self.flow_ok


@dataclass(slots=True, eq=False)
class VehicleContext:
    """One vehicle as the parts of its autopilot see it: ``state``, ``params``, row ``index``
    of the shared ``physics``/``snapshot``/``odometry``, and the outbox to ``links``.

    ``projection`` maps world north/east to latitude/longitude; ``ground_amsl_m`` is the
    altitude of the flat ground. ``status_log`` keeps the latest STATUSTEXTs as (time_s, text)
    for observers (tests, a world module); ``on_statustext(time_s, severity, text)`` is called
    for each.
    """

    index: int
    state: VehicleState
    params: ParamStore
    physics: ph.MulticopterPhysics
    odometry: Odometry
    snapshot: Snapshot
    projection: MapProjection
    ground_amsl_m: float
    links: list[Link] = field(default_factory=list)
    status_log: deque[tuple[float, str]] = field(
        default_factory=lambda: deque(maxlen=STATUS_LOG_LENGTH)
    )
    on_statustext: Callable[[float, int, str], None] | None = None
    _statustext_id: int = field(default=0, init=False, repr=False)

    @property
    def sysid(self) -> int:
        """MAVLink system id: PX4 SITL instance ``index`` is system ``index + 1``."""
        return self.index + 1

    @property
    def compid(self) -> int:
        """MAVLink component id of the autopilot."""
        return 1

    # ---------------------------------------------------------------- reading
    def is_for_me(self, msg: mavlink.MAVLink_message) -> bool:
        """``msg`` is addressed to this vehicle's autopilot (component 0 means any)."""
        return msg.target_system == self.sysid and msg.target_component in (0, self.compid)

    def position_ned(self) -> list[float]:
        """True world NED position, m."""
        return self.snapshot.position_ned_m[self.index]

    def velocity_ned(self) -> list[float]:
        """True world NED velocity, m/s."""
        return self.snapshot.velocity_ned_m_s[self.index]

    def attitude(self) -> tuple[float, float, float, float]:
        """(roll, pitch, yaw, yaw rate), rad and rad/s."""
        i = self.index
        s = self.snapshot
        return s.roll_rad[i], s.pitch_rad[i], s.yaw_rad[i], s.yaw_rate_rad_s[i]

    def height_above_ground_m(self) -> float:
        return -self.position_ned()[2]

    def altitude_above_home_m(self) -> float:
        return self.state.home_ned_m[2] - self.position_ned()[2]

    def down_from_altitude(self, altitude_m: float, relative_to_home: bool) -> float:
        """World down coordinate (m) of an altitude above home or above mean sea level."""
        if relative_to_home:
            return self.state.home_ned_m[2] - altitude_m
        return self.ground_amsl_m - altitude_m

    # ---------------------------------------------------------------- writing
    def motors_off(self) -> None:
        self.physics.control_mode[self.index] = ph.MOTORS_OFF

    def fly_to(
        self,
        position_ned_m: list[float],
        feedforward_ned_m_s: list[float] | None = None,
        *,
        yaw_rad: float = math.nan,
    ) -> None:
        """Position control towards ``position_ned_m`` (world NED m), plus a velocity
        feed-forward; NaN ``yaw_rad`` keeps the heading."""
        i = self.index
        phys = self.physics
        phys.control_mode[i] = ph.POSITION
        phys.position_setpoint_ned_m[i] = position_ned_m
        phys.velocity_feedforward_ned_m_s[i] = feedforward_ned_m_s or (0.0, 0.0, 0.0)
        phys.yaw_setpoint_rad[i] = yaw_rad
        phys.yaw_rate_setpoint_rad_s[i] = math.nan

    def fly_at(
        self, velocity_ned_m_s: list[float], *, yaw_rad: float = math.nan, yaw_rate_rad_s: float
    ) -> None:
        """Velocity control at ``velocity_ned_m_s`` (world NED m/s), turning at
        ``yaw_rate_rad_s`` or, when that is NaN, towards ``yaw_rad`` (NaN: keep the heading)."""
        i = self.index
        phys = self.physics
        phys.control_mode[i] = ph.VELOCITY
        phys.velocity_setpoint_ned_m_s[i] = velocity_ned_m_s
        phys.yaw_setpoint_rad[i] = yaw_rad
        phys.yaw_rate_setpoint_rad_s[i] = yaw_rate_rad_s

    def statustext(self, now_s: float, severity: int, text: str) -> None:
        """Log ``text`` and send it; PX4 sends texts over 50 bytes in 50-byte chunks that share
        a non-zero id (a tab that PX4 appends to many texts is kept on the wire only)."""
        shown = text.rstrip("\t")
        self.status_log.append((now_s, shown))
        logger.debug("vehicle %d: %s", self.sysid, shown)
        if self.on_statustext is not None:
            self.on_statustext(now_s, severity, shown)
        if not self.state.alive:
            return
        data = text.encode()
        size = _STATUSTEXT_CHUNK_BYTES
        if len(data) <= size:
            self.broadcast(mavlink.MAVLink_statustext_message(severity, data))
            return
        self._statustext_id = self._statustext_id % 0xFFFF + 1
        for seq, start in enumerate(range(0, len(data), size)):
            chunk = data[start : start + size]
            self.broadcast(
                mavlink.MAVLink_statustext_message(severity, chunk, self._statustext_id, seq)
            )

    def broadcast(self, msg: mavlink.MAVLink_message) -> None:
        """Send ``msg`` on every link of this vehicle (events: texts, parameters, missions)."""
        for link in self.links:
            link.send(msg)
