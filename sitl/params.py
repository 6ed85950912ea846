"""PX4 parameters the emulated vehicles know, and the parameter store each vehicle keeps.

The table holds the PX4 names that clients ask for (MAVSDK's action plugin, QGroundControl's
start-up, mission runners) and the ones that drive the emulator's behaviour: speed and
acceleration limits (MPC_*), take-off / RTL altitudes, failsafe timeouts and actions. Defaults
follow PX4 v1.14/v1.15 multicopter defaults, except where the emulator has no RC and PX4 SITL
would refuse to fly without changing them (COM_RC_IN_MODE).

INT32 parameters travel in PARAM_VALUE's float field byte-wise, as PX4 does (capability
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): the four bytes of the int32 are read as a float32.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Literal

ParamType = Literal["INT32", "REAL32"]

#: MAV_PARAM_TYPE values used on the wire.
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One PX4 parameter: name, type, default and allowed range (inclusive)."""

    name: str
    type: ParamType
    default: float
    minimum: float
    maximum: float
    description: str

    @property
    def mav_type(self) -> int:
        return MAV_PARAM_TYPE_INT32 if self.type == "INT32" else MAV_PARAM_TYPE_REAL32

    def check(self, value: float) -> float:
        """Return ``value`` converted to this parameter's type, or raise ``ValueError``."""
        if not math.isfinite(value):
            raise ValueError(f"{self.name} must be finite, got {value!r}")
        if self.type == "INT32":
            if value != int(value):
                raise ValueError(f"{self.name} is an integer parameter, got {value!r}")
            value = int(value)
        if not self.minimum <= value <= self.maximum:
            raise ValueError(
                f"{self.name} must be within [{self.minimum:g}, {self.maximum:g}], got {value!r}"
            )
        return value


def _p(  # noqa: PLR0917 - table rows read best positionally
    name: str, type_: ParamType, default: float, lo: float, hi: float, description: str
) -> ParamSpec:
    return ParamSpec(name, type_, default, lo, hi, description)


# Sorted by name so that PARAM_REQUEST_LIST indices are stable.
PARAM_TABLE: Mapping[str, ParamSpec] = {
    spec.name: spec
    for spec in sorted(
        [
            _p("BAT1_N_CELLS", "INT32", 4, 1, 16, "Number of battery cells (telemetry only)"),
            _p("COM_ARM_WO_GPS", "INT32", 1, 0, 1, "Allow arming without GPS"),
            _p(
                "COM_DISARM_LAND",
                "REAL32",
                2.0,
                -1.0,
                20.0,
                "Seconds on the ground after landing before auto-disarm; negative disables",
            ),
            _p(
                "COM_DISARM_PRFLT",
                "REAL32",
                10.0,
                -1.0,
                20.0,
                "Seconds armed on the ground without taking off before auto-disarm; "
                "negative disables",
            ),
            _p(
                "COM_DL_LOSS_T",
                "INT32",
                10,
                5,
                300,
                "Seconds without a GCS/API heartbeat before the data link counts as lost",
            ),
            _p(
                "COM_OBL_RC_ACT",
                "INT32",
                0,
                0,
                7,
                "Offboard loss action: 0-2,5 hold (no RC here), 3 return, 4 land, 6-7 disarm",
            ),
            _p(
                "COM_OF_LOSS_T",
                "REAL32",
                1.0,
                0.0,
                60.0,
                "Seconds without offboard setpoints before offboard counts as lost",
            ),
            _p("COM_RC_IN_MODE", "INT32", 4, 0, 4, "RC input mode (4: stick input disabled)"),
            _p("MAV_COMP_ID", "INT32", 1, 1, 250, "Autopilot component id"),
            _p("MAV_SYS_ID", "INT32", 1, 1, 255, "System id (set per vehicle, read only here)"),
            _p(
                "MIS_TAKEOFF_ALT",
                "REAL32",
                2.5,
                0.0,
                80.0,
                "Take-off altitude above home in metres (takeoff command and mission start)",
            ),
            _p("MPC_ACC_DOWN_MAX", "REAL32", 3.0, 2.0, 15.0, "Maximum downward accel, m/s^2"),
            _p(
                "MPC_ACC_HOR",
                "REAL32",
                3.0,
                2.0,
                15.0,
                "Horizontal acceleration limit in m/s^2 (offboard and auto modes)",
            ),
            _p("MPC_ACC_UP_MAX", "REAL32", 4.0, 2.0, 15.0, "Maximum upward accel, m/s^2"),
            _p("MPC_LAND_SPEED", "REAL32", 0.7, 0.6, 4.0, "Landing descent speed, m/s"),
            _p("MPC_TKO_SPEED", "REAL32", 1.5, 1.0, 5.0, "Take-off climb speed, m/s"),
            _p(
                "MPC_XY_CRUISE",
                "REAL32",
                5.0,
                3.0,
                20.0,
                "Horizontal speed in auto modes (goto, mission, return), m/s",
            ),
            _p(
                "MPC_XY_VEL_MAX",
                "REAL32",
                12.0,
                0.0,
                20.0,
                "Horizontal speed limit in every mode, m/s",
            ),
            _p("MPC_YAWRAUTO_MAX", "REAL32", 45.0, 5.0, 360.0, "Yaw rate limit, deg/s"),
            _p("MPC_Z_VEL_MAX_DN", "REAL32", 1.5, 0.5, 4.0, "Descent speed limit, m/s"),
            _p("MPC_Z_VEL_MAX_UP", "REAL32", 3.0, 0.5, 8.0, "Climb speed limit, m/s"),
            _p(
                "NAV_ACC_RAD",
                "REAL32",
                10.0,
                0.05,
                200.0,
                "Mission waypoint acceptance radius when the item gives none, m",
            ),
            _p(
                "NAV_DLL_ACT",
                "INT32",
                0,
                0,
                6,
                "Data link loss action: 0 off, 1 hold, 2 return, 3 land, 5-6 disarm",
            ),
            _p("NAV_MC_ALT_RAD", "REAL32", 0.8, 0.05, 200.0, "Waypoint altitude acceptance, m"),
            _p("NAV_RCL_ACT", "INT32", 2, 0, 6, "RC loss action (no RC here; reported only)"),
            _p(
                "RTL_DESCEND_ALT",
                "REAL32",
                30.0,
                2.0,
                500.0,
                "Return: altitude above home to descend to before landing, m",
            ),
            _p(
                "RTL_LAND_DELAY",
                "REAL32",
                0.0,
                -1.0,
                300.0,
                "Return: seconds to hover above home before landing; negative hovers forever",
            ),
            _p(
                "RTL_RETURN_ALT",
                "REAL32",
                60.0,
                0.0,
                150.0,
                "Return: minimum altitude above home while flying back, m",
            ),
            _p("SYS_AUTOSTART", "INT32", 10040, 0, 9999999, "Airframe (10040: SIH quadrotor)"),
        ],
        key=lambda spec: spec.name,
    )
}

PARAM_NAMES: tuple[str, ...] = tuple(PARAM_TABLE)


def int32_to_wire_float(value: int) -> float:
    """Encode an int32 byte-wise into a float32, as PX4 does in PARAM_VALUE/PARAM_SET."""
    return struct.unpack("<f", struct.pack("<i", int(value)))[0]


def wire_float_to_int32(value: float) -> int:
    """Decode a byte-wise encoded int32 from the float field of PARAM_SET/PARAM_VALUE."""
    return struct.unpack("<i", struct.pack("<f", value))[0]


def validate_overrides(overrides: Mapping[str, float]) -> dict[str, float]:
    """Check parameter overrides from a configuration; raise ``ValueError`` naming the problem."""
    checked: dict[str, float] = {}
    for name, value in overrides.items():
        spec = PARAM_TABLE.get(name)
        if spec is None:
            raise ValueError(f"unknown parameter {name!r}; known: {', '.join(PARAM_NAMES)}")
        checked[name] = spec.check(float(value))
    return checked


class ParamStore:
    """The parameter values of one vehicle.

    ``on_change(name, value)`` is called after every successful :meth:`set`, so the vehicle can
    update limits that live elsewhere (e.g. physics arrays).
    """

    def __init__(
        self,
        overrides: Mapping[str, float] | None = None,
        on_change: Callable[[str, float], None] | None = None,
    ) -> None:
        self._values: dict[str, float] = {name: spec.default for name, spec in PARAM_TABLE.items()}
        self._values.update(validate_overrides(overrides or {}))
        self._on_change = on_change

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __contains__(self, name: object) -> bool:
        return name in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(PARAM_NAMES)

    def __len__(self) -> int:
        return len(PARAM_NAMES)

    def set(self, name: str, value: float) -> float:
        """Set a parameter (``ValueError`` if unknown or out of range); returns the stored value."""
        spec = PARAM_TABLE.get(name)
        if spec is None:
            raise ValueError(f"unknown parameter {name!r}")
        stored = spec.check(value)
        self._values[name] = stored
        if self._on_change is not None:
            self._on_change(name, stored)
        return stored

    def set_silently(self, name: str, value: float) -> None:
        """Set a read-only-to-clients value (e.g. MAV_SYS_ID) without notification."""
        self._values[name] = PARAM_TABLE[name].check(value)

    def index_of(self, name: str) -> int:
        return PARAM_NAMES.index(name)

    def wire_value(self, name: str) -> tuple[float, int]:
        """``(param_value, param_type)`` as they go into PARAM_VALUE."""
        spec = PARAM_TABLE[name]
        value = self._values[name]
        if spec.type == "INT32":
            return int32_to_wire_float(int(value)), MAV_PARAM_TYPE_INT32
        return float(value), MAV_PARAM_TYPE_REAL32

    def decode_wire_value(self, name: str, param_value: float, param_type: int) -> float:
        """Interpret PARAM_SET's float for ``name``: byte-wise for INT32 parameters."""
        spec = PARAM_TABLE[name]
        if spec.type == "INT32":
            if param_type == MAV_PARAM_TYPE_REAL32:
                # A client that sends an INT32 as a plain float (not byte-wise) still means it.
                return float(param_value)
            return float(wire_float_to_int32(param_value))
        return float(param_value)
