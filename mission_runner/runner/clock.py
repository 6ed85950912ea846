"""Mission clocks: the time base every vehicle's t_k = start + kT refers to.

- :class:`EmulatorClock`: the emulator's simulated time (real time, sped up, or lockstep). In
  lockstep each controller is a participant: the world advances only as far as every controller
  has released, so results do not depend on machine load.
- :class:`WallClock`: UNIX time (optionally scaled, :class:`.timesync.MissionTime`), for vehicle
  processes on time-synchronised companion computers (NTP or GPS); each autopilot's boot clock is
  mapped onto it continuously (:class:`.timesync.ClockMapping`).

Both are the mission side's one :class:`mission_runner.clock.Clock` (``now_s()``,
``sleep(seconds)``) plus what a controller needs (:class:`.ports.ControllerClock`):
``sleep_until(t)``, ``release(t)``, ``rate`` and ``lockstep``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any, Protocol, Self

from .timesync import MissionTime

if TYPE_CHECKING:
    from sitl.clock import Clock as SimulatedClock
    from sitl.clock import Participant

logger = logging.getLogger(__name__)

#: How long (wall seconds) a lockstep command waits to be seen by the emulated vehicle.
DELIVERY_TIMEOUT_S = 1.0


class SetpointsTaken(Protocol):
    """An emulated vehicle's offboard setpoints taken (``sitl.autopilot.Px4Autopilot``): how
    many so far, and a call after each."""

    @property
    def accepted_setpoints(self) -> int: ...

    def add_setpoint_listener(self, listener: Callable[[], None]) -> None: ...

    def remove_setpoint_listener(self, listener: Callable[[], None]) -> None: ...


class EmulatorClock:
    """A participant view of a :class:`sitl.clock.Clock`. Use as ``async with``.

    ``setpoints``: the emulated vehicle's offboard setpoints taken. With it, a lockstep command
    (:meth:`commanding`) is applied at a fixed simulated time: the world waits at the release
    point until the setpoint has arrived, whatever the MAVSDK server and the machine's load make
    of its delivery.
    """

    def __init__(
        self, clock: SimulatedClock, name: str, setpoints: SetpointsTaken | None = None
    ) -> None:
        self._clock = clock
        self._setpoints = setpoints
        #: Set by the vehicle each time it takes a setpoint (while this clock is entered).
        self._setpoint_taken = asyncio.Event()
        self.name = name
        self.lockstep = clock.mode == "lockstep"
        self._participant: Participant | None = None
        self._stack = contextlib.AsyncExitStack()

    async def __aenter__(self) -> Self:
        async with contextlib.AsyncExitStack() as stack:
            if self.lockstep:
                self._participant = await stack.enter_async_context(
                    self._clock.participant(self.name)
                )
                if self._setpoints is not None:
                    taken = self._setpoint_taken.set
                    self._setpoints.add_setpoint_listener(taken)
                    stack.callback(self._setpoints.remove_setpoint_listener, taken)
            self._stack = stack.pop_all()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self._stack.aclose()
        self._participant = None

    def now_s(self) -> float:
        return self._clock.now_s()

    @property
    def rate(self) -> float:
        """Mission seconds per wall second (the speed factor; lockstep has none)."""
        return self._clock.speed if not self.lockstep else 1.0

    async def sleep(self, seconds: float) -> None:
        await self._clock.sleep_until(self._clock.now_s() + seconds)

    async def sleep_until(self, time_s: float) -> None:
        await self._clock.sleep_until(time_s)

    def release(self, time_s: float) -> None:
        """Let the world run up to ``time_s`` (lockstep); a no-op in real time."""
        if self._participant is not None:
            self._participant.acted(time_s)

    @contextlib.asynccontextmanager
    async def commanding(self, released_s: float) -> AsyncIterator[None]:
        """Around sending a setpoint whose step released the world up to ``released_s``. In
        lockstep the world is first let reach ``released_s`` and held there until the vehicle
        has the setpoint, so every command takes effect at that simulated time; in real time
        nothing is waited for."""
        setpoints = self._setpoints
        if self._participant is None or setpoints is None:
            yield
            return
        await self._clock.sleep_until(released_s)
        before = setpoints.accepted_setpoints
        yield
        try:
            async with asyncio.timeout(DELIVERY_TIMEOUT_S):
                # Woken by the emulator's datagram handler as it takes a setpoint (the MAVSDK
                # server, another process, delivers it meanwhile); no other await between the
                # count's check and the clear, so none is missed.
                while setpoints.accepted_setpoints == before:
                    self._setpoint_taken.clear()
                    await self._setpoint_taken.wait()
        except TimeoutError:
            logger.warning(
                "%s: setpoint not seen by the vehicle within %.1f s", self.name, DELIVERY_TIMEOUT_S
            )


class WallClock:
    """The mission clock of a vehicle process: ``time`` (a :class:`MissionTime`, UNIX time by
    default) in seconds; ``release`` is a no-op."""

    lockstep = False

    def __init__(self, time: MissionTime | None = None) -> None:
        self.time = time or MissionTime()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        return None

    def now_s(self) -> float:
        return self.time.now_s()

    @contextlib.asynccontextmanager
    async def commanding(self, released_s: float) -> AsyncIterator[None]:
        """Nothing to wait for: real vehicles take setpoints in real time."""
        yield

    @property
    def rate(self) -> float:
        """Mission seconds per wall second."""
        return self.time.rate

    async def sleep(self, seconds: float) -> None:
        await self.sleep_until(self.now_s() + seconds)

    async def sleep_until(self, time_s: float) -> None:
        # Through the mission clock's rate changes, if one falls in the sleep.
        delay = self.time.to_unix(time_s) - self.time.unix_now_s()
        if delay > 0:
            await asyncio.sleep(delay)

    def release(self, time_s: float) -> None:
        return None
