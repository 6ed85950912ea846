"""PX4's MAVLink shell (SERIAL_CONTROL, device SERIAL_CONTROL_DEV_SHELL) with a few commands.

PX4 (``mavlink_shell.cpp``, ``MavlinkReceiver::handle_message_serial_control`` and, on POSIX, the
remote ``pxh`` of ``px4_daemon/pxh.cpp``) opens a shell per MAVLink link when a SERIAL_CONTROL
for the shell device arrives, echoes what it is sent, runs each line when a newline comes,
prints the prompt ``pxh> `` and sends what the shell prints back in SERIAL_CONTROL messages
(flag REPLY, up to 70 bytes each, addressed to whoever wrote last). A SERIAL_CONTROL without the
RESPOND flag closes the shell (its data is still read). Clients: QGroundControl's MAVLink
console, MAVSDK's ``shell`` plugin, PX4's ``Tools/mavlink_shell.py``.

:class:`Pxh` runs command lines against one vehicle and prints what PX4 prints (formats taken
from PX4's ``param``, ``commander`` and ``ver`` commands and from real PX4 SITL):

- ``param show [-a | -c | -q <name>] [<filter>]``, ``param set <name> <value> [fail]``
  (a change is announced with PARAM_VALUE, as PX4 announces changed parameters);
- ``commander status``;
- ``ver all`` (and ``hw``, ``git``, ``bdate``, ``uri``, ``gcc``, ``px4guid``, ``mcu``);
- ``help``; anything else is an ``Invalid command``. The other subcommands of ``param`` and
  ``commander`` say that the emulator does not have them and fail.

:class:`MavlinkShell` is the SERIAL_CONTROL side, one session per link.
"""

from __future__ import annotations

import logging
import math
import platform
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime

from pymavlink.dialects.v20 import common as mavlink

from sitl.modes import FlightMode
from sitl.params import PARAM_TABLE
from sitl.telemetry import FLIGHT_SW_VERSION
from sitl.vehicle_state import Link, VehicleContext

logger = logging.getLogger(__name__)

PROMPT = "pxh> "
DATA_BYTES = 70
"""SERIAL_CONTROL.data holds 70 bytes."""
_TARGET_OFFSET = 79
"""Payload offset of SERIAL_CONTROL's extension fields target_system, target_component."""
_READ_ONLY_PARAMS = frozenset(["MAV_SYS_ID", "MAV_COMP_ID"])  # as for PARAM_SET: reboot only
#: Subcommands PX4 has that the emulator does not run (``param``, ``commander``).
_PARAM_ELSEWHERE = frozenset(
    [
        *("load", "import", "save", "select", "select-backup", "show-for-airframe", "status"),
        *("set-default", "compare", "greater", "touch", "reset", "reset_all", "index"),
        *("index_used", "find"),
    ]
)
_COMMANDER_ELSEWHERE = frozenset(
    [
        *("start", "calibrate", "check", "safety", "arm", "disarm", "takeoff", "land"),
        *("transition", "mode", "pair", "termination", "set_ekf_origin", "lat", "lon", "alt"),
        *("set_heading", "poweroff", "stop"),
    ]
)
_PARAM_USAGE = """
### Description
Command to access and manipulate parameters via shell or script.

Usage: param <command> [arguments...]
 Commands:

   show          Show parameter values
     [-a]        Show all parameters (not just used)
     [-c]        Show only changed params (unused too)
     [-q]        quiet mode, print only param value (name needs to be exact)
     [<filter> ] Filter by param name (wildcard at end allowed, eg. sys_*)

   set           Set parameter to a value
     <param_name> <value> Parameter name and value to set
     [fail     ] If provided, let the command fail if param is not found
"""
_COMMANDER_USAGE = """
### Description
The commander module contains the state machine for mode switching and failsafe behavior.

Usage: commander <command> [arguments...]
 Commands:

   status        print status info
"""
_VER_USAGE = """Tool to print various version information

Usage: ver <command> [arguments...]
 Commands:

   hw            Hardware architecture

   mcu           MCU info

   git           git version information

   bdate         Build date and time

   gcc           Compiler info

   px4guid       PX4 GUID

   uri           Build URI

   all           Print all versions
"""
_INT_PREFIX = re.compile(r"\s*([+-]?\d+)")
_FLOAT_PREFIX = re.compile(
    r"\s*([+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|inf(?:inity)?|nan))", re.IGNORECASE
)


def _strtol(text: str) -> int:
    """C's ``strtol(text, &end, 10)``: the leading integer, 0 if there is none."""
    match = _INT_PREFIX.match(text)
    return int(match.group(1)) if match else 0


def _strtod_float32(text: str) -> float:
    """C's ``strtod`` stored in a float32, as ``param set`` does: the leading number or 0."""
    match = _FLOAT_PREFIX.match(text)
    value = float(match.group(1)) if match else 0.0
    try:
        return float(struct.unpack("<f", struct.pack("<f", value))[0])
    except OverflowError:
        return math.copysign(math.inf, value)


def _version_text(number: int) -> str:
    """``Release 1.15.0 (17760511)`` or ``1.15.0 c0 (...)``, as ``ver`` prints a version."""
    major, minor, patch = (number >> 24) & 0xFF, (number >> 16) & 0xFF, (number >> 8) & 0xFF
    kind = number & 0xFF
    if kind == 255:
        return f"Release {major}.{minor}.{patch} ({number})"
    return f"{major}.{minor}.{patch} {kind:x} ({number})"


def _os_version_number() -> int:
    """The host kernel's release as PX4 encodes it (major.minor.patch, type release)."""
    parts = [int(p) for p in re.findall(r"\d+", platform.release())[:3]]
    major, minor, patch = [*parts, 0, 0, 0][:3]
    return ((major & 0xFF) << 24) | ((minor & 0xFF) << 16) | ((patch & 0xFF) << 8) | 255


@dataclass
class Pxh:
    """PX4's shell for one vehicle: :meth:`run` takes a command line, returns what PX4 prints.

    ``announce_param(name)`` is called after ``param set`` changed a parameter. ``commands``
    adds commands that other parts of the autopilot own (name -> handler(args) returning the
    text and the exit status), such as ``failure``.
    """

    vehicle: VehicleContext
    announce_param: Callable[[str], None] = lambda name: None
    started: datetime = field(default_factory=lambda: datetime.now(UTC))
    commands: dict[str, Callable[[list[str]], tuple[str, int]]] = field(default_factory=dict)

    def run(self, line: str) -> str:
        words = line.split()
        if not words or words[0].startswith("#"):
            return ""
        command, args = words[0], words[1:]
        own = {"param": self._param, "commander": self._commander, "ver": self._ver}
        handler = {**own, **self.commands}.get(command)
        if handler is not None:
            text, status = handler(args)
            if status:
                text += f"Command '{command}' failed, returned {status}.\n"
            return text
        if command == "help":
            return "Builtin Commands:\n" + "".join(
                f"  {name}\n" for name in sorted(("commander", "param", "ver", *self.commands))
            )
        return f"Invalid command: {command}\ntype 'help' for a list of commands\n"

    # ----------------------------------------------------------------- param
    def _param(self, args: list[str]) -> tuple[str, int]:
        sub = args[0] if args else ""
        if sub == "show":
            return self._param_show(args[1:])
        if sub == "set":
            return self._param_set(args[1:])
        if sub in _PARAM_ELSEWHERE:
            return f"ERROR [param] 'param {sub}' is not emulated\n", 1
        return _PARAM_USAGE, 1

    def _param_line(self, name: str) -> str:
        params = self.vehicle.params
        spec = PARAM_TABLE[name]
        changed = "+" if params[name] != spec.default else " "
        index = params.index_of(name)
        return f"x {changed} {name} [{index},{index}] : {self._value_text(name)}\n"

    def _value_text(self, name: str) -> str:
        value = self.vehicle.params[name]
        if PARAM_TABLE[name].type == "INT32":
            return str(int(value))
        return f"{value:4.4f}"

    def _param_show(self, args: list[str]) -> tuple[str, int]:
        params = self.vehicle.params
        header = "Symbols: x = used, + = saved, * = unsaved\n"
        count = len(params)
        if args[:1] == ["-q"]:
            if len(args) < 2 or args[1] not in params:
                return "", 1
            return self._value_text(args[1]) + "\n", 0
        if args[:1] == ["-a"]:
            lines = "".join(self._param_line(name) for name in params)
            return f"{header}{lines}\n {count} parameters total, {count} used.\n", 0
        only_changed = args[:1] == ["-c"]
        if only_changed:
            args = args[1:]
        pattern = args[0] if args else None
        if pattern is not None and "*" in pattern[:-1]:
            return f"{header}WARN  [param] * symbol only allowed at end of search string\n", 0
        lines = "".join(
            self._param_line(name)
            for name in params
            if (pattern is None or _matches(pattern, name))
            and not (only_changed and params[name] == PARAM_TABLE[name].default)
        )
        return f"{header}{lines}\n {count}/{count} parameters used.\n", 0

    def _param_set(self, args: list[str]) -> tuple[str, int]:
        if len(args) < 2:
            name = args[0] if args else "MIS_TAKEOFF_ALT"
            return (
                f"ERROR [param] not enough arguments.\nTry 'param set {name} 3 [fail]'\n",
                1,
            )
        name, text = args[0], args[1]
        fail = args[2:3] == ["fail"]
        params = self.vehicle.params
        if name not in params:
            return f"ERROR [param] Parameter {name} not found.\n", 1 if fail else 0
        if name in _READ_ONLY_PARAMS:
            return f"ERROR [param] {name} is read-only in the emulator\n", 1
        spec = PARAM_TABLE[name]
        new = float(_strtol(text)) if spec.type == "INT32" else _strtod_float32(text)
        current = params[name]
        if new == current:
            return "", 0
        before = self._value_text(name)
        changed = "+" if current != spec.default else " "
        try:
            params.set(name, new)
        except (ValueError, OverflowError) as exc:
            return f"ERROR [param] {exc}\n", 1
        self.announce_param(name)
        return f"{changed} {name}: curr: {before} -> new: {self._value_text(name)}\n", 0

    # ------------------------------------------------------------- commander
    def _commander(self, args: list[str]) -> tuple[str, int]:
        sub = args[0] if args else ""
        if sub == "status":
            state = self.vehicle.state
            mode = _nav_state_name(state.mode)
            lines = [
                "Armed" if state.armed else "Disarmed",
                "prearm safety: Off",  # SITL has no safety switch
                f"navigation mode: {mode}",
                f"user intended navigation mode: {mode}",
                f"in failsafe: {'yes' if state.failsafe_active else 'no'}",
            ]
            return "".join(f"INFO  [commander] {text}\n" for text in lines), 0
        if sub in _COMMANDER_ELSEWHERE:
            return f"ERROR [commander] 'commander {sub}' is not emulated; use MAVLink\n", 1
        unknown = "INFO  [commander] unknown command\n" if sub else ""
        return unknown + _COMMANDER_USAGE, 1

    # ------------------------------------------------------------------- ver
    def _ver(self, args: list[str]) -> tuple[str, int]:
        if not args:
            return "Error, not enough parameters.\n" + _VER_USAGE, 1
        what = args[0]
        started = self.started
        sysid = self.vehicle.sysid
        # (subcommand, lines) in the order "ver all" prints them; None: only "all" prints it.
        sections: list[tuple[str | None, list[str]]] = [
            ("hw", ["HW arch: PX4_SITL"]),
            (
                "git",
                [
                    "PX4 git-hash: " + "0" * 40,
                    f"PX4 version: {_version_text(FLIGHT_SW_VERSION)}",
                    f"OS: {platform.system()}",
                    f"OS version: {_version_text(_os_version_number())}",
                ],
            ),
            ("bdate", [f"Build datetime: {started:%b} {started.day:2d} {started:%Y %H:%M:%S}"]),
            ("uri", ["Build uri: localhost"]),
            (None, ["Build variant: default"]),
            (
                "gcc",
                [f"Toolchain: {platform.python_implementation()}, {platform.python_version()}"],
            ),
            ("px4guid", ["PX4GUID: 1006" + (b"SITL" + sysid.to_bytes(12, "big")).hex()]),
            ("mcu", ["UNKNOWN MCU"]),
        ]
        lines = [line for key, text in sections if what in ("all", key) for line in text]
        if not lines:
            return "ERROR [ver] unknown command\n", 1
        return "".join(f"{line}\n" for line in lines), 0


def _matches(pattern: str, name: str) -> bool:
    """PX4's ``param show`` filter: case-insensitive, one ``*`` allowed at the end."""
    pattern = pattern.upper()
    if pattern.endswith("*"):
        return name.startswith(pattern[:-1])
    return name == pattern


def _nav_state_name(mode: FlightMode) -> str:
    return mode.display_name  # PX4's nav_state_names (src/lib/modes/ui.hpp)


class SerialControl(mavlink.MAVLink_serial_control_message):
    """SERIAL_CONTROL with MAVLink's extension fields target_system and target_component, which
    pymavlink's common dialect does not define: PX4 addresses its shell output to the system
    and component that wrote last, and MAVSDK addresses its commands to the autopilot."""

    def __init__(
        self,
        data: bytes,
        flags: int,
        target_system: int,
        target_component: int,
        device: int = mavlink.SERIAL_CONTROL_DEV_SHELL,
    ) -> None:
        super().__init__(device, flags, 0, 0, len(data), list(data.ljust(DATA_BYTES, b"\0")))
        self.target_system = target_system
        self.target_component = target_component

    def pack(self, mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(
            self.baudrate, self.timeout, self.device, self.flags, self.count, *self.data
        )
        if not force_mavlink1:  # extensions travel in MAVLink 2 only
            payload += bytes([self.target_system, self.target_component])
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


def targets(msg: mavlink.MAVLink_message) -> tuple[int, int]:
    """SERIAL_CONTROL's target_system/target_component (0 when the sender left them out)."""
    buf = msg.get_msgbuf()
    if buf[0] != mavlink.PROTOCOL_MARKER_V2:
        return 0, 0
    payload = bytes(buf[10 : 10 + buf[1]]).ljust(_TARGET_OFFSET + 2, b"\0")
    return payload[_TARGET_OFFSET], payload[_TARGET_OFFSET + 1]


@dataclass
class _Session:
    """One open shell: the line typed so far (bytes, echoed as they come)."""

    line: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes, pxh: Pxh) -> bytes:
        """What the shell prints for ``data``: the echo, each completed line's output and a
        prompt after it (PX4's remote pxh drops control bytes up to 3)."""
        out = bytearray()
        for byte in data:
            if byte == 0x0A:
                out += b"\n"
                text = pxh.run(self.line.decode("latin-1"))
                out += text.encode("latin-1", errors="replace") + PROMPT.encode()
                self.line.clear()
            elif byte > 3:
                out.append(byte)
                self.line.append(byte)
        return bytes(out)


class MavlinkShell:
    """The SERIAL_CONTROL shell of one vehicle: a session per link, as PX4 has one per MAVLink
    instance. ``pxh`` runs the command lines."""

    def __init__(self, vehicle: VehicleContext, pxh: Pxh) -> None:
        self._vehicle = vehicle
        self._pxh = pxh
        self._sessions: dict[str, _Session] = {}

    @property
    def pxh(self) -> Pxh:
        """The shell's command interpreter (to add commands to)."""
        return self._pxh

    @property
    def open_sessions(self) -> list[str]:
        """Names of the links with an open shell."""
        return list(self._sessions)

    def on_serial_control(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        vehicle = self._vehicle
        target_system, target_component = targets(msg)
        if (target_system not in (0, vehicle.sysid)) or (
            target_component not in (0, vehicle.compid)
        ):
            return
        if msg.device != mavlink.SERIAL_CONTROL_DEV_SHELL or (
            msg.flags & mavlink.SERIAL_CONTROL_FLAG_REPLY
        ):
            return
        session = self._sessions.setdefault(link.name, _Session())
        out = b""
        if 0 < msg.count <= DATA_BYTES:
            out = session.feed(bytes(msg.data[: msg.count]), self._pxh)
        if not msg.flags & mavlink.SERIAL_CONTROL_FLAG_RESPOND:
            # PX4 closes the shell; what it printed has nowhere to go.
            del self._sessions[link.name]
            return
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        for start in range(0, len(out), DATA_BYTES):
            chunk = out[start : start + DATA_BYTES]
            link.send(SerialControl(chunk, mavlink.SERIAL_CONTROL_FLAG_REPLY, *source))
