"""Errors of the flying runner.

Exception tree::

    MissionRunnerError               (mission_runner.errors)
    └── RunnerError
        ├── VehicleConnectionError   a vehicle could not be reached or did not become healthy
        ├── VehicleCommandError      a vehicle refused or did not acknowledge a command
        └── RunnerTimeoutError       an external wait ran out; the message names what
"""

from ..errors import MissionRunnerError


class RunnerError(MissionRunnerError):
    """Base class of the runner's errors."""


class VehicleConnectionError(RunnerError):
    """A vehicle could not be reached, discovered or did not report healthy."""


class VehicleCommandError(RunnerError):
    """A vehicle refused a command (arm, takeoff, offboard, land)."""


class RunnerTimeoutError(RunnerError):
    """An external wait timed out; ``what`` names it and ``timeout_s`` how long it waited."""

    def __init__(self, what: str, timeout_s: float) -> None:
        self.what = what
        self.timeout_s = timeout_s
        super().__init__(f"timed out after {timeout_s:g} s waiting for {what}")
