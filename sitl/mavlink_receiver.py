"""The MAVLink side of one vehicle's autopilot: each incoming message to the part that owns it.

As PX4's mavlink module (MavlinkReceiver, the parameter manager), :class:`MavlinkReceiver`
takes every decoded message a link delivers and routes it by type: heartbeats and SET_MODE to
the commander (:mod:`sitl.commander`), setpoints to offboard (:mod:`sitl.offboard`), mission
protocol to the navigator's mission store (:mod:`sitl.mission`), commands to the
:class:`sitl.commands.CommandDispatcher`. It answers the protocol-level requests itself:
parameters (PARAM_REQUEST_LIST / READ / SET), PING, TIMESYNC, MAVLink FTP (:mod:`sitl.ftp`) and
the log protocol (:mod:`sitl.log_handler`), one server of each per link as on PX4, and the
commands that ask for messages (REQUEST_MESSAGE, SET/GET_MESSAGE_INTERVAL, GET_HOME_POSITION,
REQUEST_AUTOPILOT_CAPABILITIES, REQUEST_PROTOCOL_VERSION). Replies go to the link a request came
on; parameter changes to every link. Messages that do not make sense are ignored, as PX4 does.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Mapping

from pymavlink.dialects.v20 import common as mavlink

from sitl.commander import COMMANDER_COMMANDS, Commander
from sitl.commands import Command, CommandDispatcher, CommandHandler, CommandTable, bind
from sitl.flight_log import FlightLogStore
from sitl.ftp import FileSystem, FtpServer
from sitl.log_handler import LogHandler
from sitl.navigator import NAVIGATOR_COMMANDS, Navigator
from sitl.offboard import Offboard
from sitl.params import PARAM_NAMES
from sitl.shell import MavlinkShell, Pxh
from sitl.telemetry import BUILDABLE, MSG_PROTOCOL_VERSION, TelemetryBuilder
from sitl.vehicle_state import Link, VehicleContext

logger = logging.getLogger(__name__)

#: Rejected PARAM_SETs are reported (log line, STATUSTEXT) at most this often, simulated s:
#: a client flooding bad writes must not flood the log and the links too.
_REJECTION_REPORT_INTERVAL_S = 1.0


class _ThrottledReport:
    """Counts events and lets one report through per ``interval_s``, saying how many were
    held back since the last one."""

    def __init__(self, interval_s: float) -> None:
        self._interval_s = interval_s
        self._next_s = -math.inf
        self.count = 0
        self._held = 0

    def due(self, now_s: float) -> int | None:
        """Count one event; the number held back before it if it is to be reported, else None."""
        self.count += 1
        if now_s < self._next_s:
            self._held += 1
            return None
        held, self._held = self._held, 0
        self._next_s = now_s + self._interval_s
        return held


MessageHandler = Callable[[mavlink.MAVLink_message, Link], None]

_MISSION_MESSAGES = (
    "MISSION_COUNT",
    "MISSION_ITEM_INT",
    "MISSION_ITEM",
    "MISSION_REQUEST_LIST",
    "MISSION_REQUEST_INT",
    "MISSION_REQUEST",
    "MISSION_CLEAR_ALL",
    "MISSION_SET_CURRENT",
    "MISSION_ACK",
)
_READ_ONLY_PARAMS = frozenset(["MAV_SYS_ID", "MAV_COMP_ID"])  # PX4 changes them on reboot only
_MAX_MESSAGE_ID = 2**24  # MAVLink 2 message ids are 24 bits


class MavlinkReceiver:
    """Routes one vehicle's incoming messages; answers parameters, pings and message requests.

    ``boot_time_s(now_s)`` is the autopilot's boot clock (for TIMESYNC); ``telemetry`` builds
    the messages that commands ask for. ``handlers`` (message type -> handler) and
    ``command_tables`` (bound, see :func:`sitl.commands.bind`) route what the other parts of
    the autopilot own.
    """

    def __init__(
        self,
        vehicle: VehicleContext,
        *,
        commander: Commander,
        navigator: Navigator,
        offboard: Offboard,
        telemetry: TelemetryBuilder,
        boot_time_s: Callable[[float], float],
        files: FileSystem | None = None,
        ftp_echo_session: bool = False,
        flight_logs: FlightLogStore | None = None,
        handlers: Mapping[str, MessageHandler] | None = None,
        command_tables: Iterable[Mapping[int, CommandHandler]] = (),
    ) -> None:
        self._vehicle = vehicle
        self.param_rejections = _ThrottledReport(_REJECTION_REPORT_INTERVAL_S)
        self._files = files if files is not None else FileSystem()
        self._ftp: dict[Link, FtpServer] = {}
        self._ftp_echo_session = ftp_echo_session
        self._flight_logs = flight_logs if flight_logs is not None else FlightLogStore()
        self._log_handlers: dict[Link, LogHandler] = {}
        self._telemetry = telemetry
        self._boot_time_s = boot_time_s
        self._commands = CommandDispatcher(
            vehicle,
            [
                bind(commander, COMMANDER_COMMANDS),
                bind(navigator, NAVIGATOR_COMMANDS),
                bind(self, RECEIVER_COMMANDS),
                *command_tables,
            ],
        )
        self._mission = navigator.mission
        self._handlers: dict[str, MessageHandler] = {
            "HEARTBEAT": commander.on_heartbeat,
            "COMMAND_LONG": self._commands.on_command_long,
            "COMMAND_INT": self._commands.on_command_int,
            "SET_MODE": commander.on_set_mode,
            "SET_POSITION_TARGET_LOCAL_NED": offboard.on_position_target_local,
            "SET_POSITION_TARGET_GLOBAL_INT": offboard.on_position_target_global,
            "SET_ATTITUDE_TARGET": offboard.on_attitude_target,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "PING": self._on_ping,
            "TIMESYNC": self._on_timesync,
            "FILE_TRANSFER_PROTOCOL": self._on_file_transfer,
            "LOG_REQUEST_LIST": self._on_log_message,
            "LOG_REQUEST_DATA": self._on_log_message,
            "LOG_REQUEST_END": self._on_log_message,
            "LOG_ERASE": self._on_log_message,
        }
        for kind in _MISSION_MESSAGES:
            self._handlers[kind] = self._on_mission_message
        # SERIAL_CONTROL: PX4's MAVLink shell (sitl.shell); a parameter changed there is
        # announced like one set over MAVLink.
        self.shell = MavlinkShell(
            vehicle, Pxh(vehicle, lambda name: vehicle.broadcast(self._param_value(name)))
        )
        self._handlers["SERIAL_CONTROL"] = self.shell.on_serial_control
        self._handlers.update(handlers or {})

    def handle(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        """React to one decoded message received on ``link``."""
        handler = self._handlers.get(msg.get_type())
        if handler is not None:
            handler(msg, link)

    # ------------------------------------------------------------------ misc
    def _on_mission_message(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        self._mission.handle(msg, link, self._vehicle.state.now_s)

    def _on_file_transfer(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        # One server, with its own session, per link: PX4 runs one per MAVLink instance.
        server = self._ftp.get(link)
        if server is None:
            vehicle = self._vehicle
            server = FtpServer(
                self._files,
                sysid=vehicle.sysid,
                compid=vehicle.compid,
                now_s=lambda: vehicle.state.now_s,
                echo_session=self._ftp_echo_session,
            )
            self._ftp[link] = server
        server.handle(msg, link)

    def _on_log_message(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        handler = self._log_handlers.get(link)
        if handler is None:
            handler = LogHandler(self._flight_logs, sysid=self._vehicle.sysid)
            self._log_handlers[link] = handler
        handler.handle(msg, link)

    def pump(self) -> None:
        """Go on with transfers that take more than one reply (log downloads)."""
        for handler in self._log_handlers.values():
            if handler.sending:
                handler.pump()

    def _on_ping(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            link.send(
                mavlink.MAVLink_ping_message(
                    msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )

    def _on_timesync(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if msg.tc1 == 0:
            boot_ns = int(self._boot_time_s(self._vehicle.state.now_s) * 1e9)
            link.send(mavlink.MAVLink_timesync_message(boot_ns, msg.ts1))

    # ---------------------------------------------------------------- params
    def _on_param_request_list(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if not self._vehicle.is_for_me(msg):
            return
        for name in self._vehicle.params:
            link.send(self._param_value(name))

    def _on_param_request_read(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if not self._vehicle.is_for_me(msg):
            return
        names = self._vehicle.params
        if msg.param_index >= 0:
            if msg.param_index >= len(names):
                return
            name = PARAM_NAMES[msg.param_index]
        else:
            name = _param_name(msg.param_id)
            if name not in names:
                return  # PX4 stays silent about unknown names
        link.send(self._param_value(name))

    def _on_param_set(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        vehicle = self._vehicle
        if not vehicle.is_for_me(msg):
            return
        params = vehicle.params
        now = vehicle.state.now_s
        name = _param_name(msg.param_id)
        if name not in params:
            # PX4 answers PARAM_ERROR and logs "unknown param"; it sends no STATUSTEXT.
            error = mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST
            link.send(
                mavlink.MAVLink_param_error_message(
                    msg.get_srcSystem(), msg.get_srcComponent(), name.encode()[:16], -1, error
                )
            )
            self._param_rejected(now, name, "unknown parameter", text=False)
            return
        if name not in _READ_ONLY_PARAMS:  # for those: echo the value in use
            try:
                value = params.decode_wire_value(name, msg.param_value, msg.param_type)
                params.set(name, value)
            except (ValueError, OverflowError) as exc:
                self._param_rejected(now, name, str(exc), text=True)
        # PX4 announces the (possibly unchanged) value on every link.
        vehicle.broadcast(self._param_value(name))

    def _param_rejected(self, now_s: float, name: str, why: str, *, text: bool) -> None:
        """Log (and with ``text`` say in a STATUSTEXT) a refused write, throttled."""
        held = self.param_rejections.due(now_s)
        if held is None:
            return
        vehicle = self._vehicle
        more = f" (+{held} more)" if held else ""
        if text:
            vehicle.statustext(now_s, mavlink.MAV_SEVERITY_WARNING, f"Param {name} rejected{more}")
        logger.info("vehicle %d: PARAM_SET %s rejected: %s%s", vehicle.sysid, name, why, more)

    def _param_value(self, name: str) -> mavlink.MAVLink_message:
        params = self._vehicle.params
        value, mav_type = params.wire_value(name)
        return mavlink.MAVLink_param_value_message(
            name.encode(), value, mav_type, len(params), params.index_of(name)
        )

    # -------------------------------------------------------------- commands
    def _cmd_get_home_position(self, cmd: Command, link: Link) -> int:
        self._commands.then(lambda: self._send_built(mavlink.MAVLINK_MSG_ID_HOME_POSITION, link))
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, cmd: Command, link: Link) -> int:
        msg_id = cmd.params[0]
        if not math.isfinite(msg_id) or not 0 <= msg_id < _MAX_MESSAGE_ID:
            return mavlink.MAV_RESULT_DENIED
        interval = link.streams.interval_us(int(msg_id)) if int(msg_id) in BUILDABLE else 0
        self._commands.then(
            lambda: link.send(mavlink.MAVLink_message_interval_message(int(msg_id), interval))
        )
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_set_message_interval(self, cmd: Command, link: Link) -> int:
        msg_id, interval_us = cmd.params[0], cmd.params[1]
        if not (math.isfinite(msg_id) and 0 <= msg_id < _MAX_MESSAGE_ID):
            return mavlink.MAV_RESULT_DENIED
        if int(msg_id) == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return mavlink.MAV_RESULT_FAILED  # PX4 keeps its heartbeat at 1 Hz
        ok = link.streams.set_interval(int(msg_id), interval_us, self._vehicle.state.now_s)
        # PX4 answers FAILED for a message it has no stream of (e.g. RAW_IMU).
        return mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_FAILED

    def _cmd_request_message(self, cmd: Command, link: Link) -> int:
        msg_id = cmd.params[0]
        if not (math.isfinite(msg_id) and int(msg_id) in BUILDABLE):
            return mavlink.MAV_RESULT_DENIED
        msg = self._telemetry.build(int(msg_id), self._vehicle.state.now_s)
        if msg is None:
            return mavlink.MAV_RESULT_FAILED
        self._commands.then(lambda: link.send(msg))
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_request_autopilot_capabilities(self, cmd: Command, link: Link) -> int:
        self._commands.then(
            lambda: self._send_built(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, link)
        )
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_request_protocol_version(self, cmd: Command, link: Link) -> int:
        self._commands.then(lambda: self._send_built(MSG_PROTOCOL_VERSION, link))
        return mavlink.MAV_RESULT_ACCEPTED

    def _send_built(self, msg_id: int, link: Link) -> None:
        msg = self._telemetry.build(msg_id, self._vehicle.state.now_s)
        if msg is not None:
            link.send(msg)


#: The commands PX4's MAVLink module answers itself: requests for messages.
RECEIVER_COMMANDS: CommandTable[MavlinkReceiver] = {
    mavlink.MAV_CMD_GET_HOME_POSITION: MavlinkReceiver._cmd_get_home_position,
    mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: MavlinkReceiver._cmd_get_message_interval,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: MavlinkReceiver._cmd_set_message_interval,
    mavlink.MAV_CMD_REQUEST_MESSAGE: MavlinkReceiver._cmd_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: (
        MavlinkReceiver._cmd_request_autopilot_capabilities
    ),
    mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION: MavlinkReceiver._cmd_request_protocol_version,
}


def _param_name(param_id: str | bytes) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", errors="replace")
    return param_id.split("\x00", 1)[0]
