"""PX4 flight modes as they appear on MAVLink (HEARTBEAT.custom_mode, DO_SET_MODE).

custom_mode = main_mode << 16 | sub_mode << 24 (PX4 ``px4_custom_mode.h``).
"""

from __future__ import annotations

import enum


class MainMode(enum.IntEnum):
    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7


class AutoSubMode(enum.IntEnum):
    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6
    FOLLOW_TARGET = 8


class PosctlSubMode(enum.IntEnum):
    POSCTL = 0
    ORBIT = 1


class FlightMode(enum.Enum):
    """The PX4 modes the emulator flies, with their (main, sub) pair."""

    MANUAL = (MainMode.MANUAL, 0)
    STABILIZED = (MainMode.STABILIZED, 0)
    ALTCTL = (MainMode.ALTCTL, 0)
    POSCTL = (MainMode.POSCTL, PosctlSubMode.POSCTL)
    ORBIT = (MainMode.POSCTL, PosctlSubMode.ORBIT)
    OFFBOARD = (MainMode.OFFBOARD, 0)
    TAKEOFF = (MainMode.AUTO, AutoSubMode.TAKEOFF)
    HOLD = (MainMode.AUTO, AutoSubMode.LOITER)
    MISSION = (MainMode.AUTO, AutoSubMode.MISSION)
    RTL = (MainMode.AUTO, AutoSubMode.RTL)
    LAND = (MainMode.AUTO, AutoSubMode.LAND)
    FOLLOW_TARGET = (MainMode.AUTO, AutoSubMode.FOLLOW_TARGET)

    @property
    def display_name(self) -> str:
        """The name PX4's commander uses in its texts (``mode_util::nav_state_names``)."""
        return _DISPLAY_NAMES[self]

    @property
    def stick_controlled(self) -> bool:
        """Flown by the pilot's sticks: PX4 needs manual control input to enter it."""
        return self in _STICK_MODES

    @property
    def custom_mode(self) -> int:
        main, sub = self.value
        return (int(main) << 16) | (int(sub) << 24)

    @classmethod
    def from_main_sub(cls, main: int, sub: int) -> FlightMode | None:
        """The mode DO_SET_MODE(main, sub) asks for, or None if PX4 has no such mode here.

        AUTO without a sub mode, or AUTO READY, means HOLD in PX4. PX4's commander ignores the
        sub mode of the other main modes: POSCTL with sub mode ORBIT is plain POSCTL (orbiting
        takes MAV_CMD_DO_ORBIT).
        """
        if main == MainMode.AUTO and sub in (0, AutoSubMode.READY):
            return cls.HOLD
        if main != MainMode.AUTO:
            sub = 0
        for mode in cls:
            if mode.value == (main, sub):
                return mode
        return None

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> FlightMode | None:
        return cls.from_main_sub((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)


_DISPLAY_NAMES = {
    FlightMode.MANUAL: "Manual",
    FlightMode.STABILIZED: "Stabilized",
    FlightMode.ALTCTL: "Altitude",
    FlightMode.POSCTL: "Position",
    FlightMode.ORBIT: "Orbit",
    FlightMode.OFFBOARD: "Offboard",
    FlightMode.TAKEOFF: "Takeoff",
    FlightMode.HOLD: "Hold",
    FlightMode.MISSION: "Mission",
    FlightMode.RTL: "Return",
    FlightMode.LAND: "Land",
    FlightMode.FOLLOW_TARGET: "Follow Target",
}
_STICK_MODES = frozenset(
    [FlightMode.MANUAL, FlightMode.STABILIZED, FlightMode.ALTCTL, FlightMode.POSCTL]
)

#: HEARTBEAT.base_mode bits.
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_STABILIZE_ENABLED = 16
MAV_MODE_FLAG_GUIDED_ENABLED = 8
MAV_MODE_FLAG_AUTO_ENABLED = 4
MAV_MODE_FLAG_MANUAL_INPUT_ENABLED = 64
MAV_MODE_FLAG_SAFETY_ARMED = 128


def base_mode(mode: FlightMode, armed: bool) -> int:
    """HEARTBEAT.base_mode PX4 sends for ``mode`` (flags as set by PX4's commander).

    ORBIT and FOLLOW_TARGET are neither manual nor auto in PX4's control-mode flags (sticks
    may adjust them): they carry the stabilize flag alone.
    """
    flags = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED
    if mode in (
        FlightMode.TAKEOFF,
        FlightMode.HOLD,
        FlightMode.MISSION,
        FlightMode.RTL,
        FlightMode.LAND,
        FlightMode.OFFBOARD,
    ):
        flags |= MAV_MODE_FLAG_AUTO_ENABLED | MAV_MODE_FLAG_GUIDED_ENABLED
    elif mode.stick_controlled:
        flags |= MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    if armed:
        flags |= MAV_MODE_FLAG_SAFETY_ARMED
    return flags
