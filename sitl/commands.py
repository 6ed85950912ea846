"""The MAVLink command protocol of one vehicle: COMMAND_LONG / COMMAND_INT in, COMMAND_ACK out.

Which part answers which ``MAV_CMD`` is data: each part of the autopilot publishes a
:data:`CommandTable` of its handlers next to its class, as each PX4 module answers the vehicle
commands it owns. :class:`CommandDispatcher` joins the tables, runs the handler a command names
and acknowledges every copy it receives; commands nobody handles are acknowledged UNSUPPORTED.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TypeVar

from pymavlink.dialects.v20 import common as mavlink

from sitl.vehicle_state import Link, VehicleContext

Owner = TypeVar("Owner")

#: A handler answers a command with a MAV_RESULT.
CommandHandler = Callable[["Command", Link], int]
#: MAV_CMD -> handler (an unbound method of the part that owns the command).
CommandTable = Mapping[int, Callable[[Owner, "Command", Link], int]]

# COMMAND_INT x/y: INT32_MAX means "not given" (MAVLink spec; pymavlink has no constant for it).
_INT32_MAX = 2**31 - 1

#: Commands PX4 also answers when they are sent to every system (target_system 0).
_BROADCAST_COMMANDS = frozenset(
    [mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION]
)


@dataclass(slots=True)
class Command:
    """COMMAND_LONG and COMMAND_INT in one shape (x/y stay integers for COMMAND_INT)."""

    command: int
    params: tuple[float, float, float, float, float, float, float]
    frame: int | None  # None for COMMAND_LONG
    x_int: int = 0
    y_int: int = 0
    source: tuple[int, int] = (0, 0)  # sender's system and component id

    def latitude_longitude(self) -> tuple[float, float] | None:
        """(latitude, longitude) in degrees of params 5/6: COMMAND_INT's x/y in degE7,
        COMMAND_LONG's floats; None when not given (INT32_MAX or NaN, as the spec says)."""
        if self.frame is None:
            lat, lon = self.params[4], self.params[5]
            return (lat, lon) if math.isfinite(lat) and math.isfinite(lon) else None
        if _INT32_MAX in (self.x_int, self.y_int):
            return None
        return self.x_int * 1e-7, self.y_int * 1e-7


def bind(owner: Owner, table: CommandTable[Owner]) -> dict[int, CommandHandler]:
    """``table``'s handlers bound to ``owner``."""

    def bound(handler: Callable[[Owner, Command, Link], int]) -> CommandHandler:
        return lambda cmd, link: handler(owner, cmd, link)

    return {command: bound(handler) for command, handler in table.items()}


class CommandDispatcher:
    """Runs the handler of each command addressed to ``vehicle`` and sends the COMMAND_ACK.

    ``tables`` are bound tables (see :func:`bind`); a command in two of them is a wiring error.
    """

    def __init__(self, vehicle: VehicleContext, tables: Iterable[Mapping[int, CommandHandler]]):
        self._vehicle = vehicle
        self._handlers: dict[int, CommandHandler] = {}
        for table in tables:
            for command, handler in table.items():
                if command in self._handlers:
                    raise ValueError(f"MAV_CMD {command} has two handlers")
                self._handlers[command] = handler
        self._after_ack: Callable[[], None] | None = None

    def on_command_long(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        vehicle = self._vehicle
        broadcast_ok = msg.command in _BROADCAST_COMMANDS
        if not (
            vehicle.is_for_me(msg) or (broadcast_ok and msg.target_system in (0, vehicle.sysid))
        ):
            return
        cmd = Command(
            msg.command,
            (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7),
            None,
            source=(msg.get_srcSystem(), msg.get_srcComponent()),
        )
        self._run(cmd, msg, link)

    def on_command_int(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        if not self._vehicle.is_for_me(msg):
            return
        cmd = Command(
            msg.command,
            (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z),
            msg.frame,
            msg.x,
            msg.y,
            source=(msg.get_srcSystem(), msg.get_srcComponent()),
        )
        self._run(cmd, msg, link)

    def then(self, action: Callable[[], None]) -> None:
        """Run ``action`` right after the COMMAND_ACK is sent (e.g. the requested message)."""
        self._after_ack = action

    def _run(self, cmd: Command, msg: mavlink.MAVLink_message, link: Link) -> None:
        handler = self._handlers.get(cmd.command)
        result = mavlink.MAV_RESULT_UNSUPPORTED if handler is None else handler(cmd, link)
        # Every copy of a command gets an answer: MAVSDK may miss a very fast first one.
        ack = mavlink.MAVLink_command_ack_message(
            cmd.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        link.send(ack)
        follow_up = self._after_ack
        if follow_up is not None:
            self._after_ack = None
            follow_up()
