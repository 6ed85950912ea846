"""Lightweight PX4 SITL look-alike: many kinematic multicopters speaking MAVLink over UDP.

Start vehicles in-process with :class:`sitl.emulator.Emulator` (an async context manager) or from
the command line with ``sitl --vehicles N``. MAVSDK, QGroundControl and MAVProxy connect to them
as to PX4 SITL (same ports, modes, commands, parameters, mission protocol).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from sitl.errors import ClockError, EmulatorStateError, PortInUseError, SitlError, SitlTimeoutError

if TYPE_CHECKING:
    from sitl.clock import Clock
    from sitl.config import EmulatorConfig
    from sitl.emulator import Emulator, Truth, VehicleEndpoints, VehicleStatus

#: Loaded on first use: a tool that only adds the emulator's command-line options
#: (``sitl.cli``) imports this package without the emulator and its MAVLink dialect.
_LAZY = {
    "Clock": "sitl.clock",
    "EmulatorConfig": "sitl.config",
    "Emulator": "sitl.emulator",
    "Truth": "sitl.emulator",
    "VehicleEndpoints": "sitl.emulator",
    "VehicleStatus": "sitl.emulator",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'sitl' has no attribute {name!r}")


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
