"""Lightweight PX4 SITL look-alike: many kinematic multicopters speaking MAVLink over UDP.

Start vehicles in-process with :class:`sitl.emulator.Emulator` (an async context manager) or from
the command line with ``sitl --vehicles N``. MAVSDK, QGroundControl and MAVProxy connect to them
as to PX4 SITL (same ports, modes, commands, parameters, mission protocol).
"""

from sitl.clock import Clock
from sitl.config import EmulatorConfig
from sitl.emulator import Emulator, Truth, VehicleEndpoints, VehicleStatus
from sitl.errors import ClockError, EmulatorStateError, PortInUseError, SitlError, SitlTimeoutError

__all__ = [
    "Clock",
    "ClockError",
    "Emulator",
    "EmulatorConfig",
    "EmulatorStateError",
    "PortInUseError",
    "SitlError",
    "SitlTimeoutError",
    "Truth",
    "VehicleEndpoints",
    "VehicleStatus",
]
