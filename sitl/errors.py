"""Errors raised by the vehicle emulator (package ``sitl``).

Exception tree::

    SitlError
    ├── PortInUseError        a UDP port the emulator must bind is taken (names the port and
    │                         the setting that moves it)
    ├── SitlTimeoutError      something the emulator waited for did not happen in time (names
    │                         what, and how long it waited); also a builtin ``TimeoutError``
    ├── ClockError            the shared clock was used against its rules (unknown participant,
    │                         time released backwards, advancing past the allowed time)
    └── EmulatorStateError    an emulator method was called in the wrong lifecycle state (e.g.
                              before ``async with`` entered) or with an unknown vehicle index

Malformed MAVLink traffic is never an error: the emulator drops it and counts it, like PX4.
Configuration problems are pydantic ``ValidationError`` s raised by :mod:`sitl.config`.
"""

from __future__ import annotations


class SitlError(Exception):
    """Base class of every error this package raises on purpose."""


class PortInUseError(SitlError):
    """A UDP port the emulator needs is already bound by another program.

    ``port`` is the port number, ``setting`` the configuration field (or command line option)
    that moves it, ``vehicle_index`` the vehicle whose link needed it.
    """

    def __init__(self, port: int, setting: str, vehicle_index: int, reason: str = "") -> None:
        self.port = port
        self.setting = setting
        self.vehicle_index = vehicle_index
        detail = f" ({reason})" if reason else ""
        super().__init__(
            f"UDP port {port} for vehicle {vehicle_index} is already in use{detail}; "
            f"another emulator or a PX4 SITL may be running. Choose another base with {setting}."
        )


class SitlTimeoutError(SitlError, TimeoutError):
    """Waiting for ``what`` took longer than ``timeout_s`` seconds."""

    def __init__(self, what: str, timeout_s: float) -> None:
        self.what = what
        self.timeout_s = timeout_s
        super().__init__(f"timed out after {timeout_s:g} s waiting for {what}")


class ClockError(SitlError):
    """The shared clock was used against its rules."""


class EmulatorStateError(SitlError):
    """An emulator method was called in a state where it cannot work."""
