"""Which flight task flies the modes that are neither the navigator's nor offboard.

PX4's flight mode manager runs a flight task per mode: the navigator's setpoints in the AUTO
modes, and its own tasks for the modes the navigator does not fly, ORBIT, FOLLOW_TARGET and the
stick modes. :class:`FlightModeManager` is that choice for the emulator: the commander asks
:meth:`FlightModeManager.flies` whether a mode is one of them, :meth:`FlightModeManager.activate`
when the vehicle starts flying it, and the autopilot calls :meth:`FlightModeManager.update` once
per step while armed.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

from sitl.modes import FlightMode
from sitl.vehicle_state import VehicleContext


class FlightTask(Protocol):
    """A mode's setpoint generator: it writes into its vehicle's row of the physics."""

    def activate(self) -> None:
        """The vehicle starts flying the mode (armed): take over from the current motion."""

    def update(self, dt_s: float) -> None:
        """One autopilot step, ``dt_s`` after the previous one (0 right after activation)."""


class FlightModeManager:
    """The flight tasks of one vehicle, by the mode each flies."""

    def __init__(self, vehicle: VehicleContext, tasks: Mapping[FlightMode, FlightTask]) -> None:
        self._vehicle = vehicle
        self._tasks = dict(tasks)
        self._last_s: float | None = None

    def flies(self, mode: FlightMode) -> bool:
        return mode in self._tasks

    def activate(self) -> None:
        task = self._tasks.get(self._vehicle.state.mode)
        if task is not None:
            self._last_s = None
            task.activate()

    def update(self, now_s: float) -> None:
        task = self._tasks.get(self._vehicle.state.mode)
        if task is not None:
            dt = 0.0 if self._last_s is None else max(now_s - self._last_s, 0.0)
            self._last_s = now_s
            task.update(dt)
