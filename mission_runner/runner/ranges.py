"""A SIMULATION AID: UWB ranges and target observations synthesised from the vehicles' positions,
for flying the mission on vehicles without UWB. It publishes exactly what a UWB driver and a target
tracker would publish, so the controllers run unchanged; nothing here is used when real sensors
exist.

Two sources of positions:

- ``sih``: a simulator's ground truth, HIL_STATE_QUATERNION as PX4's SIH sends it on its own UDP
  link (instance i: from 19450+i to 19410+i; the emulator's ``truth_stream`` sends the same).
  PX4 leaves its ``time_usec`` at 0, so each message is stamped on arrival (host clock, a
  millisecond or less on one machine). Ranges are then as good as the chosen UWB model
  (``scenario.sensors``, :class:`mission_runner.sensors.UwbRanging`).
- ``gps``: each vehicle's GLOBAL_POSITION_INT through MAVSDK (a GCS link where every vehicle is
  heard), stamped with the autopilot's boot time mapped continuously onto the mission clock
  (:mod:`.timesync`). For field tests without UWB: GPS/EKF positions differ between vehicles by
  decimetres (PX4 SIH: -0.54..+0.38 m, 5th-95th percentile of pair ranges against truth), which
  is far more than the RLSE tolerates: expect metres of tracking error.

With ``sih``, the aid can also stand in for a vision/flow odometry (``vision``): it sends each
instance ODOMETRY (MAV_ESTIMATOR_TYPE_VIO, local NED) made from the same truth with white noise,
back on the truth link, for EKF2 to fuse (``EKF2_EV_CTRL``) as an indoor swarm's vehicles fuse
their own VIO. PX4 stamps it on arrival. The controllers still read only LOCAL_POSITION_NED:
EKF2's estimate, its latency and its filtering included. Without it, SIH's EKF2 follows SIH's
GPS (0.2 m white noise, hard-coded) and its local position wanders 0.2-0.3 m within seconds.

Each step's ranges are published as soon as every live vehicle has a position after t_k (the two
samples bracketing t_k, interpolated), not after a fixed delay. Under a sparse ``algorithm.graph``
only the graph's edges are ranged, among the vehicles heard within ``STALE_AFTER_S`` (a ring
closes over one that went silent, :class:`mission_runner.wiring.RangingGraph`). The scenario
frame's origin is placed so that the first vehicle's first fix is at its ``initial_position_m``;
the virtual target follows the scenario's path on the mission clock from k = 0.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from ..bus import (
    Bus,
    ControlCommand,
    MissionControl,
    RangeSet,
    Sender,
    Subscription,
    Topics,
    VehicleStatus,
    open_bus,
)
from ..records import ControllerState, TruthSample
from ..scenario import target_positions
from ..sensors import UwbRanging, ranging_plan
from ..wiring import RangingGraph
from ..world.world import publish_measurements, step_measurements
from .errors import RunnerError
from .handshake import freeze_heap, next_command, start_command, take_clock_change
from .links import MavsdkVehicle, connected_vehicles
from .mavlink_frames import OdometryFrames, TruthDecoder
from .odometry import OdometrySample, OdometryTrack
from .timesync import ClockMapping, MissionTime

if TYPE_CHECKING:
    from ..config import Scenario

logger = logging.getLogger(__name__)

EARTH_RADIUS_M = 6_371_000.0
POSITION_RATE_HZ = 20.0
SOURCES = ("sih", "gps")
TRUTH_PORT_BASE = 19410
#: SIH's own ground-truth rate [Hz], when the aid asks for none.
SIH_TRUTH_RATE_HZ = 25.0
#: The ground truth's rate asked of each SIH instance [Hz] (PX4 streams 25), or the vision
#: odometry's if that is higher (each ODOMETRY is made from a truth sample). A step's ranges take
#: the newest sample at its velocity when it is at most EXTRAPOLATE_PERIODS old, so a faster
#: truth barely shortens the wait; 100 Hz cost the aid twice the datagrams for nothing.
TRUTH_RATE_HZ = 50.0
#: The attitude's std a vision odometry reports [rad]: the truth's, sent as is.
ATTITUDE_NOISE_STD_RAD = 0.01
#: A vehicle whose last position is older than this at t_k is not waited for (dead or silent).
STALE_AFTER_S = 1.0
#: Longest wait for one message to be handed to the broker before it is dropped.
PUBLISH_TIMEOUT_S = 0.25
#: Longest wait after t_k for the positions bracketing it; never past the step's deadline
#: (``flight.step_deadline_s``): what comes later is no vehicle's, and a wait of 0.25 s for one
#: vehicle whose truth paused (PX4 short of CPU at speed factor 2) put the aid, and every
#: vehicle behind it, seconds late.
MAX_WAIT_S = 0.25
#: How far past a vehicle's newest truth sample t_k is taken at that sample's velocity instead of
#: waiting for the next one, in periods of the truth rate (the wait was half a period on average
#: and put every step's ranges, and every vehicle's step behind them, that much later).
EXTRAPOLATE_PERIODS = 1.5
#: After its last step, the longest the aid goes on feeding the vision odometry while the
#: vehicles land [s]: until every vehicle reports itself done (landed and disarmed) for this
#: mission, else this long (the ground station waits 60 s for a landing). A VIO does not switch
#: off when the mission's steps end; when the aid's did, EKF2 lost its position aiding in the
#: descent, and a vehicle was once still not landed and disarmed 60 s later.
VISION_AFTER_STEPS_S = 90.0


class FlatEarth:
    """Fixes to north-east-down from one reference ``(lat, lon, alt)``, flat earth: the metres
    per degree are worked out once (hundreds of fixes a second go through it)."""

    def __init__(self, reference: tuple[float, float, float]) -> None:
        self.reference = reference
        self.north_m_per_deg = math.radians(1.0) * EARTH_RADIUS_M
        self.east_m_per_deg = self.north_m_per_deg * math.cos(math.radians(reference[0]))

    def ned(self, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
        lat0, lon0, alt0 = self.reference
        return (
            (lat_deg - lat0) * self.north_m_per_deg,
            (lon_deg - lon0) * self.east_m_per_deg,
            alt0 - alt_m,
        )


class GeodeticFrame:
    """Latitude/longitude/altitude to the scenario's north-east-down frame: flat earth around the
    first vehicle's first fix, which is placed at its ``initial_position_m``. Fixes of other
    vehicles before that one are dropped (the frame is not known yet)."""

    def __init__(self, first_id: int, first_position_m: Sequence[float]) -> None:
        self.first_id = first_id
        self.first_position_m = first_position_m
        self.reference: tuple[float, float, float] | None = None  # (lat, lon, alt) of first fix
        self.flat_earth: FlatEarth | None = None

    def local(
        self, vehicle_id: int, lat_deg: float, lon_deg: float, alt_m: float
    ) -> tuple[float, float, float] | None:
        """``(north_m, east_m, down_m)`` in the scenario frame, or None before the first fix."""
        if self.flat_earth is None:
            if vehicle_id != self.first_id:
                return None
            self.reference = (lat_deg, lon_deg, alt_m)
            self.flat_earth = FlatEarth(self.reference)
        north, east, down = self.flat_earth.ned(lat_deg, lon_deg, alt_m)
        return north + self.first_position_m[0], east + self.first_position_m[1], down


@dataclass
class VehiclePositions:
    """One vehicle's positions in the scenario frame, stamped on UNIX time."""

    vehicle_id: int
    track: OdometryTrack = field(default_factory=lambda: OdometryTrack(capacity=512))
    received: int = 0

    def newest_s(self) -> float:
        latest = self.track.latest
        return -math.inf if latest is None else latest.time_s


@dataclass(frozen=True)
class VisionSettings:
    """The simulated vision odometry: how often each instance gets one, and its white noise."""

    rate_hz: float
    position_noise_std_m: float = 0.02
    velocity_noise_std_m_s: float = 0.05

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and 0 < self.rate_hz <= 1000):
            raise RunnerError(f"vision odometry rate {self.rate_hz} Hz: give 0 < rate <= 1000")
        for name in ("position_noise_std_m", "velocity_noise_std_m_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise RunnerError(f"vision odometry {name} = {value}: give a finite value >= 0")


class VisionOdometry:
    """ODOMETRY messages from one instance's ground truth: position in the vehicle's own NED frame
    (origin at its first truth sample, like a VIO switched on there) and NED velocity, each with
    white noise and that noise's variance in the covariance, at most ``rate_hz``.

    The noise is drawn from ``rng`` NOISE_BLOCK messages ahead (standard normals, scaled): the
    same draws, in the same order (three of position, three of velocity per message), as one
    call per message."""

    #: Messages whose noise one call to the generator draws (a call per message cost more than
    #: the rest of the message).
    NOISE_BLOCK = 256

    def __init__(self, vehicle_id: int, settings: VisionSettings, rng: np.random.Generator) -> None:
        self.vehicle_id = vehicle_id
        self.settings = settings
        self.rng = rng
        self.origin: tuple[float, float, float] | None = None
        self.flat_earth: FlatEarth | None = None
        self.next_s = -math.inf
        self.sent = 0
        position_sd = settings.position_noise_std_m
        velocity_sd = settings.velocity_noise_std_m_s
        self.noise_scale = np.array([position_sd] * 3 + [velocity_sd] * 3)
        self.noise: list[list[float]] = []
        self.frames = OdometryFrames(
            vehicle_id,
            mavlink.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
            position_variance_m2=position_sd**2,
            attitude_variance_rad2=ATTITUDE_NOISE_STD_RAD**2,
            velocity_variance_m2_s2=velocity_sd**2,
        )

    def message(self, arrived_s: float, truth: Any) -> bytes | None:
        """The ODOMETRY for a HIL_STATE_QUATERNION ``truth`` (its fields in MAVLink units)
        received at ``arrived_s``, or None when the last one went out less than a period ago."""
        if arrived_s < self.next_s:
            return None
        period_s = 1.0 / self.settings.rate_hz
        self.next_s = max(self.next_s + period_s, arrived_s + 0.5 * period_s)
        lat_deg, lon_deg, alt_m = truth.lat / 1e7, truth.lon / 1e7, truth.alt / 1e3
        if self.flat_earth is None:
            self.origin = (lat_deg, lon_deg, alt_m)
            self.flat_earth = FlatEarth(self.origin)
        north_m, east_m, down_m = self.flat_earth.ned(lat_deg, lon_deg, alt_m)
        if not self.noise:
            block = self.rng.standard_normal((self.NOISE_BLOCK, 6)) * self.noise_scale
            self.noise = block.tolist()[::-1]  # popped from the end: drawn order
        n, e, d, vn, ve, vd = self.noise.pop()
        self.sent += 1
        return self.frames.frame(
            (north_m + n, east_m + e, down_m + d),
            truth.attitude_quaternion,  # a VIO's attitude: for EKF2_EV_CTRL's yaw bit
            (truth.vx / 100.0 + vn, truth.vy / 100.0 + ve, truth.vz / 100.0 + vd),
        )


def _per_host_second(
    velocity_cm_s: tuple[float, float, float], clock_rate: float
) -> tuple[float, float, float]:
    """A MAVLink velocity (cm per second of an autopilot's clock running ``clock_rate`` x the
    host's) in m per host second, the aid's time base."""
    return (
        velocity_cm_s[0] * 0.01 * clock_rate,
        velocity_cm_s[1] * 0.01 * clock_rate,
        velocity_cm_s[2] * 0.01 * clock_rate,
    )


@dataclass
class RangeStats:
    """What the aid published: steps, ranges, and how long after t_k each step went out."""

    steps: int = 0
    ranges: int = 0
    missing_vehicles: int = 0
    #: Messages not published within PUBLISH_TIMEOUT_S (dropped, as a radio drops a packet).
    unsent: int = 0
    #: Steps whose deadline had passed when the aid got to them: measured for the truth, not
    #: published (every vehicle would drop them as late).
    skipped: int = 0
    lateness_s: list[float] = field(default_factory=list)
    truth: list[TruthSample] = field(default_factory=list)  # per step, for scoring only
    #: Positions received per second during the mission, by vehicle id.
    position_rates_hz: dict[int, float] = field(default_factory=dict)
    #: Vision odometry messages sent per second during the mission, by vehicle id (if asked).
    vision_rates_hz: dict[int, float] = field(default_factory=dict)
    #: How long the vision odometry went on after the last step, while the vehicles landed [s].
    vision_after_steps_s: float = 0.0
    #: Vehicles the aid saw report themselves done (only waited for with a vision odometry).
    vehicles_done: int = 0

    def lateness_percentiles_ms(self) -> dict[str, float]:
        if not self.lateness_s:
            return {}
        values = np.asarray(self.lateness_s) * 1000.0
        return {f"p{q}": float(np.percentile(values, q)) for q in (50, 95, 99)} | {
            "max": float(values.max())
        }


class _Positions:
    """Every vehicle's positions, with a wake-up on each new sample."""

    def __init__(self, scenario: Scenario) -> None:
        self.ids = [v.id for v in scenario.vehicles]
        self.vehicles = {i: VehiclePositions(i) for i in self.ids}
        self.frame = GeodeticFrame(self.ids[0], scenario.vehicles[0].initial_position_m)
        self.changed = asyncio.Event()

    def add(
        self,
        vehicle_id: int,
        unix_s: float,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        *,
        velocity_ned_m_s: tuple[float, float, float] = (math.nan, math.nan, math.nan),
    ) -> None:
        """A fix received at ``unix_s``; ``velocity_ned_m_s`` per host second (NaN: unknown)."""
        local = self.frame.local(vehicle_id, lat_deg, lon_deg, alt_m)
        if local is None:
            return
        positions = self.vehicles[vehicle_id]
        if positions.track.add(OdometrySample(unix_s, *local, *velocity_ned_m_s)):
            positions.received += 1
            self.changed.set()

    def heard(self, unix_s: float) -> NDArray[np.bool_]:
        """``(n,)`` bool: the vehicles with a position at most ``STALE_AFTER_S`` before
        ``unix_s`` (the others are dead or silent)."""
        newest = [self.vehicles[vehicle_id].newest_s() for vehicle_id in self.ids]
        return np.asarray(newest) >= unix_s - STALE_AFTER_S

    async def bracketing(
        self, unix_s: float, max_wait_s: float, *, extrapolate_s: float = 0.0
    ) -> NDArray[np.float64]:
        """Wait until every vehicle heard recently has a sample after ``unix_s``, or one at
        most ``extrapolate_s`` before it with a velocity (or ``max_wait_s``); return ``(n, 3)``
        positions at ``unix_s``, NaN rows where unknown."""

        def known(p: VehiclePositions) -> bool:
            return p.track.at(unix_s, extrapolate_s=extrapolate_s) is not None

        def ready() -> bool:
            return all(
                known(p) or p.newest_s() < unix_s - STALE_AFTER_S for p in self.vehicles.values()
            )

        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(max_wait_s):
                while not ready():
                    self.changed.clear()
                    await self.changed.wait()
        rows: list[tuple[float, float, float]] = []
        for vehicle_id in self.ids:
            at = self.vehicles[vehicle_id].track.at(unix_s, extrapolate_s=extrapolate_s)
            rows.append(at if at is not None else (math.nan,) * 3)
        return np.asarray(rows, dtype=float)


class _TruthProtocol(asyncio.DatagramProtocol):
    """HIL_STATE_QUATERNION datagrams from one SIH instance, stamped on arrival. On the first one,
    asks the instance for ``rate_hz`` of them (MAV_CMD_SET_MESSAGE_INTERVAL, to where they come
    from): PX4 starts the stream at 25 Hz, so a step's bracketing sample would come up to 40 ms
    after t_k, and every vehicle's step waits for it."""

    def __init__(
        self,
        positions: _Positions,
        vehicle_id: int,
        rate_hz: float | None,
        vision: VisionOdometry | None = None,
        unix_s: Callable[[], float] = time.time,
    ) -> None:
        self.positions = positions
        #: The UNIX clock arrivals are stamped on (the positions' and the steps' clock).
        self.unix_s = unix_s
        self.vehicle_id = vehicle_id
        self.vision = vision
        self.decoder = TruthDecoder(vehicle_id)
        self.rate_hz = rate_hz
        self.transport: asyncio.DatagramTransport | None = None
        self.address: tuple[str | Any, int] | None = None
        self.clock_rate = 1.0
        self._asks = 0  # requests sent
        self.asked = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    @property
    def malformed(self) -> int:
        """Frames not acted on: cut short, a bad CRC, another system's (see TruthDecoder)."""
        return self.decoder.malformed

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        arrived_s = self.unix_s()
        for truth in self.decoder.states(data):
            if not self.asked:
                self._ask_rate(addr)
            self.positions.add(
                self.vehicle_id,
                arrived_s,
                truth.lat / 1e7,
                truth.lon / 1e7,
                truth.alt / 1e3,
                velocity_ned_m_s=_per_host_second((truth.vx, truth.vy, truth.vz), self.clock_rate),
            )
            if self.vision is not None and self.transport is not None:
                odometry = self.vision.message(arrived_s, truth)
                if odometry is not None:
                    self.transport.sendto(odometry, addr)

    def _ask_rate(self, addr: tuple[str | Any, int]) -> None:
        self.asked, self.address = True, addr
        self.ask_rate(self.clock_rate)

    def ask_rate(self, clock_rate: float) -> None:
        """Ask for ``rate_hz`` per second of host time from an instance whose clock runs at
        ``clock_rate`` x the host's (PX4's intervals are on its own clock; at speed factor 2 the
        aid would otherwise parse twice as much), and for none of the HIL_ACTUATOR_CONTROLS PX4
        also sends on this link (200 Hz of its clock, for a viewer: at 2x, 70 % of what the aid
        received and parsed). Before its first message, only noted."""
        self.clock_rate = clock_rate
        if self.rate_hz is None or self.transport is None or self.address is None:
            return
        self._asks += 1
        sender = mavlink.MAVLink(
            None, srcSystem=255, srcComponent=mavlink.MAV_COMP_ID_MISSIONPLANNER
        )
        for message_id, interval_us in (
            (mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION, 1e6 * clock_rate / self.rate_hz),
            (mavlink.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS, -1),  # -1: stop the stream
        ):
            request = mavlink.MAVLink_command_long_message(
                self.vehicle_id,
                1,
                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                message_id,
                interval_us,
                0,
                0,
                0,
                0,
                0,
            )
            self.transport.sendto(request.pack(sender), self.address)
        # Asked again at every mission clock change: the first ask and the start's are the news.
        logger.log(
            logging.DEBUG if self._asks > 1 else logging.INFO,
            "vehicle %s: ground truth asked for at %g Hz (from %s:%s, clock %gx)",
            self.vehicle_id,
            self.rate_hz,
            *self.address,
            clock_rate,
        )


async def _sih_source(
    stack: contextlib.AsyncExitStack,
    positions: _Positions,
    port_base: int,
    rate_hz: float | None,
    vision: dict[int, VisionOdometry],
    *,
    unix_s: Callable[[], float],
) -> list[_TruthProtocol]:
    loop = asyncio.get_running_loop()
    protocols: list[_TruthProtocol] = []
    for vehicle_id in positions.ids:
        port = port_base + vehicle_id - 1
        protocol = functools.partial(
            _TruthProtocol, positions, vehicle_id, rate_hz, vision.get(vehicle_id), unix_s=unix_s
        )
        try:
            transport, _ = await loop.create_datagram_endpoint(
                protocol,
                local_addr=("127.0.0.1", port),
            )
        except OSError as error:
            raise RunnerError(
                f"cannot listen for vehicle {vehicle_id}'s ground truth on UDP {port}: "
                f"{error.strerror} (--truth-port-base moves it)"
            ) from None
        stack.callback(transport.close)
        protocols.append(cast(_TruthProtocol, transport.get_protocol()))
    return protocols


async def _gps_source(
    stack: contextlib.AsyncExitStack,
    positions: _Positions,
    urls: list[str],
    mission_time: MissionTime,
    group: asyncio.TaskGroup,
) -> None:
    """Stream every vehicle's GLOBAL_POSITION_INT into ``positions`` (tasks in ``group``, cancelled
    when ``stack`` closes)."""
    ids = positions.ids
    tasks: list[asyncio.Task[None]] = []
    systems = await stack.enter_async_context(connected_vehicles(urls, ids, url_setting="--url"))
    for vehicle_id in ids:
        vehicle = await stack.enter_async_context(MavsdkVehicle(systems[vehicle_id], vehicle_id))
        await vehicle.request_rate(vehicle.telemetry.set_rate_position(POSITION_RATE_HZ))
        mapping = await vehicle.follow_clock(mission_time)
        tasks.append(
            group.create_task(_gps_stream(vehicle, mapping, positions), name=f"gps-{vehicle_id}")
        )
    stack.callback(lambda: [task.cancel() for task in tasks])


async def _gps_stream(vehicle: MavsdkVehicle, mapping: ClockMapping, positions: _Positions) -> None:
    stream = vehicle.raw.subscribe_message("GLOBAL_POSITION_INT")
    async with contextlib.aclosing(stream):
        async for message in stream:
            if message.system_id != vehicle.system_id:
                continue
            fields = json.loads(message.fields_json)
            positions.add(
                vehicle.system_id,
                mapping.unix_s(fields["time_boot_ms"] / 1000.0),
                fields["lat"] / 1e7,
                fields["lon"] / 1e7,
                fields["alt"] / 1000.0,
                velocity_ned_m_s=_per_host_second(
                    (fields["vx"], fields["vy"], fields["vz"]), mapping.fit.boot_rate
                ),
            )


async def run_range_provider(
    scenario: Scenario,
    *,
    source: str = "sih",
    urls: Iterable[str] = (),
    truth_port_base: int = TRUTH_PORT_BASE,
    truth_rate_hz: float | None = TRUTH_RATE_HZ,
    vision: VisionSettings | None = None,
    steps: int | None = None,
    seed: int = 0,
    start_timeout_s: float = 600.0,
    vision_after_s: float = VISION_AFTER_STEPS_S,
    unix_s: Callable[[], float] = time.time,
) -> RangeStats:
    """Publish synthetic ranges for ``steps`` steps (default: the scenario's) from the ground
    station's start, and with ``vision`` (``sih`` only) a vision odometry to every instance from
    the moment its truth arrives until every vehicle is done or ``vision_after_s`` after the
    last step. Returns :class:`RangeStats`. ``unix_s``: the UNIX clock the mission clock, the
    truth's arrivals and the steps' deadlines read."""
    truth_rate_hz = _truth_rate(scenario, source, vision, truth_rate_hz)
    topics = scenario.bus.topics(scenario.name)
    ranging = RangingGraph.of(scenario)
    frame = None if ranging is None else ranging.frame
    n, step_s = len(scenario.vehicles), scenario.timing.step_s
    logger.info(ranging_plan(n, scenario.sensors, step_s, frame))
    mission_time = MissionTime(unix=unix_s)
    positions = _Positions(scenario)
    odometry = {
        vehicle.id: VisionOdometry(
            vehicle.id, vision, np.random.default_rng([seed, 12, vehicle.id])
        )
        for vehicle in scenario.vehicles
        if vision is not None
    }
    async with contextlib.AsyncExitStack() as stack:
        bus = await stack.enter_async_context(
            open_bus(
                scenario.bus, sender=Sender.ranges(), client_id=f"{scenario.name}-range-provider"
            )
        )
        control = await stack.enter_async_context(bus.subscribe(topics.control()))
        group = await stack.enter_async_context(asyncio.TaskGroup())
        truth: list[_TruthProtocol] = []
        if source == "sih":
            truth = await _sih_source(
                stack, positions, truth_port_base, truth_rate_hz, odometry, unix_s=unix_s
            )
        else:
            await _gps_source(stack, positions, list(urls), mission_time, group)
        start = await _take_start(control, mission_time, truth, start_timeout_s)
        following = group.create_task(
            _follow_clock(control, mission_time, truth, start.mission_id), name="aid-clock"
        )
        stack.callback(following.cancel)  # before the task group waits for its tasks
        # Up to 1.5 periods of the positions' rate: SIH's truth as asked, or the GPS stream's.
        rate_hz = (truth_rate_hz or SIH_TRUTH_RATE_HZ) if source == "sih" else POSITION_RATE_HZ
        aid = _AidSteps(bus, topics, scenario, mission_time, positions, unix_s, ranging)
        rates = _Rates(positions, odometry, unix_s)
        stats = await aid.run(
            start.time_s,
            scenario.timing.steps if steps is None else steps,
            np.random.default_rng([seed, 11]),
            extrapolate_s=EXTRAPOLATE_PERIODS / rate_hz,
        )
        rates.measure(stats)
        if odometry:
            await _vision_while_landing(
                bus, topics, scenario, start.mission_id, stats=stats, timeout_s=vision_after_s
            )
    return stats


async def _vision_while_landing(
    bus: Bus,
    topics: Topics,
    scenario: Scenario,
    mission_id: str | None,
    *,
    stats: RangeStats,
    timeout_s: float,
) -> None:
    """Keep the vision odometry going (the truth links stay open) until every vehicle of the
    scenario reports itself done for ``mission_id`` (statuses are retained: one done before
    this began counts), or ``timeout_s``."""
    waiting = {vehicle.id for vehicle in scenario.vehicles}
    began_s = time.monotonic()
    logger.info("vision odometry kept on while the vehicles land (at most %g s)", timeout_s)
    async with bus.subscribe(topics.all_status()) as heard:
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                async for _, status in heard.messages(VehicleStatus):
                    if status.mission_id == mission_id and status.state == ControllerState.DONE:
                        waiting.discard(status.vehicle_id)
                    if not waiting:
                        break
    stats.vision_after_steps_s = time.monotonic() - began_s
    stats.vehicles_done = len(scenario.vehicles) - len(waiting)
    if waiting:
        logger.warning(
            "vision odometry stopped %g s after the last step with vehicles %s not done",
            timeout_s,
            sorted(waiting),
        )


def _truth_rate(
    scenario: Scenario, source: str, vision: VisionSettings | None, truth_rate_hz: float | None
) -> float | None:
    """The truth rate to ask SIH for (the vision's, if faster); raises on a setting the aid
    cannot serve."""
    if scenario.bus.kind != "mqtt":
        raise RunnerError("the range provider publishes for vehicle processes: set bus.kind: mqtt")
    if source not in SOURCES:
        raise RunnerError(f"unknown range source {source!r}: use one of {', '.join(SOURCES)}")
    if vision is not None and source != "sih":
        raise RunnerError("a vision odometry is made from a simulator's truth: use --source sih")
    if vision is not None and truth_rate_hz is not None:
        return max(truth_rate_hz, vision.rate_hz)
    return truth_rate_hz


async def _take_start(
    control: Subscription,
    mission_time: MissionTime,
    truth: Sequence[_TruthProtocol],
    timeout_s: float,
) -> MissionControl:
    """The ground station's start: the mission clock set by it, and SIH's truth asked at its
    rate where the clock does not run at 1x."""
    start = await start_command(control, timeout_s=timeout_s)
    freeze_heap()
    mission_time.set(start.clock_rate or 1.0, start.clock_reference_s or start.time_s)
    if mission_time.rate != 1.0:
        for protocol in truth:
            protocol.ask_rate(mission_time.rate)
    return start


@dataclass
class _AidSteps:
    """The aid's step loop: at each t_k (on the mission clock), the positions of that instant,
    and the step's ranges published while its deadline has not passed."""

    bus: Bus
    topics: Topics
    scenario: Scenario
    mission_time: MissionTime
    positions: _Positions
    unix_s: Callable[[], float]
    ranging: RangingGraph | None = None

    async def run(
        self, start_s: float, steps: int, rng: np.random.Generator, *, extrapolate_s: float
    ) -> RangeStats:
        stats = RangeStats()
        uwb = UwbRanging(
            self.scenario.sensors,
            len(self.scenario.vehicles),
            self.scenario.timing.step_s,
            graph=None if self.ranging is None else self.ranging.frame,
        )
        for k in range(steps):
            t_k = start_s + k * self.scenario.timing.step_s
            unix_k = self.mission_time.to_unix(t_k)
            await asyncio.sleep(max(0.0, unix_k - self.unix_s()))
            deadline_s = self.mission_time.to_unix(t_k + self.scenario.flight.step_deadline_s)
            # Behind (short of CPU: four PX4 at speed factor 2 on two cores), a step already past
            # its deadline only costs the time the next ones need: the aid was seconds behind at
            # p95 and stayed there, every vehicle holding for want of ranges.
            publish = self.unix_s() <= deadline_s
            stats.skipped += not publish
            wait_s = min(MAX_WAIT_S, max(0.0, deadline_s - self.unix_s()))
            now = await self.positions.bracketing(unix_k, wait_s, extrapolate_s=extrapolate_s)
            graph = (
                None if self.ranging is None else self.ranging.among(self.positions.heard(unix_k))
            )
            await _publish_step(
                self.bus,
                self.topics,
                self.scenario,
                now,
                k,
                t_k,
                start_s,
                (rng, uwb),
                stats,
                publish=publish,
                graph=graph,
            )
            if publish:
                stats.lateness_s.append(self.mission_time.now_s() - t_k)
        return stats


class _Rates:
    """The positions' and the vision's rates over the steps, from their counts when made."""

    def __init__(
        self,
        positions: _Positions,
        odometry: Mapping[int, VisionOdometry],
        unix_s: Callable[[], float],
    ) -> None:
        self.positions, self.odometry, self.unix_s = positions, odometry, unix_s
        self.started_s = unix_s()
        self.received = {i: p.received for i, p in positions.vehicles.items()}
        self.sent = {i: o.sent for i, o in odometry.items()}

    def measure(self, stats: RangeStats) -> None:
        elapsed_s = max(self.unix_s() - self.started_s, 1e-9)
        stats.position_rates_hz = {
            i: (p.received - self.received[i]) / elapsed_s
            for i, p in self.positions.vehicles.items()
        }
        stats.vision_rates_hz = {
            i: (o.sent - self.sent[i]) / elapsed_s for i, o in self.odometry.items()
        }


async def _follow_clock(
    control: Subscription,
    mission_time: MissionTime,
    truth: Sequence[_TruthProtocol],
    mission_id: str | None,
) -> None:
    """Take the ground's mission clock changes as the vehicles take them (the aid's steps keep
    theirs), and ask the simulators' truth at the new rate."""
    while True:
        command = await next_command(control, {ControlCommand.CLOCK}, mission_id=mission_id)
        if take_clock_change(command, mission_time, unix_clock=mission_time.unix_now_s):
            for protocol in truth:
                protocol.ask_rate(mission_time.latest_rate)


async def _publish_step(  # noqa: PLR0917
    bus: Bus,
    topics: Topics,
    scenario: Scenario,
    positions_m: NDArray[np.float64],
    k: int,
    t_k: float,
    start_s: float,
    noise: tuple[np.random.Generator, UwbRanging],
    stats: RangeStats,
    *,
    publish: bool = True,
    graph: NDArray[np.bool_] | None = None,
) -> None:
    """Publish step ``k``'s ranges and target observations from ``positions_m`` ``(n, 3)``
    (north-east-down [m], NaN rows: no position; ``publish``: False to only record) and
    record its truth in ``stats``. ``noise``: the aid's generator and its radios (a step not
    published still ages their errors at the next one). ``graph`` ``(n, n)``: the pairs
    scheduled to range (None: every pair)."""
    rng, uwb = noise
    ids = [v.id for v in scenario.vehicles]
    known = ~np.isnan(positions_m[:, 0])
    stats.steps += 1
    elapsed = np.array([t_k - start_s, t_k - start_s + 1e-3])
    target = target_positions(scenario.target.path, elapsed)
    stats.truth.append(TruthSample(k, t_k, target[0], positions_m[:, :2].copy(), known))
    stats.missing_vehicles += int((~known).sum())
    if not publish:
        return
    measured = step_measurements(
        k,
        t_k,
        ids=ids,
        topics=topics,
        positions_m=positions_m,
        ranging=known,
        tracking=known & [vehicle.senses_target for vehicle in scenario.vehicles],
        target_m=target[0],
        target_velocity_m_s=(target[1] - target[0]) / 1e-3,
        sensors=scenario.sensors,
        rng=rng,
        uwb=uwb,
        graph=graph,
    )

    # All at once: one after the other, each waited for the loop to write it out, and with four
    # PX4 at 2x on two cores that put the aid's p95 at 0.3 s after t_k.
    errors = await publish_measurements(bus, measured, timeout_s=PUBLISH_TIMEOUT_S)
    for (_, message), error in zip(measured, errors, strict=True):
        if error is not None:
            # Lost like a UWB packet: the receivers see a dropout; the next step goes on.
            stats.unsent += 1
            if stats.unsent == 1:
                logger.warning("step %d: %s (dropped; counted in the last line)", k, error)
        elif isinstance(message, RangeSet):
            stats.ranges += len(message.ranges_m)
