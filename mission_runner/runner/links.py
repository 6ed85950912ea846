"""Vehicles through MAVSDK (``mavsdk`` 4.x, ``mavsdk.asyncio``): the same code for the bundled
emulator and for real PX4 over UDP or serial.

One :class:`Mavsdk` object serves every vehicle of a process (:func:`connected_vehicles`). Each
:class:`MavsdkVehicle` streams its own odometry - LOCAL_POSITION_NED through MAVSDK's raw-message
plugin, because the step alignment needs the autopilot's timestamp (``time_boot_ms``), which
MAVSDK's telemetry plugin drops - and sends velocity setpoints in OFFBOARD.

Failsafe: the controller only ever *streams* setpoints, one a step, itself: nothing re-sends
them for it. If it dies or stalls, the stream stops and PX4's offboard-loss failsafe
(COM_OF_LOSS_T, then COM_OBL_RC_ACT) holds or lands the vehicle; if the link drops, PX4's
data-link-loss failsafe does. :meth:`MavsdkVehicle.finish` lands, returns or holds on a normal
end.

The setpoints go out as SET_POSITION_TARGET_LOCAL_NED through MAVSDK's raw-message plugin, not
MAVSDK's offboard plugin: that one re-sends the last setpoint every 50 ms from its own thread
until ``offboard.stop()``, which also commands HOLD (a pilot's mode is the pilot's), or until a
HEARTBEAT shows the vehicle out of OFFBOARD, and a setpoint that crosses that heartbeat starts
it again for a 3 s grace (MAVSDK ``offboard_impl.cpp``). Whatever stops the runner driving a
vehicle stops its setpoints at once and for good: :meth:`MavsdkVehicle.release` (see there for
who gets which command).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ctypes
import dataclasses
import json
import logging
import math
import threading
import time
from collections.abc import AsyncGenerator, AsyncIterator, Awaitable, Callable, Coroutine, Mapping
from typing import Any, Self, TypeVar

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkError
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync, MavlinkMessage
from mavsdk.asyncio.plugins.param import ParamAsync, ParamError, ParamResult
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.logging import LogLevel, log_subscribe

from . import mavlink_ids as mavlink
from .errors import RunnerTimeoutError, VehicleCommandError, VehicleConnectionError
from .odometry import ODOMETRY_RATE_HZ, FedTrack, OdometrySample, OdometryTrack
from .timesync import ClockMapping, ClockMappingError, FedClockMapping, MissionTime

_T = TypeVar("_T")

logger = logging.getLogger(__name__)

#: The most a velocity setpoint is scaled from mission to autopilot seconds (see
#: :attr:`MavsdkVehicle.velocity_scale`): clocks further apart than this are not one mission's,
#: and a broken or hostile SYSTEM_TIME must not multiply the vehicle's speed.
MAX_VELOCITY_SCALE = 1.25
SYSTEM_TIME_RATE_HZ = 10.0  # pairs to interpolate a jittery simulated clock between
#: Streams PX4 sends a companion computer's (onboard) link by default that a vehicle flying the
#: mission never reads (PX4 v1.16 mavlink_main.cpp, MAVLINK_MODE_ONBOARD), with their default
#: rates [Hz], each packed by PX4's mavlink thread and parsed by MAVSDK's receive thread (PX4 SIH
#: at 1x, odometry at 50 Hz: 269 messages a second came, 67 once these but the last two were
#: stopped, 13 of those DISTANCE_SENSOR and GPS_RAW_INT). Stopped once the vehicle flies in
#: OFFBOARD (take-off and health need some of them); the link is the companion computer's own
#: (a ground station has its own link and rates).
UNREAD_STREAMS = {
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 100.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 50.0,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: 30.0,
    mavlink.MAVLINK_MSG_ID_RC_CHANNELS: 20.0,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 10.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET: 10.0,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 10.0,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT: 10.0,
    mavlink.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT: 10.0,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 10.0,
    mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: 10.0,
    mavlink.MAVLINK_MSG_ID_WIND_COV: 10.0,
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR: 10.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: math.inf,  # each fix (5 Hz in SIH)
}
#: Height above which a vehicle taking off is airborne enough to be handed to OFFBOARD.
TAKEOFF_CLEAR_M = 2.0
#: How long a refused arm is asked again, and how often [s].
ARM_RETRY_S = 15.0
ARM_RETRY_INTERVAL_S = 1.0
#: How many times OFFBOARD is asked for, each after a fresh zero-velocity setpoint, and how long
#: apart [s]: PX4 refuses it ("no setpoints") when the setpoint before the request was lost.
OFFBOARD_ATTEMPTS = 5
OFFBOARD_RETRY_INTERVAL_S = 0.2
#: How often discovery looks for the vehicles it waits for [s].
DISCOVERY_POLL_S = 0.1
#: PX4 sends HEARTBEAT at 1 Hz, so a disarm happened up to a period before the heartbeat that
#: shows it, and a vehicle disarmed in the air falls meanwhile (5 m in the first second): its
#: height at the disarm is the highest of this much of its odometry before [autopilot s].
DISARM_LOOKBACK_S = 1.5
#: Above this height (odometry, from an origin on the ground) a disarm was in the air [m].
IN_AIR_ABOVE_M = 0.5
#: The runner's address on the vehicle's link: MAVSDK's own ids as a ground station.
OWN_SYSTEM_ID = 245
OWN_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER
#: PX4's main mode OFFBOARD (``px4_custom_mode.h``), for MAV_CMD_DO_SET_MODE's param2.
PX4_MAIN_MODE_OFFBOARD = 6
#: SET_POSITION_TARGET_LOCAL_NED's type_mask for a velocity and a yaw: position, acceleration
#: and yaw rate ignored (what MAVSDK's offboard plugin sends for ``set_velocity_ned``).
VELOCITY_YAW_MASK = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)
_mavsdk_logging_routed = False
_threads_kept: set[int] = set()


def keep_thread_state() -> None:
    """Keep the Python thread state of the MAVSDK thread calling back, for the thread's life.

    ctypes makes a thread state for each callback on a thread Python did not start and frees it
    after (PyGILState_Ensure/Release), and Python 3.11 maps and unmaps a frame stack with each:
    the unmap interrupts every core (a TLB shootdown), dearer than the callback itself (0.3 %
    of a core at 35 odometry samples a second on PX4 SIH). One more Ensure, never released,
    keeps the thread state; ctypes' Release still hands the GIL back after each callback.
    """
    thread = threading.get_ident()
    if thread not in _threads_kept:
        ctypes.pythonapi.PyGILState_Ensure()
        _threads_kept.add(thread)


_REASON_SEVERITIES = frozenset({"EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING"})


def route_mavsdk_logs() -> None:
    """Send MAVSDK's own log lines to the ``mavsdk`` Python logger instead of stdout."""
    global _mavsdk_logging_routed  # noqa: PLW0603 - MAVSDK's log hook is process-wide
    if _mavsdk_logging_routed:
        return
    mavsdk_logger = logging.getLogger("mavsdk")
    levels = {
        LogLevel.DEBUG: logging.DEBUG,
        LogLevel.INFO: logging.DEBUG,
        LogLevel.WARN: logging.WARNING,
        LogLevel.ERROR: logging.ERROR,
    }

    def forward(level: Any, message: str, _file: str, _line: int) -> bool:
        mavsdk_logger.log(levels.get(level, logging.INFO), "%s", message)
        return True

    log_subscribe(forward)
    _mavsdk_logging_routed = True


@contextlib.asynccontextmanager
async def connected_vehicles(
    urls: list[str],
    system_ids: list[int],
    *,
    timeout_s: float = 20.0,
    url_setting: str = "the connection URL",
) -> AsyncIterator[dict[int, Any]]:
    """One Mavsdk with a connection per URL, until every system id in ``system_ids`` is found.

    Yields ``{system_id: mavsdk System}``. URLs are MAVSDK's: ``udpin://0.0.0.0:14540``,
    ``serial:///dev/ttyACM0:57600``. Raises :class:`VehicleConnectionError` if a URL cannot be
    opened (its message names ``url_setting``, what moves it) or a vehicle is not found.
    """
    route_mavsdk_logs()
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        for url in urls:
            try:
                await mavsdk.add_any_connection(url)
            except MavsdkError as error:
                raise VehicleConnectionError(
                    f"MAVSDK cannot open {url} ({error}): for udpin:// its UDP port may be "
                    f"taken by another program (a ground station, PX4 SITL, another run); "
                    f"choose another with {url_setting}"
                ) from None
        wanted = set(system_ids)
        found: dict[int, Any] = {}
        try:
            async with asyncio.timeout(timeout_s):
                async for _ in _discovery_ticks():
                    for system in await mavsdk.get_systems():
                        if await system.has_autopilot():
                            found.setdefault(await system.get_system_id(), system)
                    if wanted <= found.keys():
                        break
        except TimeoutError:
            missing = sorted(wanted - found.keys())
            raise VehicleConnectionError(
                f"vehicles with MAVLink system ids {missing} not found on {urls} within "
                f"{timeout_s:g} s; check the vehicles run and the connection URLs/ports"
            ) from None
        yield {sysid: found[sysid] for sysid in wanted}


async def _discovery_ticks() -> AsyncIterator[None]:
    """Yield at once, then every DISCOVERY_POLL_S. (MAVSDK's new-system stream is an async
    generator: a timeout around its ``anext`` ends it for good, and discovery died with
    StopAsyncIteration whenever the vehicle was not up within the first wait - a vehicle
    process started with PX4, as docs/real-px4.md's block does.)"""
    while True:
        yield
        await asyncio.sleep(DISCOVERY_POLL_S)


def _resolve(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)


class MappedTrack:
    """A vehicle's odometry track (on its autopilot's boot clock) read on the mission clock:
    ``boot_s_at(mission_s)`` maps the query time, so a better clock fit applies at once to every
    sample already received."""

    def __init__(self, track: OdometryTrack, boot_s_at: Callable[[float], float]) -> None:
        self._track = track
        self._boot_s_at = boot_s_at

    @property
    def latest(self) -> OdometrySample | None:
        return self._track.latest

    def at(
        self, mission_s: float, *, extrapolate_s: float = 0.0
    ) -> tuple[float, float, float] | None:
        """``(north_m, east_m, down_m)`` at mission time ``mission_s``, or None (no two samples
        bracket it and the newest is more than ``extrapolate_s`` of the autopilot's clock
        before it, see :meth:`OdometryTrack.at`; or the autopilot's clock is not known yet)."""
        try:
            boot_s = self._boot_s_at(mission_s)
        except ClockMappingError:
            return None
        return self._track.at(boot_s, extrapolate_s=extrapolate_s)


@dataclasses.dataclass(frozen=True)
class Disarm:
    """A disarm the runner saw (HEARTBEAT): when (``time.monotonic()``) and the vehicle's height
    then (the highest of its odometry in the :data:`DISARM_LOOKBACK_S` before; None without
    odometry)."""

    seen_s: float
    height_m: float | None

    @property
    def in_air(self) -> bool:
        return self.height_m is not None and self.height_m > IN_AIR_ABOVE_M


#: How long the runner waits for a vehicle in the air to reach a safe state (landed and
#: disarmed, or in RTL or hold) when its mission ends abnormally [s].
SAFE_STATE_TIMEOUT_S = 30.0


class MavsdkVehicle:
    """One PX4 vehicle. An async context manager that owns its telemetry tasks.

    Odometry samples are kept on the autopilot's boot clock (``time_boot_ms``); ``odometry``
    reads them on the mission clock. By default boot time *is* mission time (the in-process
    emulator, whose boot clock is the simulated time); :meth:`follow_clock` maps it through
    SYSTEM_TIME onto a :class:`.timesync.MissionTime` instead, continuously.
    """

    def __init__(self, system: Any, system_id: int, *, command_timeout_s: float = 10.0) -> None:
        self.system = system
        self.system_id = system_id
        self.action = ActionAsync(system)
        self.telemetry = TelemetryAsync(system)
        self.param = ParamAsync(system)
        self.raw = MavlinkDirectAsync(system)
        self.track = FedTrack()
        self.boot_s_at: Callable[[float], float] = float
        self.odometry = MappedTrack(self.track, self._boot_s)
        self.clock_mapping: ClockMapping | None = None
        self._mission_time: MissionTime | None = None
        self._scale_bounded = False  # warned once that the clocks are too far apart
        #: Setpoints whose scale was bounded (clocks too far apart to fly what the law asked).
        self.scale_bounded_setpoints = 0
        self.status_texts: collections.deque[tuple[float, str, str]] = collections.deque(
            maxlen=50
        )  # (monotonic s, severity, text)
        self._status_text = asyncio.Event()
        self._timeout_s = command_timeout_s
        self._odometry_waiters: set[asyncio.Future[None]] = set()
        self.odometry_malformed = 0  # LOCAL_POSITION_NED samples that could not be read
        self.clock_malformed = 0  # SYSTEM_TIME messages that could not be read
        self.clock_fed = asyncio.Event()  # a SYSTEM_TIME pair came (until the mapping is ready)
        self._group: asyncio.TaskGroup | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._stack = contextlib.AsyncExitStack()
        self.in_offboard = False
        self.flight_mode: str | None = None  # as the autopilot reports it (HEARTBEAT)
        self.armed: bool | None = None
        self._seen_in_control = False
        self._control_lost: str | None = None
        #: Why the runner stopped driving the vehicle (None: it may still); final.
        self.released: str | None = None
        #: Setpoints the controller asked for after that, not sent.
        self.setpoints_withheld = 0
        self._streamed = False  # a setpoint of the runner's went out
        self._ending: asyncio.Task[None] | None = None  # the mode command release() gives
        self.disarms: list[Disarm] = []

    def _boot_s(self, mission_s: float) -> float:
        return self.boot_s_at(mission_s)  # late-bound: follow_clock replaces boot_s_at

    async def __aenter__(self) -> Self:
        async with contextlib.AsyncExitStack() as stack:
            self._group = await stack.enter_async_context(asyncio.TaskGroup())
            stack.callback(self._cancel_streams)  # they run for ever: end them, then the group
            self._stream_odometry(stack)
            self._spawn(self._collect_status_texts(), "statustext")
            self._spawn(self._watch_flight_mode(), "flight-mode")
            self._spawn(self._watch_armed(), "armed")
            await self.request_rate(self.telemetry.set_rate_position_velocity_ned(ODOMETRY_RATE_HZ))
            self._stack = stack.pop_all()
        return self

    async def request_rate(self, request: Awaitable[object]) -> None:
        """A telemetry rate change, within the command timeout; a vehicle may refuse or ignore
        it (then its own rate is used), which is logged, not fatal."""
        try:
            await self._within(request, "telemetry rate")
        except (MavsdkError, RunnerTimeoutError) as error:
            logger.info("vehicle %s: rate change not taken (%s)", self.system_id, error)

    async def __aexit__(self, *exc_info: Any) -> bool | None:
        # Nothing more of ours; closing the Mavsdk (connected_vehicles) ends MAVSDK's stream.
        self._withhold("the runner's link to it closed")
        return await self._stack.__aexit__(*exc_info)

    def _cancel_streams(self) -> None:
        for task in self._tasks:
            task.cancel()

    def _spawn(self, coroutine: Coroutine[Any, Any, None], what: str) -> None:
        if self._group is None:
            raise RuntimeError("MavsdkVehicle used outside its async with block")
        self._tasks.append(
            self._group.create_task(coroutine, name=f"vehicle-{self.system_id}-{what}")
        )

    def _stream_odometry(self, stack: contextlib.AsyncExitStack) -> None:
        """LOCAL_POSITION_NED into :attr:`track` straight from MAVSDK's receive thread (see
        :class:`.odometry.FedTrack`), waking :meth:`odometry_updated`'s waiters only; the
        subscription ends when ``stack`` closes."""
        loop = asyncio.get_running_loop()
        # The blocking plugin under the asyncio one: its callbacks run in MAVSDK's thread.
        plugin = self.raw._plugin

        def wake() -> None:
            for waiter in tuple(self._odometry_waiters):
                loop.call_soon_threadsafe(_resolve, waiter)

        def received(message: Any, _user_data: object) -> None:
            keep_thread_state()
            if message.system_id != self.system_id:
                return
            try:
                fields = json.loads(message.fields_json)
                sample = OdometrySample(
                    float(fields["time_boot_ms"]) / 1000.0,
                    *(float(fields[name]) for name in ("x", "y", "z", "vx", "vy", "vz")),
                )
            except (ValueError, KeyError, TypeError):
                self.odometry_malformed += 1
                return
            self.track.feed(sample)

        self.track.on_feed = wake
        handle = plugin.subscribe_message("LOCAL_POSITION_NED", received)
        stack.callback(plugin.unsubscribe_message, handle)

    async def _collect_status_texts(self) -> None:
        stream = self.telemetry.subscribe_status_text()
        async with contextlib.aclosing(stream):
            async for status in stream:
                # This process's own monotonic clock, as the commands' (_commanded): it tells
                # which autopilot messages came after a command was sent.
                self.status_texts.append((time.monotonic(), status.type.name, status.text))
                logger.info("vehicle %s says: %s", self.system_id, status.text)
                self._status_text.set()

    async def _watch_flight_mode(self) -> None:
        stream = self.telemetry.subscribe_flight_mode()
        async with contextlib.aclosing(stream):
            async for mode in stream:
                self.flight_mode = mode.name
                self._check_control()

    async def _watch_armed(self) -> None:
        stream = self.telemetry.subscribe_armed()
        async with contextlib.aclosing(stream):
            async for armed in stream:
                was, self.armed = self.armed, bool(armed)
                if was and not self.armed:
                    self._note_disarm()
                self._check_control()

    def _note_disarm(self) -> None:
        sample = self.track.latest
        highest = (
            None if sample is None else self.track.highest_since(sample.time_s - DISARM_LOOKBACK_S)
        )
        # This process's own monotonic clock: when the runner saw it, for logs and the ending.
        self.disarms.append(Disarm(time.monotonic(), None if highest is None else -highest))

    @property
    def in_control(self) -> bool:
        """Seen armed and in OFFBOARD since :meth:`start_offboard` (and not taken over)."""
        return (
            self._seen_in_control
            and self._control_lost is None
            and self.released is None
            and self._offboard_now()
        )

    @property
    def control_lost(self) -> str | None:
        """Why someone else took the vehicle out of OFFBOARD (or disarmed it) while the runner
        drove it; None while nobody has. Final until the next :meth:`start_offboard`."""
        return self._control_lost

    def _offboard_now(self) -> bool:
        return self.flight_mode == "OFFBOARD" and self.armed is True

    def _check_control(self) -> None:
        if not self.in_offboard or self._control_lost is not None:
            return
        if self._offboard_now():
            self._seen_in_control = True
        elif self._seen_in_control:
            # Only after OFFBOARD was seen: a heartbeat sent before the switch is not a takeover.
            disarmed = self.armed is False
            what = self._disarm_words() if disarmed else f"switched to {self.flight_mode}"
            self._control_lost = (
                f"{what} by someone other than the runner (pilot, another ground station or a "
                "failsafe)"
            )
            logger.warning("vehicle %s: %s", self.system_id, self._control_lost)
            self.release(self._control_lost)

    async def reason_since(self, since_s: float, *, wait_s: float = 1.0) -> str | None:
        """The autopilot's last warning-or-worse STATUSTEXT since monotonic ``since_s`` (PX4
        explains a refusal that way, usually just after its COMMAND_ACK), waiting up to
        ``wait_s`` for one; None if it said nothing."""

        def latest() -> str | None:
            for at_s, severity, text in reversed(self.status_texts):
                if at_s >= since_s and severity in _REASON_SEVERITIES:
                    return text
            return None

        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(wait_s):
                while latest() is None:
                    self._status_text.clear()
                    await self._status_text.wait()
        return latest()

    async def follow_clock(
        self, mission_time: MissionTime, *, timeout_s: float = 10.0
    ) -> ClockMapping:
        """Map this autopilot's boot clock onto ``mission_time`` from now on, refitted at every
        SYSTEM_TIME (requested at ``SYSTEM_TIME_RATE_HZ``). Returns the :class:`ClockMapping`
        once it has its first pair; raises :class:`RunnerTimeoutError` if none comes."""
        mapping = FedClockMapping()
        self._stream_clock(mapping)
        with contextlib.suppress(VehicleCommandError, RunnerTimeoutError):
            # Some autopilots stream it anyway; PX4 SITL sends it at 1 Hz by default.
            await self.request_interval(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, SYSTEM_TIME_RATE_HZ)
        try:
            async with asyncio.timeout(timeout_s):
                while not mapping.ready:
                    await self.clock_fed.wait()
                    self.clock_fed.clear()
        except TimeoutError:
            raise RunnerTimeoutError(
                f"vehicle {self.system_id}: SYSTEM_TIME with a UNIX time (is the autopilot's "
                "clock set?)",
                timeout_s,
            ) from None
        self.clock_mapping = mapping
        self._mission_time = mission_time
        self.boot_s_at = lambda mission_s: mapping.boot_s(mission_time.to_unix(mission_s))
        return mapping

    def _stream_clock(self, mapping: FedClockMapping) -> None:
        """SYSTEM_TIME pairs into ``mapping`` straight from MAVSDK's thread (as odometry, see
        :meth:`_stream_odometry`), waking :attr:`clock_fed` only until the mapping is ready; the
        subscription ends when the vehicle's link closes."""
        loop = asyncio.get_running_loop()
        plugin = self.raw._plugin  # the blocking plugin: its callbacks run in MAVSDK's thread

        def received(message: Any, _user_data: object) -> None:
            keep_thread_state()
            if message.system_id != self.system_id:
                return
            try:
                fields = json.loads(message.fields_json)
                boot_s, unix_s = fields["time_boot_ms"] / 1000.0, fields["time_unix_usec"] / 1e6
            except (ValueError, KeyError, TypeError):
                self.clock_malformed += 1
                return
            if unix_s:
                mapping.feed(boot_s, unix_s)
                if not mapping.fitted:  # the loop's thread adds the pairs as it reads them
                    loop.call_soon_threadsafe(self.clock_fed.set)

        handle = plugin.subscribe_message("SYSTEM_TIME", received)
        self._stack.callback(plugin.unsubscribe_message, handle)

    @property
    def velocity_scale(self) -> float:
        """Mission seconds per autopilot (boot-clock) second: what a velocity in metres per
        mission second is multiplied by to be the setpoint the autopilot integrates on its own
        clock. 1 where boot time is mission time (the in-process emulator) and before the
        mission starts (holds); with :meth:`follow_clock`, once the ground's start has set the
        mission clock, its rate over the fitted boot-clock rate. PX4 SIH's clock runs at
        0.95-0.99x wall time at speed factor 1 and 1.93-1.96x at 2, and the mission clock at
        the rate the ground chose at the start: unscaled, a vehicle moved up to 2 % (7 % at 2x)
        off what the law commanded. Bounded to [1/MAX_VELOCITY_SCALE, MAX_VELOCITY_SCALE]."""
        mapping, mission_time = self.clock_mapping, self._mission_time
        if mapping is None or mission_time is None or not mission_time.started:
            return 1.0
        scale = mission_time.rate * mapping.fit.rate
        bounded = min(max(scale, 1.0 / MAX_VELOCITY_SCALE), MAX_VELOCITY_SCALE)
        if bounded != scale:
            self.scale_bounded_setpoints += 1
        if bounded != scale and not self._scale_bounded:
            self._scale_bounded = True
            logger.warning(
                "vehicle %s: its clock runs %.3fx the mission clock; velocity setpoints are "
                "scaled by %.3f, not %.3f (is its SYSTEM_TIME right?)",
                self.system_id,
                1.0 / scale,
                bounded,
                scale,
            )
        return bounded

    async def quiet_unread_streams(self) -> None:
        """Stop the :data:`UNREAD_STREAMS` on this link. An autopilot that refuses one keeps
        sending it (logged; the vehicle flies as before, only dearer)."""
        for message_id in UNREAD_STREAMS:
            try:
                await self.request_interval(message_id, 0.0)
            except (VehicleCommandError, RunnerTimeoutError) as error:
                logger.info(
                    "vehicle %s: stream %d not stopped: %s", self.system_id, message_id, error
                )

    async def request_interval(self, message_id: int, rate_hz: float) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL for ``message_id`` at ``rate_hz`` on this link (0: stop
        the stream, as MAVLink's interval -1)."""
        await self._command_long(
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
            f"interval of {message_id}",
            message_id,
            1e6 / rate_hz if rate_hz > 0 else -1,
        )

    async def _command_long(self, command: int, what: str, *params: float) -> None:
        """COMMAND_LONG ``command`` with ``params`` (the rest 0) through the raw-message plugin,
        which re-sends it until its final COMMAND_ACK; anything but ACCEPTED is a
        VehicleCommandError naming ``what``, the result and the autopilot's reason."""
        fields: dict[str, float] = {f"param{i}": 0.0 for i in range(1, 8)}
        fields.update({f"param{i}": float(value) for i, value in enumerate(params, start=1)})
        request = MavlinkMessage(
            message_name="COMMAND_LONG",
            system_id=OWN_SYSTEM_ID,
            component_id=OWN_COMPONENT_ID,
            target_system_id=self.system_id,
            target_component_id=1,
            fields_json=json.dumps(
                {
                    "target_system": self.system_id,
                    "target_component": 1,
                    "command": command,
                    "confirmation": 0,
                    **fields,
                }
            ),
        )
        asked_s = time.monotonic()
        try:
            ack = await self._within(self.raw.send_command(request), what)
            result = int(json.loads(ack.fields_json)["result"])
        except MavsdkError as error:
            raise VehicleCommandError(f"vehicle {self.system_id}: {what}: {error}") from error
        except (ValueError, KeyError, TypeError) as error:
            raise VehicleCommandError(
                f"vehicle {self.system_id}: {what}: unreadable COMMAND_ACK ({error!r})"
            ) from error
        if result != mavlink.MAV_RESULT_ACCEPTED:
            reason = (await self.reason_since(asked_s) or "").strip()
            raise VehicleCommandError(
                f"vehicle {self.system_id}: {what} refused "
                f"({mavlink.result_name(result)})" + (f": {reason}" if reason else "")
            )

    async def odometry_updated(self) -> None:
        """Wait for the next odometry sample (at once if one came in since the track was last
        read)."""
        waiter = asyncio.get_running_loop().create_future()
        self._odometry_waiters.add(waiter)
        try:
            if not self.track.fed:  # checked after joining the waiters: no sample slips between
                await waiter
        finally:
            self._odometry_waiters.discard(waiter)

    async def _within(self, awaitable: Awaitable[_T], what: str) -> _T:
        try:
            async with asyncio.timeout(self._timeout_s):
                return await awaitable
        except TimeoutError:
            raise RunnerTimeoutError(f"vehicle {self.system_id}: {what}", self._timeout_s) from None

    async def _first(
        self,
        stream: AsyncGenerator[_T, None],
        predicate: Callable[[_T], object],
        what: str,
        timeout_s: float | None = None,
    ) -> _T:
        timeout_s = timeout_s or self._timeout_s
        async with contextlib.aclosing(stream):
            try:
                async with asyncio.timeout(timeout_s):
                    async for item in stream:
                        if predicate(item):
                            return item
            except TimeoutError:
                raise RunnerTimeoutError(f"vehicle {self.system_id}: {what}", timeout_s) from None
        raise VehicleConnectionError(f"vehicle {self.system_id}: telemetry ended ({what})")

    async def take_off(self, altitude_m: float, *, timeout_s: float = 60.0) -> None:
        """Wait for health, arm, take off towards ``altitude_m`` above home and return once the
        vehicle is clearly airborne (above ``min(altitude_m, TAKEOFF_CLEAR_M)``). The final
        altitude is reached in OFFBOARD (the controller's altitude hold): PX4 may apply its
        take-off altitude parameter after the take-off command, or keep its own. A refusal raises
        :class:`VehicleCommandError` with the autopilot's own reason (its STATUSTEXT)."""
        await self._first(
            self.telemetry.subscribe_health_all_ok(), bool, "health (is it armable?)", timeout_s
        )
        await self._commanded(self.action.set_takeoff_altitude(altitude_m), "takeoff altitude")
        await self._arm()
        await self._commanded(self.action.takeoff(), "takeoff")
        clear_m = min(altitude_m - 0.3, TAKEOFF_CLEAR_M)
        await self._first(
            self.telemetry.subscribe_position(),
            lambda p: p.relative_altitude_m > clear_m,
            f"climb above {clear_m:g} m",
            timeout_s,
        )

    async def _arm(self) -> None:
        """Arm. PX4 refuses while a preflight check settles (EKF2 seconds after boot or after a
        parameter change, even once MAVSDK reported it healthy): a refusal is asked again every
        ARM_RETRY_INTERVAL_S for ARM_RETRY_S, and the last one raised with PX4's reason."""
        give_up_s = time.monotonic() + ARM_RETRY_S  # a timeout: this process's own clock
        warned = False
        while True:
            try:
                await self._commanded(self.action.arm(), "arm")
                return
            except VehicleCommandError as refusal:
                if time.monotonic() + ARM_RETRY_INTERVAL_S > give_up_s:
                    raise
                if not warned:
                    logger.warning("%s; asking again for up to %g s", refusal, ARM_RETRY_S)
                    warned = True
            await asyncio.sleep(ARM_RETRY_INTERVAL_S)

    async def wait_altitude(
        self, altitude_m: float, *, tolerance_m: float = 0.3, timeout_s: float = 30.0
    ) -> None:
        """Wait until the odometry's height is within ``tolerance_m`` of ``altitude_m`` (while a
        controller's altitude hold drives it there)."""

        def reached() -> bool:
            sample = self.track.latest
            return sample is not None and abs(-sample.down_m - altitude_m) <= tolerance_m

        try:
            async with asyncio.timeout(timeout_s):
                while not reached():
                    await self.odometry_updated()
        except TimeoutError:
            raise RunnerTimeoutError(
                f"vehicle {self.system_id}: climb to {altitude_m:g} m", timeout_s
            ) from None

    async def _commanded(self, awaitable: Awaitable[_T], what: str) -> _T:
        """Run a MAVSDK command; a refusal becomes a VehicleCommandError naming the command, the
        result and the autopilot's reason."""
        asked_s = time.monotonic()
        try:
            return await self._within(awaitable, what)
        except MavsdkError as error:
            result = getattr(getattr(error, "result", None), "name", None) or str(error)
            reason = (await self.reason_since(asked_s) or "").strip()
            raise VehicleCommandError(
                f"vehicle {self.system_id}: {what} refused ({result})"
                + (f": {reason}" if reason else "")
            ) from error

    async def start_offboard(self) -> None:
        """Enter OFFBOARD with a zero-velocity setpoint (PX4 needs one streaming first). Over a
        lossy link that setpoint can be lost and PX4 refuses ("no setpoints": 1 of 4 vehicles
        across a Wi-Fi link with 2 % loss aborted a mission so): asked again with a fresh one,
        up to OFFBOARD_ATTEMPTS times."""
        if self.released is not None:
            raise VehicleCommandError(
                f"vehicle {self.system_id}: no longer driven ({self.released}); the runner "
                "never takes a vehicle back"
            )
        self._seen_in_control, self._control_lost = False, None
        for attempt in range(1, OFFBOARD_ATTEMPTS + 1):
            await self.set_velocity_ned(0.0, 0.0, 0.0)
            armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
            try:
                await self._command_long(
                    mavlink.MAV_CMD_DO_SET_MODE,
                    "offboard start",
                    mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | armed,
                    PX4_MAIN_MODE_OFFBOARD,
                )
                break
            except VehicleCommandError as refusal:
                if attempt == OFFBOARD_ATTEMPTS:
                    raise
                logger.warning("%s; asking again with a fresh setpoint", refusal)
            await asyncio.sleep(OFFBOARD_RETRY_INTERVAL_S)  # the pace of asking, not a wait
        self.in_offboard = True
        self._check_control()

    async def apply_params(self, params: Mapping[str, float | int]) -> dict[str, float | int]:
        """Set autopilot parameters (``{name: value}``) and read each back. The parameter's type
        (INT32 or REAL32) is the autopilot's, so ``5`` sets a float parameter to 5.0. Returns
        ``{name: value read back}``; a parameter the autopilot refuses or does not have raises
        :class:`VehicleCommandError`, one it changes (rounds, clamps) is logged as a warning."""
        applied: dict[str, float | int] = {}
        for name, value in params.items():
            try:
                await self._within(self.param.get_param_float(name), f"parameter {name}")
                setter, getter = self.param.set_param_float, self.param.get_param_float
                wanted = float(value)
            except ParamError as error:
                if error.result is not ParamResult.WRONG_TYPE:
                    raise VehicleCommandError(
                        f"vehicle {self.system_id}: parameter {name}: {error.result.name}"
                    ) from error
                if float(value) != int(value):
                    raise VehicleCommandError(
                        f"vehicle {self.system_id}: parameter {name} is an integer, got {value}"
                    ) from error
                setter, getter = self.param.set_param_int, self.param.get_param_int
                wanted = int(value)
            await self._commanded(setter(name, wanted), f"parameter {name} = {wanted}")
            back = await self._commanded(getter(name), f"parameter {name} read-back")
            if not math.isclose(back, wanted, rel_tol=1e-6, abs_tol=1e-6):
                logger.warning(
                    "vehicle %s: parameter %s set to %s, reads back %s",
                    self.system_id,
                    name,
                    wanted,
                    back,
                )
            applied[name] = back
        return applied

    async def set_velocity_ned(
        self, north_m_s: float, east_m_s: float, down_m_s: float, yaw_deg: float = 0.0
    ) -> None:
        """Send one velocity setpoint now, in metres per mission second (scaled to the
        autopilot's clock, :attr:`velocity_scale`); none once :attr:`released`. Sent from this
        thread and nothing re-sends it: the controller's steps are the stream."""
        if self.released is not None:
            self.setpoints_withheld += 1
            return
        scale = self.velocity_scale
        velocity = (float(north_m_s) * scale, float(east_m_s) * scale, float(down_m_s) * scale)
        if not all(map(math.isfinite, (*velocity, yaw_deg))):
            raise ValueError(f"vehicle {self.system_id}: setpoint {velocity}, {yaw_deg} not finite")
        fields = json.dumps(
            {
                # This companion computer's own boot clock, as MAVLink's time_boot_ms means.
                "time_boot_ms": int(time.monotonic() * 1000) & 0xFFFFFFFF,
                "target_system": self.system_id,
                "target_component": 1,
                "coordinate_frame": mavlink.MAV_FRAME_LOCAL_NED,
                "type_mask": VELOCITY_YAW_MASK,
                **dict.fromkeys(("x", "y", "z", "afx", "afy", "afz", "yaw_rate"), 0.0),
                **dict(zip(("vx", "vy", "vz"), velocity, strict=True)),
                "yaw": math.radians(yaw_deg),
            }
        )
        setpoint = MavlinkMessage(
            "SET_POSITION_TARGET_LOCAL_NED",
            OWN_SYSTEM_ID,
            OWN_COMPONENT_ID,
            self.system_id,
            1,
            fields,
        )
        try:
            self.raw._plugin.send_message(setpoint)
        except MavsdkError as error:
            raise VehicleConnectionError(
                f"vehicle {self.system_id}: setpoint not sent: {error}"
            ) from error
        self._streamed = True

    def _withhold(self, why: str) -> None:
        """From now on no setpoint of the runner's goes out (for good)."""
        if self.released is None:
            self.released = why
            logger.info("vehicle %s: no longer driven: %s", self.system_id, why)

    def release(self, why: str) -> None:
        """Stop driving this vehicle, at once and for good: no setpoint of the runner's goes out
        from here on. Who then gets which command (in a task of this link):

        - a vehicle seen armed in a mode other than OFFBOARD (a pilot's, another ground
          station's, a failsafe's) gets none: HOLD would take it from whoever flies it;
        - a disarmed one gets HOLD: inert while disarmed, and a pilot's re-arm arms into HOLD
          rather than into the OFFBOARD PX4 keeps through a disarm, whoever disarmed it;
        - one the runner still flies (lost, or its mission over: :meth:`finish`) gets HOLD
          too: the runner's own choice for its own vehicle, before its offboard-loss failsafe.

        A vehicle that never had a setpoint of the runner's gets none.
        """
        if self.released is not None:
            return
        self._withhold(why)
        ours = self._control_lost is None
        if self._group is None or not self._streamed:
            return  # never entered, or never driven
        if not ours and self.armed is True and self.flight_mode != "OFFBOARD":
            return
        try:
            # Not one of the streams cancelled at the end: the group waits for it.
            self._ending = self._group.create_task(
                self._hold_after_release(), name=f"vehicle-{self.system_id}-hold"
            )
        except RuntimeError:  # the link is closing: the offboard-loss failsafe takes over
            logger.info("vehicle %s: link closing; no HOLD after its release", self.system_id)

    async def stream_ended(self) -> None:
        """Wait until the command :meth:`release` gives is answered (bounded by the command
        timeout); the setpoints themselves stopped with the release."""
        if self._ending is not None:
            await asyncio.shield(self._ending)

    async def _hold_after_release(self) -> None:
        try:
            await self._within(self.action.hold(), "hold")
        except (MavsdkError, RunnerTimeoutError) as error:
            logger.info("vehicle %s: HOLD after its release: %s", self.system_id, error)

    def _disarm_words(self, disarm: Disarm | None = None) -> str:
        """``disarmed in the air at 6.0 m (it said: ...)`` for ``disarm`` (default: the last)."""
        disarm = disarm or (self.disarms[-1] if self.disarms else None)
        if disarm is None:
            return "disarmed"
        reason = self._disarm_reason(disarm.seen_s)
        said = f" (it said: {reason})" if reason else ""
        if disarm.in_air:
            return f"disarmed in the air at {disarm.height_m:.1f} m{said}"
        return f"disarmed on the ground{said}"

    def ending(self) -> str:
        """What the runner saw of this vehicle last, in words: how it was disarmed (landed, or
        in the air at what height and what the vehicle said about it) and whether it was armed
        again, else its armed state and mode."""
        parts = [self._disarm_words(disarm) for disarm in self.disarms]
        text = "; armed again, then ".join(parts)
        if self.armed:
            mode = self.flight_mode or "an unknown mode"
            text += f"; armed again, in {mode} at the end" if parts else f"armed in {mode}"
        return text or "never seen armed or disarmed"

    def _disarm_reason(self, seen_s: float) -> str | None:
        """The vehicle's STATUSTEXT about a disarm seen at monotonic ``seen_s`` (sent with the
        disarm, so up to a heartbeat period before the heartbeat that shows it)."""
        for at_s, _severity, text in self.status_texts:
            if seen_s - 2.0 <= at_s <= seen_s + 1.0 and "disarm" in text.lower():
                return text.strip()
        return None

    async def finish(self, action: str = "land", *, timeout_s: float = 60.0) -> None:
        """Stop driving the vehicle (:meth:`release`: its setpoint stream ends, for good), then
        land (waiting for the disarm), return (RTL) or hold."""
        self._withhold(f"the runner ends its flight ({action})")
        self.in_offboard = False  # from here on a mode change is the runner's own
        await self.stream_ended()  # a HOLD of release()'s is answered before the next command
        if action == "land":
            await self._commanded(self.action.land(), "land")
            await self._first(
                self.telemetry.subscribe_armed(),
                lambda armed: not armed,
                "land and disarm",
                timeout_s,
            )
        elif action == "return":
            await self._commanded(self.action.return_to_launch(), "return")
        else:
            await self._commanded(self.action.hold(), "hold")
