"""Mission clocks: the time base every vehicle's t_k = start + kT refers to.

- :class:`EmulatorClock`: the emulator's simulated time (real time, sped up, or lockstep). In
  lockstep each controller is a participant: the world advances only as far as every controller
  has released, so results do not depend on machine load.
- :class:`WallClock`: UNIX time (optionally scaled, :class:`.timesync.MissionTime`), for vehicle
  processes on time-synchronised companion computers (NTP or GPS); each autopilot's boot clock is
  mapped onto it continuously (:class:`.timesync.ClockMapping`).

Both offer ``now_s()``, ``sleep_until(t)``, ``release(t)``, ``rate`` and ``lockstep``.
"""

import asyncio
import contextlib

from .timesync import MissionTime


class EmulatorClock:
    """A participant view of a :class:`sitl.clock.Clock`. Use as ``async with``."""

    def __init__(self, clock, name):
        self._clock = clock
        self.name = name
        self.lockstep = clock.mode == "lockstep"
        self._participant = None
        self._stack = None

    async def __aenter__(self):
        self._stack = contextlib.AsyncExitStack()
        if self.lockstep:
            self._participant = await self._stack.enter_async_context(
                self._clock.participant(self.name)
            )
        return self

    async def __aexit__(self, *exc_info):
        await self._stack.aclose()
        self._participant = None

    def now_s(self):
        return self._clock.now_s

    @property
    def rate(self):
        """Mission seconds per wall second (the speed factor; lockstep has none)."""
        return self._clock.speed if not self.lockstep else 1.0

    async def sleep_until(self, time_s):
        await self._clock.sleep_until(time_s)

    def release(self, time_s):
        """Let the world run up to ``time_s`` (lockstep); a no-op in real time."""
        if self._participant is not None:
            self._participant.acted(time_s)


class WallClock:
    """The mission clock of a vehicle process: ``time`` (a :class:`MissionTime`, UNIX time by
    default) in seconds; ``release`` is a no-op."""

    lockstep = False

    def __init__(self, time=None):
        self.time = time or MissionTime()

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc_info):
        return None

    def now_s(self):
        return self.time.now_s()

    @property
    def rate(self):
        """Mission seconds per wall second."""
        return self.time.rate

    async def sleep_until(self, time_s):
        delay = (time_s - self.now_s()) / self.time.rate
        if delay > 0:
            await asyncio.sleep(delay)

    def release(self, time_s):
        return None
