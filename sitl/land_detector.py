"""Land detection of one vehicle: whether it stands on the ground, and its MAV_LANDED_STATE.

Like PX4's land_detector module, :class:`LandDetector` only observes: once per autopilot step
it reads the vehicle's height and vertical speed, sets ``landed`` and ``landed_state`` in the
shared :class:`sitl.vehicle_state.VehicleState` and reports a touchdown or a take-off as a
:class:`LandEvent`. The commander (:mod:`sitl.commander`) announces the event and lets the
navigator react (hold on the ground until auto-disarm).
"""

from __future__ import annotations

import enum

from pymavlink.dialects.v20 import common as mavlink

from sitl.vehicle_state import VehicleContext

_LANDED_AFTER_S = 0.5  # on the ground this long (armed, in flight) counts as landed
_TAKEOFF_HEIGHT_M = 0.1  # hysteresis: airborne only once clearly off the ground
_GROUND_HEIGHT_M = 0.05
_GROUND_MAX_CLIMB_RATE_M_S = 0.5


class LandEvent(enum.Enum):
    TOUCHDOWN = "touchdown"
    TAKEOFF = "takeoff"


class LandDetector:
    """Landed / airborne with hysteresis, for one vehicle."""

    def __init__(self, vehicle: VehicleContext) -> None:
        self._vehicle = vehicle
        self._ground_since_s: float | None = 0.0
        #: When the vehicle last touched down (simulated s), for the auto-disarm timeout.
        self.landed_at_s = 0.0

    def update(self, now_s: float, *, taking_off: bool) -> LandEvent | None:
        """Detect at ``now_s``; ``taking_off`` says the navigator is climbing to take off."""
        vehicle = self._vehicle
        state = vehicle.state
        pos = vehicle.position_ned()
        vel = vehicle.velocity_ned()
        on_ground = pos[2] >= -_GROUND_HEIGHT_M and abs(vel[2]) < _GROUND_MAX_CLIMB_RATE_M_S
        if on_ground:
            if self._ground_since_s is None:
                self._ground_since_s = now_s
        else:
            self._ground_since_s = None
        if state.landed:
            landed = pos[2] > -_TAKEOFF_HEIGHT_M or not state.armed
        else:
            landed = not state.armed and on_ground
            if self._ground_since_s is not None:
                landed = landed or now_s - self._ground_since_s >= _LANDED_AFTER_S
        event = None
        if landed != state.landed:
            state.landed = landed
            if landed:
                self.landed_at_s = now_s
                state.landing = False
                event = LandEvent.TOUCHDOWN
            else:
                event = LandEvent.TAKEOFF
        if landed:
            state.landed_state = mavlink.MAV_LANDED_STATE_ON_GROUND
        elif state.landing:
            state.landed_state = mavlink.MAV_LANDED_STATE_LANDING
        elif taking_off:
            state.landed_state = mavlink.MAV_LANDED_STATE_TAKEOFF
        else:
            state.landed_state = mavlink.MAV_LANDED_STATE_IN_AIR
        return event
