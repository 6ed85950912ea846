"""Mission clocks: the time base every vehicle's t_k = start + kT refers to.

- :class:`EmulatorClock`: the emulator's simulated time (real time, sped up, or lockstep). In
  lockstep each controller is a participant: the world advances only as far as every controller
  has released, so results do not depend on machine load.
- :class:`WallClock`: UNIX time, for real vehicles whose companion computers are time-synchronised
  (NTP or GPS); PX4's SYSTEM_TIME maps its boot time onto it.

Both offer ``now_s()``, ``sleep_until(t)``, ``release(t)`` and ``lockstep``.
"""

import asyncio
import contextlib
import time


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

    async def sleep_until(self, time_s):
        await self._clock.sleep_until(time_s)

    def release(self, time_s):
        """Let the world run up to ``time_s`` (lockstep); a no-op in real time."""
        if self._participant is not None:
            self._participant.acted(time_s)


class WallClock:
    """UNIX time in seconds; ``release`` is a no-op."""

    lockstep = False

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc_info):
        return None

    @staticmethod
    def now_s():
        return time.time()

    async def sleep_until(self, time_s):
        delay = time_s - time.time()
        if delay > 0:
            await asyncio.sleep(delay)

    def release(self, time_s):
        return None
