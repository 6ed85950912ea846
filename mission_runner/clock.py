"""The one clock protocol of the mission side: ``now_s()`` and ``sleep(seconds)``.

Nothing reads time or sleeps directly; it takes a :class:`Clock`, so a test can drive it
deterministically with :class:`ManualClock` (time moves only when the test says so). The bus's
link model and reconnect backoff take a :class:`MonotonicClock`; the controllers take a mission
clock (:mod:`.runner.clock`: the emulator's simulated time or synchronised UNIX time), which adds
``sleep_until``, ``release``, ``rate`` and ``lockstep`` (:class:`.runner.ports.ControllerClock`).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import time
from typing import Protocol


class Clock(Protocol):
    """Where the bus reads time (seconds, monotonic) and how it sleeps."""

    def now_s(self) -> float:
        """Current time in seconds; only differences are meaningful."""
        ...

    async def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of this clock's time."""
        ...


class MonotonicClock:
    """The real clock: ``time.monotonic`` and ``asyncio.sleep``."""

    def now_s(self) -> float:
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(seconds, 0.0))


class ManualClock:
    """A clock that stands still until ``advance`` moves it; sleepers wake in due order.

    ``advance`` wakes each sleeper due within the step at its own due time (so ``now_s()``
    seen by the woken task is its due time) and yields to the event loop after each wake
    so the woken task can run up to its next await.
    """

    def __init__(self, start_s: float = 0.0, *, yields_per_wake: int = 8) -> None:
        self._now_s = float(start_s)
        self._yields_per_wake = yields_per_wake
        self._sleepers: list[tuple[float, int, asyncio.Future[None]]] = []
        self._sequence = itertools.count()

    def now_s(self) -> float:
        return self._now_s

    async def sleep(self, seconds: float) -> None:
        if seconds <= 0.0:
            await asyncio.sleep(0)
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._sleepers, (self._now_s + seconds, next(self._sequence), waiter))
        # A cancelled sleeper stays in the heap; advance() skips futures already done.
        await waiter

    @property
    def pending_sleepers(self) -> int:
        """Number of tasks currently sleeping on this clock."""
        return sum(1 for _, _, waiter in self._sleepers if not waiter.done())

    async def advance(self, seconds: float) -> None:
        """Move time forward by ``seconds``, waking every sleeper due by then."""
        if seconds < 0.0:
            raise ValueError(f"a clock cannot go back (advance by {seconds} s)")
        target_s = self._now_s + seconds
        await self._settle()
        while self._sleepers and self._sleepers[0][0] <= target_s:
            due_s, _, waiter = heapq.heappop(self._sleepers)
            if waiter.done():
                continue
            self._now_s = max(self._now_s, due_s)
            waiter.set_result(None)
            await self._settle()
        self._now_s = target_s
        await self._settle()

    async def _settle(self) -> None:
        for _ in range(self._yields_per_wake):
            await asyncio.sleep(0)
