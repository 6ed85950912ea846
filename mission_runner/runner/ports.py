"""What a vehicle controller needs from the clock, the vehicle link and the bus it is handed.

Structural protocols holding only the members :class:`.controller.VehicleController` uses, so
that anything offering them fits: the emulator's and the wall clock (:mod:`.clock`), the MAVSDK
vehicle (:mod:`.links`), the in-process and MQTT buses (:mod:`mission_runner.bus`), and the
fakes of the controller's unit tests, none of which name these classes.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import AbstractAsyncContextManager
from typing import Protocol, TypeVar

from ..bus import Message
from ..clock import Clock
from .odometry import OdometrySample

M = TypeVar("M", bound=Message)


class ControllerClock(Clock, Protocol):
    """The mission clock every t_k = start + kT refers to: the mission side's one
    :class:`mission_runner.clock.Clock` (``now_s()``, ``sleep()``) plus what a controller needs."""

    @property
    def lockstep(self) -> bool:
        """Whether the world stands still until every controller has released it (so waits
        are bounded in wall seconds, not mission seconds)."""
        ...

    @property
    def rate(self) -> float:
        """Mission seconds per wall second."""
        ...

    async def sleep_until(self, time_s: float) -> None:
        """Return at mission time ``time_s`` [s] (at once if it is past)."""
        ...

    def release(self, time_s: float) -> None:
        """Let the world run up to mission time ``time_s`` [s] (lockstep; else nothing)."""
        ...

    def commanding(self, released_s: float) -> AbstractAsyncContextManager[None]:
        """Around sending a setpoint of a step that released the world up to ``released_s``:
        in lockstep the command takes effect at exactly that time (else nothing happens)."""
        ...


class OdometrySource(Protocol):
    """The vehicle's own odometry on the mission clock, north-east-down [m] from its origin."""

    @property
    def latest(self) -> OdometrySample | None:
        """The newest sample, or None before the first."""
        ...

    def at(self, time_s: float, *, extrapolate_s: float = 0.0) -> tuple[float, float, float] | None:
        """``(north_m, east_m, down_m)`` at mission time ``time_s``, or None if not known
        (extrapolated from the newest sample up to ``extrapolate_s`` past it, where the source
        can)."""
        ...


class ControllerLink(Protocol):
    """The vehicle as the controller drives it: odometry in, velocity setpoints out."""

    @property
    def odometry(self) -> OdometrySource: ...

    @property
    def in_control(self) -> bool:
        """Whether the vehicle is seen armed and in OFFBOARD since the runner put it there (the
        autopilot said so; never assumed from the runner's own commands)."""
        ...

    @property
    def control_lost(self) -> str | None:
        """Why the vehicle left the runner's control by someone else's hand (a pilot, another
        ground station, an autopilot failsafe): a mode change or a disarm while in OFFBOARD;
        None while it has not. Final: the runner never takes a vehicle back."""
        ...

    async def odometry_updated(self) -> None:
        """Return when the next odometry sample has arrived."""
        ...

    async def set_velocity_ned(self, north_m_s: float, east_m_s: float, down_m_s: float) -> None:
        """Send a velocity setpoint, north-east-down [m/s]."""
        ...


class MessageSource(Protocol):
    """A subscription, as the controller reads it."""

    def messages(self, message_type: type[M]) -> AsyncIterator[tuple[str, M]]:
        """``(topic, message)`` pairs decoded as ``message_type``, until the subscription ends."""
        ...


class ControllerBus(Protocol):
    """The message bus: subscriptions for the inbox, publishing with a bounded wait."""

    def subscribe(self, pattern: str) -> AbstractAsyncContextManager[MessageSource]:
        """Messages on topics matching ``pattern`` (MQTT wildcards) while inside the block."""
        ...

    async def publish_message(self, topic: str, message: Message, *, timeout: float) -> None:
        """Publish ``message`` on ``topic``, waiting at most ``timeout`` seconds."""
        ...
