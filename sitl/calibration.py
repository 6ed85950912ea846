"""Sensor calibration of one vehicle, answered and narrated the way PX4 SITL (SIH) does it.

PX4's commander runs a calibration in a worker thread and reports progress with STATUSTEXTs
starting "[cal]", which QGroundControl and MAVSDK's calibration plugin parse. A SITL vehicle
sits still on its skids, so a calibration that needs the vehicle turned over cannot finish. What
the real PX4 SITL binary does, measured, is replayed here on simulated time:

=================================  ========  ================================================
MAV_CMD_PREFLIGHT_CALIBRATION      answer    then
=================================  ========  ================================================
p1 = 1 gyro                        ACCEPTED  progress 0..100 %, done after 1.06 s
p5 = 2 level horizon               ACCEPTED  progress 0..100 %, done after 0.6 s
p5 = 1 accelerometer               ACCEPTED  measures the down side, asks for the others,
                                             fails after 26.4 s: "timeout: no motion"
p2 = 1 magnetometer                ACCEPTED  "Rotate vehicle", fails after 45 s
p3 = 1 barometer                   ACCEPTED  done after 3 s (PX4 SIH: its worker never returns)
p6 = 1 or 2 airspeed               ACCEPTED  no airspeed sensor: fails after 35 s
p5 = 4 quick accelerometer         ACCEPTED  nothing said
p4 = 1 RC / p4 = 2 RC trim         ACCEPTED  "Calibration: Disabling RC input" / "trim cal done"
p7 = 1 ESC                         DENIED    "[cal] calibration failed: Disconnect battery ..."
p1, p5 or p7 = 3 temperature       -         PX4 SITL does not answer; here UNSUPPORTED
all 0                              ACCEPTED  cancels a running calibration ("[cal] calibration
                                             cancelled" 0.1 s later), ends an RC calibration
anything else                      UNSUPPORTED
=================================  ========  ================================================

While armed or while a calibration runs a new one is TEMPORARILY_REJECTED; a running
calibration answers other PREFLIGHT_CALIBRATION commands DENIED with "command denied during
calibration: 241" (PX4 sends a second acknowledgement, TEMPORARILY_REJECTED, from its commander:
clients act on the first). MAV_CMD_FIXED_MAG_CAL_YAW (quick magnetometer calibration from a
known heading) is accepted and finishes at once. During a calibration the heartbeat says
MAV_STATE_CALIBRATING and arming is denied ("Arming denied: calibrating").
"""

from __future__ import annotations

import math
from collections import deque

from pymavlink.dialects.v20 import common as mavlink

from sitl.commands import Command, CommandTable
from sitl.vehicle_state import Link, VehicleContext

_INFO = mavlink.MAV_SEVERITY_INFO
_CRITICAL = mavlink.MAV_SEVERITY_CRITICAL
_TEMPERATURE = 3  # vehicle_command_s::PREFLIGHT_CALIBRATION_TEMPERATURE_CALIBRATION
_CANCEL_NOTICED_S = 0.1

#: (seconds after the start, severity, text) of one calibration's STATUSTEXTs.
Script = list[tuple[float, int, str]]


def _started(sensor: str) -> tuple[float, int, str]:
    return 0.0, _INFO, f"[cal] calibration started: 2 {sensor}"


def _progress(sensor: str, step_pct: int, period_s: float, done_s: float) -> Script:
    """Steady progress to 100 %, then done (gyro, level)."""
    script = [_started(sensor), (0.05, _INFO, "[cal] progress <0>")]
    for k, pct in enumerate(range(step_pct, 101, step_pct)):
        script.append((0.1 + k * period_s, _INFO, f"[cal] progress <{pct}>"))
    script.append((done_s, _INFO, f"[cal] calibration done: {sensor}"))
    return script


def _accelerometer() -> Script:
    script = [
        _started("accel"),
        (0.05, _INFO, "[cal] pending: back front left right up down"),
        (0.1, _INFO, "[cal] hold vehicle still on a pending side"),
        (2.5, _INFO, "[cal] detected rest position, hold still..."),
        (3.8, _INFO, "[cal] down orientation detected"),
        (3.9, _INFO, "[cal] Hold still, measuring down side"),
        (6.9, _INFO, "[cal] down side result: [0.000 0.000 -9.807]"),
        (6.95, _INFO, "[cal] progress <17>"),
        (7.0, _INFO, "[cal] down side done, rotate to a different side"),
    ]
    # Asked for another side, the vehicle stays on the one it did: PX4 repeats the request
    # every 3.8 s until 20 s pass without motion.
    start = 7.2
    while start + 3.8 < 26.4:
        script += [
            (start, _INFO, "[cal] pending: back front left right up"),
            (start + 0.05, _INFO, "[cal] hold vehicle still on a pending side"),
            (start + 2.45, _INFO, "[cal] detected rest position, hold still..."),
            (start + 3.75, _INFO, "[cal] down side already completed"),
        ]
        start += 3.8
    script += [
        (26.4, _CRITICAL, "[cal] calibration failed: timeout: no motion"),
        (26.45, _CRITICAL, "[cal] calibration failed: accel"),
    ]
    return script


# A text "" only keeps the worker busy until then (PX4 says nothing on MAVLink).
_SCRIPTS: dict[str, Script] = {
    "gyro": _progress("gyro", 10, 0.1, 1.06),
    "level": _progress("level", 20, 0.1, 0.6),
    "accel": _accelerometer(),
    "mag": [
        _started("mag"),
        (0.05, _INFO, "[cal] pending: back front left right up down"),
        (0.1, _INFO, "[cal] hold vehicle still on a pending side"),
        (1.9, _INFO, "[cal] detected rest position, hold still..."),
        (2.4, _INFO, "[cal] down orientation detected"),
        (2.5, _INFO, "[cal] Rotate vehicle"),
        (37.9, _CRITICAL, "Failed: This calibration requires rotation."),
        (38.0, _INFO, "[cal] down side calibration: progress <1>"),
        (39.4, _INFO, "[cal] down side calibration: progress <2>"),
        (42.8, _INFO, "[cal] down side calibration: progress <3>"),
        (45.0, _CRITICAL, "[cal] calibration failed: mag"),
    ],
    "baro": [_started("baro"), (3.0, _INFO, "[cal] calibration done: baro")],
    "airspeed": [
        _started("airspeed"),
        (0.05, _CRITICAL, "[cal] Ensure sensor is not measuring wind"),
        (35.0, _CRITICAL, "[cal] calibration failed: airspeed"),
    ],
    "accel_quick": [(0.1, _INFO, "")],
    "rc_trim": [(0.4, _INFO, "trim cal done\t")],
}


def _is(value: float, wanted: int) -> bool:
    """PX4's ``(int)param == wanted`` (NaN matches nothing)."""
    return math.isfinite(value) and int(value) == wanted


class Calibration:
    """The calibration worker of one vehicle (PX4's commander worker thread)."""

    def __init__(self, vehicle: VehicleContext) -> None:
        self._vehicle = vehicle
        self._texts: deque[tuple[float, int, str]] = deque()
        self.running: str | None = None
        """The calibration under way ("gyro", "accel", ...), None when idle."""
        # The ones whose PX4 routine checks for a cancel command while it runs.
        self._cancellable = frozenset(["gyro", "accel", "mag", "airspeed"])
        self.rc_calibration = False

    def update(self, now_s: float) -> None:
        """Say what is due by ``now_s``; the worker is idle after its last text."""
        vehicle = self._vehicle
        texts = self._texts
        if not texts and self.running is None:
            return  # idle: the usual case, once per autopilot step
        while texts and texts[0][0] <= now_s + 1e-9:
            _, severity, text = texts.popleft()
            if text:
                vehicle.statustext(now_s, severity, text)
        if not texts:
            self.running = None
        self._publish()

    def _publish(self) -> None:
        self._vehicle.state.calibrating = self.running is not None or self.rc_calibration

    def _start(self, name: str) -> int:
        now = self._vehicle.state.now_s
        self.running = name
        self._texts = deque((now + offset, level, text) for offset, level, text in _SCRIPTS[name])
        self.update(now)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cancelled(self) -> bool:
        """A cancel is acknowledged and about to be announced."""
        texts = self._texts
        return len(texts) == 1 and texts[0][2] == "[cal] calibration cancelled"

    def _cancel_check(self, cmd: Command) -> int:
        """PX4's calibrate_cancel_check: all-zero parameters cancel, anything else is denied."""
        vehicle = self._vehicle
        now = vehicle.state.now_s
        if all(v == 0.0 for v in cmd.params[:6]):
            # PX4's routine notices the cancel at its next poll and says so after the
            # acknowledgement. The order matters to MAVSDK: its cancel() holds the lock its
            # STATUSTEXT handler needs until the acknowledgement of its second cancel command
            # arrives, so a "cancelled" text before that one would deadlock it.
            self._texts = deque(
                [(now + _CANCEL_NOTICED_S, _CRITICAL, "[cal] calibration cancelled")]
            )
            return mavlink.MAV_RESULT_ACCEPTED
        vehicle.statustext(now, _CRITICAL, f"command denied during calibration: {cmd.command}\t")
        return mavlink.MAV_RESULT_DENIED

    # ------------------------------------------------------------- commands
    def _cmd_preflight_calibration(self, cmd: Command, link: Link) -> int:
        vehicle = self._vehicle
        state = vehicle.state
        if self.running in self._cancellable and not self._cancelled():
            return self._cancel_check(cmd)
        if state.armed or self.running is not None:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        p1, p2, p3, p4, p5, p6, p7 = cmd.params
        if _is(p1, 1):
            return self._start("gyro")
        if _is(p1, _TEMPERATURE) or _is(p5, _TEMPERATURE) or _is(p7, _TEMPERATURE):
            return mavlink.MAV_RESULT_UNSUPPORTED
        if _is(p2, 1):
            return self._start("mag")
        if _is(p3, 1):
            return self._start("baro")
        if _is(p4, 1):
            self.rc_calibration = True
            vehicle.statustext(state.now_s, _INFO, "Calibration: Disabling RC input\t")
            self._publish()
            return mavlink.MAV_RESULT_ACCEPTED
        if _is(p4, 2):
            return self._start("rc_trim")
        if _is(p5, 1):
            return self._start("accel")
        if _is(p5, 2):
            return self._start("level")
        if _is(p5, 4):
            return self._start("accel_quick")
        if _is(p6, 1) or _is(p6, 2):
            return self._start("airspeed")
        if _is(p7, 1):
            # SITL cannot tell that the battery is disconnected, so PX4 refuses.
            vehicle.statustext(
                state.now_s,
                _CRITICAL,
                "[cal] calibration failed: Disconnect battery and try again",
            )
            return mavlink.MAV_RESULT_DENIED
        if _is(p4, 0):
            if self.rc_calibration:
                self.rc_calibration = False
                vehicle.statustext(state.now_s, _INFO, "Calibration: Restoring RC input\t")
                self._publish()
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _cmd_fixed_mag_cal_yaw(self, cmd: Command, link: Link) -> int:
        vehicle = self._vehicle
        state = vehicle.state
        if state.armed or self.running is not None:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        heading = float(round(cmd.params[0])) if math.isfinite(cmd.params[0]) else 0.0
        self.running = "mag_quick"
        self._texts = deque(
            [
                (state.now_s, _INFO, f"Assuming vehicle is facing heading {heading:.1f} degrees"),
                (state.now_s + 0.05, _INFO, "Mag quick calibration finished"),
            ]
        )
        self.update(state.now_s)
        return mavlink.MAV_RESULT_ACCEPTED


#: The calibration commands PX4's commander answers.
CALIBRATION_COMMANDS: CommandTable[Calibration] = {
    mavlink.MAV_CMD_PREFLIGHT_CALIBRATION: Calibration._cmd_preflight_calibration,
    mavlink.MAV_CMD_FIXED_MAG_CAL_YAW: Calibration._cmd_fixed_mag_cal_yaw,
}
