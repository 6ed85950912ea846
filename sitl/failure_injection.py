"""PX4's failure injection for one vehicle: SYS_FAILURE_EN and MAV_CMD_INJECT_FAILURE.

A client (MAVSDK's failure plugin, QGroundControl) sends MAV_CMD_INJECT_FAILURE with a failure
unit (param 1), a failure type (param 2) and an instance (param 3, 0 = all). PX4 answers DENIED
while SYS_FAILURE_EN is 0 (no STATUSTEXT), else the module that owns the unit answers. The
emulator maps the units onto its own faults, the same ones its Python API and configuration
inject (:meth:`sitl.emulator.Emulator.inject_failure`):

================  ======================  ==================================================
unit              types                   effect
================  ======================  ==================================================
gps               ok, off                 GPS receiver off: no fix, GLOBAL_POSITION_INT stops
optical_flow      ok, off                 flow odometry off: LOCAL_POSITION_NED stops
motor             ok, off                 motors stop: the vehicle falls (still talking)
motor             stuck, wrong            accepted, no effect (PX4: ESC telemetry only)
battery           ok, off                 battery reads empty: low-battery failsafe
rc_signal         ok, off                 MANUAL_CONTROL ignored: manual-control loss
mavlink_signal    ok, off                 every MAVLink link of the vehicle goes silent
================  ======================  ==================================================

Everything else is answered UNSUPPORTED, as PX4 answers a type its handler does not know
(motor garbage). Real PX4 SITL with SIH handles only motor and battery (sensor failures need the
Gazebo simulator, and no PX4 module handles optical_flow, rc_signal or mavlink_signal): it does
not answer the others at all, so MAVSDK times out there.

PX4's ``failure`` shell command (``failure gps off``, ``failure motor off -i 1``) is there too,
in the vehicle's MAVLink shell (:mod:`sitl.shell`), with PX4's texts.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

from sitl.commands import Command, CommandTable
from sitl.manual_control import ManualControl
from sitl.vehicle_state import Link, VehicleContext

#: PX4's names of the failure units (its ``failure`` shell command: ``failure gps off``).
UNITS: dict[str, int] = {
    "gyro": mavlink.FAILURE_UNIT_SENSOR_GYRO,
    "accel": mavlink.FAILURE_UNIT_SENSOR_ACCEL,
    "mag": mavlink.FAILURE_UNIT_SENSOR_MAG,
    "baro": mavlink.FAILURE_UNIT_SENSOR_BARO,
    "gps": mavlink.FAILURE_UNIT_SENSOR_GPS,
    "optical_flow": mavlink.FAILURE_UNIT_SENSOR_OPTICAL_FLOW,
    "vio": mavlink.FAILURE_UNIT_SENSOR_VIO,
    "distance_sensor": mavlink.FAILURE_UNIT_SENSOR_DISTANCE_SENSOR,
    "airspeed": mavlink.FAILURE_UNIT_SENSOR_AIRSPEED,
    "battery": mavlink.FAILURE_UNIT_SYSTEM_BATTERY,
    "motor": mavlink.FAILURE_UNIT_SYSTEM_MOTOR,
    "servo": mavlink.FAILURE_UNIT_SYSTEM_SERVO,
    "avoidance": mavlink.FAILURE_UNIT_SYSTEM_AVOIDANCE,
    "rc_signal": mavlink.FAILURE_UNIT_SYSTEM_RC_SIGNAL,
    "mavlink_signal": mavlink.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL,
}
#: PX4's names of the failure types.
TYPES: dict[str, int] = {
    "ok": mavlink.FAILURE_TYPE_OK,
    "off": mavlink.FAILURE_TYPE_OFF,
    "stuck": mavlink.FAILURE_TYPE_STUCK,
    "garbage": mavlink.FAILURE_TYPE_GARBAGE,
    "wrong": mavlink.FAILURE_TYPE_WRONG,
    "slow": mavlink.FAILURE_TYPE_SLOW,
    "delayed": mavlink.FAILURE_TYPE_DELAYED,
    "intermittent": mavlink.FAILURE_TYPE_INTERMITTENT,
}
_ON_OFF = frozenset([mavlink.FAILURE_TYPE_OK, mavlink.FAILURE_TYPE_OFF])
#: What the emulator can inject: unit -> types.
SUPPORTED: dict[int, frozenset[int]] = {
    mavlink.FAILURE_UNIT_SENSOR_GPS: _ON_OFF,
    mavlink.FAILURE_UNIT_SENSOR_OPTICAL_FLOW: _ON_OFF,
    mavlink.FAILURE_UNIT_SYSTEM_MOTOR: _ON_OFF
    | {mavlink.FAILURE_TYPE_STUCK, mavlink.FAILURE_TYPE_WRONG},
    mavlink.FAILURE_UNIT_SYSTEM_BATTERY: _ON_OFF,
    mavlink.FAILURE_UNIT_SYSTEM_RC_SIGNAL: _ON_OFF,
    mavlink.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL: _ON_OFF,
}
_MOTORS = 8  # PX4: esc_status_s::CONNECTED_ESC_MAX
_SENSORS = {
    mavlink.FAILURE_UNIT_SENSOR_GPS: "gps",
    mavlink.FAILURE_UNIT_SENSOR_OPTICAL_FLOW: "flow",
}

#: ``set_sensor(name, ok, now_s)`` for ``"gps"`` and ``"flow"``.
SensorSwitch = Callable[[str, bool, float], None]
#: ``switch(up)``: every MAVLink link of the vehicle carries traffic (True) or nothing.
LinkSwitch = Callable[[bool], None]


def describe(unit: int, failure_type: int) -> str:
    """``"gps off"``: PX4's names for a unit and a type (numbers when it has none)."""
    unit_name = next((name for name, value in UNITS.items() if value == unit), str(unit))
    type_name = next((n for n, v in TYPES.items() if v == failure_type), str(failure_type))
    return f"{unit_name} {type_name}"


class FailureInjector:
    """The failures injected into one vehicle and MAV_CMD_INJECT_FAILURE.

    ``set_sensor`` switches the GPS or flow sensor (with its STATUSTEXT); ``on_motors`` is called
    after the motors failed or recovered (to hand the physics the new state). ``link_switch``
    is set by whoever owns the vehicle's links (the emulator); without it mavlink_signal is
    unsupported.
    """

    def __init__(
        self,
        vehicle: VehicleContext,
        *,
        set_sensor: SensorSwitch,
        manual_control: ManualControl,
        on_motors: Callable[[], None],
    ) -> None:
        self._vehicle = vehicle
        self._set_sensor = set_sensor
        self._manual = manual_control
        self._on_motors = on_motors
        self.link_switch: LinkSwitch | None = None
        self._stopped_motors = 0  # bit i: motor i + 1 off

    def supported(self, unit: int, failure_type: int, instance: int = 0) -> bool:
        if failure_type not in SUPPORTED.get(unit, ()):
            return False
        if unit == mavlink.FAILURE_UNIT_SYSTEM_MOTOR:
            return 0 <= instance <= _MOTORS
        if unit == mavlink.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL:
            return self.link_switch is not None
        if unit == mavlink.FAILURE_UNIT_SYSTEM_BATTERY:
            return instance == 0  # PX4's battery simulator: instance 0 only
        return True

    def inject(self, unit: int, failure_type: int, instance: int = 0) -> bool:
        """Apply a failure (or its end: type ok) now; False (nothing done) if unsupported."""
        if not self.supported(unit, failure_type, instance):
            return False
        vehicle = self._vehicle
        state = vehicle.state
        ok = failure_type == mavlink.FAILURE_TYPE_OK
        if unit in _SENSORS:
            self._set_sensor(_SENSORS[unit], ok, state.now_s)
        elif unit == mavlink.FAILURE_UNIT_SYSTEM_MOTOR:
            if failure_type in _ON_OFF:
                mask = (1 << _MOTORS) - 1 if instance == 0 else 1 << (instance - 1)
                if ok:
                    self._stopped_motors &= ~mask
                else:
                    self._stopped_motors |= mask
                failed = self._stopped_motors != 0
                if failed != state.motors_failed:
                    state.motors_failed = failed
                    self._on_motors()
        elif unit == mavlink.FAILURE_UNIT_SYSTEM_BATTERY:
            state.battery_failed = not ok
        elif unit == mavlink.FAILURE_UNIT_SYSTEM_RC_SIGNAL:
            self._manual.signal_blocked = not ok
        elif unit == mavlink.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL and self.link_switch is not None:
            self.link_switch(ok)
        return True

    def shell_command(self, args: list[str]) -> tuple[str, int]:
        """PX4's ``failure <unit> <type> [-i <instance>]`` (systemcmds/failure): its texts and
        exit status."""
        if int(self._vehicle.params["SYS_FAILURE_EN"]) != 1:
            return "ERROR [failure] Failure injection disabled by SYS_FAILURE_EN param.\n", 1
        if args == ["help"]:
            return _FAILURE_USAGE, 0
        instance = 0
        words = list(args)
        if "-i" in words:
            at = words.index("-i")
            value = words[at + 1] if at + 1 < len(words) else ""
            del words[at : at + 2]
            instance = int(value) if value.isdigit() else 0  # PX4: atoi
        if len(words) < 2:
            return _FAILURE_USAGE + "ERROR [failure] Not enough arguments.\n", 1
        unit, failure_type = words[0], words[1]
        if unit not in UNITS:
            return f"ERROR [failure] Component '{unit}' not found\n", 1
        if failure_type not in TYPES:
            return f"ERROR [failure] Failure type '{failure_type}' not found\n", 1
        unit_id, type_id = UNITS[unit], TYPES[failure_type]
        text = (
            f"WARN  [failure] inject failure unit: {unit} ({unit_id}), "
            f"type: {failure_type} ({type_id}), instance: {instance}\n"
        )
        if not self.inject(unit_id, type_id, instance):
            return text + f"ERROR [failure] Result: {mavlink.MAV_RESULT_UNSUPPORTED}\n", 1
        return text, 0

    def _cmd_inject_failure(self, cmd: Command, link: Link) -> int:
        if int(self._vehicle.params["SYS_FAILURE_EN"]) != 1:
            return mavlink.MAV_RESULT_DENIED
        unit, failure_type, instance = cmd.params[0], cmd.params[1], cmd.params[2]
        if not all(math.isfinite(v) for v in (unit, failure_type, instance)):
            return mavlink.MAV_RESULT_UNSUPPORTED
        # PX4 rounds the three parameters (lroundf).
        if not self.inject(round(unit), round(failure_type), round(instance)):
            return mavlink.MAV_RESULT_UNSUPPORTED
        return mavlink.MAV_RESULT_ACCEPTED


_FAILURE_USAGE = (
    "\n### Description\nInject failures into system.\n\n### Implementation\n"
    "This system command sends a vehicle command over uORB to trigger failure.\n\n"
    "### Examples\nTest the GPS failsafe by stopping GPS:\n\nfailure gps off\n\n"
    "Usage: failure [arguments...]\n\n"
    "   help          Show this help text\n\n"
    "   gps|...       Specify component\n\n"
    "   ok|off|...    Specify failure type\n"
    "     [-i <val>]  sensor instance (0=all)\n"
    "                 default: 0\n\n"
    "Components:\n" + "".join(f"- {name}\n" for name in UNITS) + "\n"
    "Failure types:\n" + "".join(f"- {name}\n" for name in TYPES)
)

#: The command PX4's failure injection answers (MAVLink receiver + the unit's module).
FAILURE_COMMANDS: CommandTable[FailureInjector] = {
    mavlink.MAV_CMD_INJECT_FAILURE: FailureInjector._cmd_inject_failure
}
