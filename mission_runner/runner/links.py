"""Vehicles through MAVSDK (``mavsdk`` 4.x, ``mavsdk.asyncio``): the same code for the bundled
emulator and for real PX4 over UDP or serial.

One :class:`Mavsdk` object serves every vehicle of a process (:func:`connected_vehicles`). Each
:class:`MavsdkVehicle` streams its own odometry - LOCAL_POSITION_NED through MAVSDK's raw-message
plugin, because the step alignment needs the autopilot's timestamp (``time_boot_ms``), which
MAVSDK's telemetry plugin drops - and sends velocity setpoints in OFFBOARD.

Failsafe: the controller only ever *streams* setpoints. If it dies, MAVSDK stops sending and PX4's
offboard-loss failsafe (COM_OF_LOSS_T, then COM_OBL_RC_ACT) holds or lands the vehicle; if the link
drops, PX4's data-link-loss failsafe does. :meth:`MavsdkVehicle.finish` leaves offboard and lands or
holds on a normal end.
"""

import asyncio
import contextlib
import json
import logging

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

from .errors import RunnerTimeoutError, VehicleCommandError, VehicleConnectionError
from .odometry import OdometrySample, OdometryTrack

logger = logging.getLogger(__name__)

ODOMETRY_RATE_HZ = 50.0
_mavsdk_logging_routed = False


def route_mavsdk_logs():
    """Send MAVSDK's own log lines to the ``mavsdk`` Python logger instead of stdout."""
    global _mavsdk_logging_routed  # noqa: PLW0603 - MAVSDK's log hook is process-wide
    if _mavsdk_logging_routed:
        return
    from mavsdk.logging import LogLevel, log_subscribe  # noqa: PLC0415

    mavsdk_logger = logging.getLogger("mavsdk")
    levels = {
        LogLevel.DEBUG: logging.DEBUG,
        LogLevel.INFO: logging.DEBUG,
        LogLevel.WARN: logging.WARNING,
        LogLevel.ERROR: logging.ERROR,
    }

    def forward(level, message, _file, _line):
        mavsdk_logger.log(levels.get(level, logging.INFO), "%s", message)
        return True

    log_subscribe(forward)
    _mavsdk_logging_routed = True


@contextlib.asynccontextmanager
async def connected_vehicles(urls, system_ids, *, timeout_s=20.0):
    """One Mavsdk with a connection per URL, until every system id in ``system_ids`` is found.

    Yields ``{system_id: mavsdk System}``. URLs are MAVSDK's: ``udpin://0.0.0.0:14540``,
    ``serial:///dev/ttyACM0:57600``.
    """
    route_mavsdk_logs()
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        for url in urls:
            await mavsdk.add_any_connection(url)
        wanted = set(system_ids)
        found = {}
        try:
            async with asyncio.timeout(timeout_s):
                async for _ in _discovery_ticks(mavsdk):
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


async def _discovery_ticks(mavsdk):
    """Yield at once, then whenever MAVSDK reports a new system (and at least every 0.2 s)."""
    yield
    stream = mavsdk.on_new_system()
    async with contextlib.aclosing(stream):
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.2):
                    await anext(stream)
            yield


class MavsdkVehicle:
    """One PX4 vehicle. An async context manager that owns its odometry task.

    sample_time_s(time_boot_ms) maps the autopilot's boot time to the mission clock (identity in
    seconds for the in-process emulator, whose boot time is the simulated time).
    """

    def __init__(self, system, system_id, *, sample_time_s, command_timeout_s=10.0):
        self.system = system
        self.system_id = system_id
        self.action = ActionAsync(system)
        self.telemetry = TelemetryAsync(system)
        self.offboard = OffboardAsync(system)
        self.raw = MavlinkDirectAsync(system)
        self.odometry = OdometryTrack()
        self._sample_time_s = sample_time_s
        self._timeout_s = command_timeout_s
        self._updated = asyncio.Event()
        self._group = None
        self._odometry_task = None
        self.in_offboard = False

    async def __aenter__(self):
        self._group = asyncio.TaskGroup()
        await self._group.__aenter__()
        self._odometry_task = self._group.create_task(
            self._stream_odometry(), name=f"vehicle-{self.system_id}-odometry"
        )
        with contextlib.suppress(Exception):  # a vehicle may refuse rate changes; use its rate
            await self._within(
                self.telemetry.set_rate_position_velocity_ned(ODOMETRY_RATE_HZ), "odometry rate"
            )
        return self

    async def __aexit__(self, *exc_info):
        self._odometry_task.cancel()
        await self._group.__aexit__(*exc_info)

    async def _stream_odometry(self):
        stream = self.raw.subscribe_message("LOCAL_POSITION_NED")
        async with contextlib.aclosing(stream):
            async for message in stream:
                if message.system_id != self.system_id:
                    continue
                fields = json.loads(message.fields_json)
                sample = OdometrySample(
                    self._sample_time_s(fields["time_boot_ms"]),
                    fields["x"],
                    fields["y"],
                    fields["z"],
                )
                if self.odometry.add(sample):
                    self._updated.set()

    async def boot_to_unix_offset_s(self, *, timeout_s=10.0):
        """UNIX time minus autopilot boot time, from SYSTEM_TIME (requested at 1 Hz): maps
        LOCAL_POSITION_NED's ``time_boot_ms`` onto UNIX time for controllers on UNIX time."""
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkMessage  # noqa: PLC0415

        stream = self.raw.subscribe_message("SYSTEM_TIME")
        request = MavlinkMessage(
            message_name="COMMAND_LONG",
            system_id=245,
            component_id=190,
            target_system_id=self.system_id,
            target_component_id=1,
            fields_json=json.dumps(
                {
                    "target_system": self.system_id,
                    "target_component": 1,
                    "command": 511,  # MAV_CMD_SET_MESSAGE_INTERVAL
                    "confirmation": 0,
                    "param1": 2,  # SYSTEM_TIME
                    "param2": 1e6,
                    "param3": 0,
                    "param4": 0,
                    "param5": 0,
                    "param6": 0,
                    "param7": 0,
                }
            ),
        )
        with contextlib.suppress(Exception):  # some autopilots stream it anyway
            await self._within(self.raw.send_command(request), "SYSTEM_TIME interval")
        message = await self._first(
            stream,
            lambda m: m.system_id == self.system_id and json.loads(m.fields_json)["time_unix_usec"],
            "SYSTEM_TIME (is the autopilot's clock set?)",
            timeout_s,
        )
        fields = json.loads(message.fields_json)
        return fields["time_unix_usec"] / 1e6 - fields["time_boot_ms"] / 1000.0

    def use_time_offset(self, offset_s):
        """From now on, odometry samples are stamped ``time_boot_ms / 1000 + offset_s``."""
        self._sample_time_s = lambda ms: ms / 1000.0 + offset_s

    async def odometry_updated(self):
        """Wait for the next odometry sample."""
        self._updated.clear()
        await self._updated.wait()

    async def _within(self, awaitable, what):
        try:
            async with asyncio.timeout(self._timeout_s):
                return await awaitable
        except TimeoutError:
            raise RunnerTimeoutError(f"vehicle {self.system_id}: {what}", self._timeout_s) from None

    async def _first(self, stream, predicate, what, timeout_s=None):
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

    async def take_off(self, altitude_m, *, timeout_s=60.0):
        """Wait for health, arm, take off and climb to ``altitude_m`` above home."""
        await self._first(
            self.telemetry.subscribe_health_all_ok(), bool, "health (is it armable?)", timeout_s
        )
        try:
            await self._within(self.action.set_takeoff_altitude(altitude_m), "takeoff altitude")
            await self._within(self.action.arm(), "arm")
            await self._within(self.action.takeoff(), "takeoff")
        except Exception as error:
            if isinstance(error, RunnerTimeoutError):
                raise
            raise VehicleCommandError(f"vehicle {self.system_id}: {error}") from error
        await self._first(
            self.telemetry.subscribe_position(),
            lambda p: p.relative_altitude_m > altitude_m - 0.3,
            f"climb to {altitude_m:g} m",
            timeout_s,
        )

    async def start_offboard(self):
        """Enter OFFBOARD with a zero-velocity setpoint (PX4 needs one streaming first)."""
        await self.set_velocity_ned(0.0, 0.0, 0.0)
        try:
            await self._within(self.offboard.start(), "offboard start")
        except Exception as error:
            if isinstance(error, RunnerTimeoutError):
                raise
            raise VehicleCommandError(f"vehicle {self.system_id}: offboard: {error}") from error
        self.in_offboard = True

    async def set_velocity_ned(self, north_m_s, east_m_s, down_m_s, yaw_deg=0.0):
        setpoint = VelocityNedYaw(
            float(north_m_s), float(east_m_s), float(down_m_s), float(yaw_deg)
        )
        await self._within(self.offboard.set_velocity_ned(setpoint), "velocity setpoint")

    async def finish(self, action="land", *, timeout_s=60.0):
        """Leave OFFBOARD and land (waiting for the disarm) or hold."""
        if self.in_offboard:
            with contextlib.suppress(Exception):
                await self._within(self.offboard.stop(), "offboard stop")
            self.in_offboard = False
        if action == "land":
            await self._within(self.action.land(), "land")
            await self._first(
                self.telemetry.subscribe_armed(),
                lambda armed: not armed,
                "land and disarm",
                timeout_s,
            )
        else:
            await self._within(self.action.hold(), "hold")
