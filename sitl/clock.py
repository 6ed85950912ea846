"""The one clock of an emulation run: real time, sped-up real time, or lockstep.

Everything in the emulator that waits (offboard-loss and link-loss timeouts, auto-disarm,
telemetry periods, mission retries) counts *simulated* seconds, which come from here, so a speed
factor scales all of them together.

Modes
-----
``realtime``
    simulated time = ``speed`` x wall time since :meth:`Clock.start`. Participants may register
    but do not hold time back.
``lockstep``
    simulated time advances only up to :meth:`Clock.allowed_time_s`, the minimum over registered
    participants of the time each has released with :meth:`Clock.acted` (infinite when nobody is
    registered, optionally capped at ``lockstep_max_speed`` x wall time). The driver (the
    emulator's physics loop) calls :meth:`Clock.advance_to` after every step, which wakes
    participants sleeping in :meth:`Clock.sleep_until`.

A participant's loop looks like::

    async with clock.participant("controller") as me:
        t = clock.now_s()
        while True:
            ...read telemetry, send setpoints...
            t += 0.05
            me.acted(t)              # the world may advance to t
            await clock.sleep_until(t)

A participant that stops acting (crashed, hung) is dropped after ``participant_timeout_s`` wall
seconds with a warning; leaving ``participant()`` unregisters it at once, also on errors.

The driver advances in fixed steps (:meth:`Clock.set_step`, the physics step). A release that
falls between two steps lets the world run to the last step before it, and ``sleep_until`` of
such a time returns there: the world cannot get closer without passing the release. Releasing
multiples of the step avoids the rounding.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import itertools
import logging
import math
import time
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from sitl.errors import ClockError

if TYPE_CHECKING:
    from sitl.config import ClockConfig

logger = logging.getLogger(__name__)

ClockMode = Literal["realtime", "lockstep"]


@dataclass(slots=True)
class _Participant:
    released_until_s: float
    last_act_wall_s: float


class Participant:
    """Handle returned by :meth:`Clock.participant`; ``acted(t)`` releases time up to ``t``."""

    def __init__(self, clock: Clock, name: str) -> None:
        self._clock = clock
        self.name = name

    def acted(self, up_to_time_s: float) -> None:
        self._clock.acted(self.name, up_to_time_s)


class Clock:
    """Simulated time shared by the emulator and everything that takes part in a run.

    ``wall_time`` is the wall clock in seconds (injected for tests, default ``time.monotonic``).
    Not thread-safe: use it from the event loop that runs the emulator.
    """

    def __init__(
        self,
        mode: ClockMode = "realtime",
        speed: float = 1.0,
        *,
        lockstep_max_speed: float | None = None,
        participant_timeout_s: float | None = 10.0,
        pace: Sequence[tuple[float, float]] = (),
        wall_time: Callable[[], float] = time.monotonic,
    ) -> None:
        if mode not in ("realtime", "lockstep"):
            raise ClockError(f"unknown clock mode {mode!r}; use 'realtime' or 'lockstep'")
        if not speed > 0:
            raise ClockError(f"speed must be > 0, got {speed!r}")
        self.mode: ClockMode = mode
        self.speed = float(speed)
        #: Realtime: (wall seconds after the start, speed from then on), in order.
        self.pace = [(float(after_s), float(later)) for after_s, later in pace]
        if any(not later > 0 for _, later in self.pace):
            raise ClockError(f"every speed of pace must be > 0, got {pace!r}")
        self.lockstep_max_speed = lockstep_max_speed
        self.participant_timeout_s = participant_timeout_s
        self._wall_time = wall_time
        self._wall_start_s: float | None = None
        self._lockstep_now_s = 0.0
        self._participants: dict[str, _Participant] = {}
        self._changed: asyncio.Event | None = None
        self._sleepers: list[tuple[float, int, asyncio.Future[None]]] = []
        self._sleeper_ids = itertools.count()
        self._step_s: float | None = None

    @classmethod
    def from_config(cls, config: ClockConfig, **kwargs: object) -> Clock:
        return cls(
            config.mode,
            config.speed,
            lockstep_max_speed=config.lockstep_max_speed,
            participant_timeout_s=config.participant_timeout_s,
            pace=[(change.after_s, change.speed) for change in config.pace],
            **kwargs,  # type: ignore[arg-type]
        )

    # ------------------------------------------------------------------ time
    def start(self) -> None:
        """Fix wall time zero; called by the emulator when it starts (later calls are no-ops)."""
        if self._wall_start_s is None:
            self._wall_start_s = self._wall_time()

    def set_step(self, step_s: float) -> None:
        """Driver only: simulated time advances in steps of ``step_s`` seconds."""
        if not step_s > 0:
            raise ClockError(f"step must be > 0, got {step_s!r}")
        self._step_s = step_s

    def _reachable(self, time_s: float) -> float:
        """The last step time at or before ``time_s`` (``time_s`` itself without steps)."""
        step = self._step_s
        if step is None or not math.isfinite(time_s):
            return time_s
        return math.floor(time_s / step + 1e-9) * step

    @property
    def started(self) -> bool:
        return self._wall_start_s is not None

    def _wall_elapsed_s(self) -> float:
        if self._wall_start_s is None:
            return 0.0
        return self._wall_time() - self._wall_start_s

    def now_s(self) -> float:
        """Current simulated time in seconds since start."""
        if self.mode == "realtime":
            return self._realtime_s(self._wall_elapsed_s())
        return self._lockstep_now_s

    def _realtime_s(self, wall_s: float) -> float:
        """Simulated time ``wall_s`` wall seconds after the start, through :attr:`pace`."""
        time_s, since_s, speed = 0.0, 0.0, self.speed
        for after_s, later in self.pace:
            if wall_s <= after_s:
                break
            time_s += (after_s - since_s) * speed
            since_s, speed = after_s, later
        return time_s + (wall_s - since_s) * speed

    @property
    def current_speed(self) -> float:
        """Simulated seconds per wall second now (realtime: through :attr:`pace`)."""
        wall_s = self._wall_elapsed_s()
        return next(
            (later for after_s, later in reversed(self.pace) if wall_s > after_s), self.speed
        )

    def allowed_time_s(self) -> float:
        """How far the driver may advance simulated time right now."""
        if self.mode == "realtime":
            return self.now_s()
        allowed = min((p.released_until_s for p in self._participants.values()), default=math.inf)
        if self.lockstep_max_speed is not None:
            allowed = min(allowed, self._wall_elapsed_s() * self.lockstep_max_speed)
        return allowed

    # ---------------------------------------------------------- participants
    @property
    def participants(self) -> dict[str, float]:
        """Registered participants and the time each has released."""
        return {name: p.released_until_s for name, p in self._participants.items()}

    def register(self, name: str, released_until_s: float | None = None) -> None:
        """Add a participant; until it acts it holds time at ``released_until_s`` (default now)."""
        if name in self._participants:
            raise ClockError(f"participant {name!r} is already registered")
        start = self.now_s() if released_until_s is None else released_until_s
        self._participants[name] = _Participant(start, self._wall_time())
        self._notify()

    def acted(self, name: str, up_to_time_s: float) -> None:
        """Participant ``name`` has done its work and lets time advance to ``up_to_time_s``."""
        participant = self._participants.get(name)
        if participant is None:
            raise ClockError(
                f"participant {name!r} is not registered (dropped after a stall, or never "
                "registered); register it again"
            )
        if not up_to_time_s >= participant.released_until_s:
            raise ClockError(
                f"participant {name!r} released {up_to_time_s!r} s, before its earlier release "
                f"{participant.released_until_s!r} s"
            )
        participant.released_until_s = up_to_time_s
        participant.last_act_wall_s = self._wall_time()
        self._notify()

    def unregister(self, name: str) -> None:
        """Remove a participant (unknown names are ignored: a dropped one may leave late)."""
        if self._participants.pop(name, None) is not None:
            self._notify()

    @contextlib.asynccontextmanager
    async def participant(
        self, name: str, released_until_s: float | None = None
    ) -> AsyncIterator[Participant]:
        """Register ``name`` for the duration of the block; unregistered however it ends."""
        self.register(name, released_until_s)
        try:
            yield Participant(self, name)
        finally:
            self.unregister(name)

    def _notify(self) -> None:
        if self._changed is not None:
            self._changed.set()

    # -------------------------------------------------------------- sleeping
    async def sleep_until(self, time_s: float) -> None:
        """Wait until simulated time has reached ``time_s``."""
        if self.mode == "realtime":
            while True:
                remaining = time_s - self.now_s()
                if remaining <= 0:
                    return
                await asyncio.sleep(remaining / self.current_speed)
        wake_s = self._reachable(time_s) - 1e-9
        if self._lockstep_now_s >= wake_s:
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._sleepers, (wake_s, next(self._sleeper_ids), future))
        await future

    async def sleep(self, duration_s: float) -> None:
        """Wait ``duration_s`` simulated seconds."""
        await self.sleep_until(self.now_s() + duration_s)

    # ---------------------------------------------------------------- driver
    def advance_to(self, time_s: float) -> None:
        """Driver only: simulated time is now ``time_s``; wakes sleepers that are due."""
        if self.mode == "realtime":
            return
        if time_s < self._lockstep_now_s:
            raise ClockError(f"time cannot go back from {self._lockstep_now_s} to {time_s}")
        if time_s > self.allowed_time_s() + 1e-9:
            raise ClockError(f"advance to {time_s} s beyond allowed {self.allowed_time_s()} s")
        self._lockstep_now_s = time_s
        sleepers = self._sleepers
        while sleepers and sleepers[0][0] <= time_s:
            _, _, future = heapq.heappop(sleepers)
            if not future.done():
                future.set_result(None)

    async def wait_until_allowed_beyond(self, time_s: float) -> None:
        """Driver only: wait until :meth:`allowed_time_s` exceeds ``time_s``.

        In realtime mode this sleeps the wall time it takes. In lockstep mode it waits for
        participants; one that has not acted for ``participant_timeout_s`` wall seconds while
        holding time back is dropped.
        """
        if self.mode == "realtime":
            await self.sleep_until(time_s + 1e-9)
            return
        if self._changed is None:
            self._changed = asyncio.Event()
        while self.allowed_time_s() <= time_s:
            self._changed.clear()
            timeout = self._wait_timeout_s(time_s)
            # asyncio.timeout, not wait_for: Python 3.11's wait_for can swallow a cancellation
            # that races with the event, and the physics loop would then never end.
            try:
                async with asyncio.timeout(timeout):
                    await self._changed.wait()
            except TimeoutError:
                self._drop_stalled(time_s)

    def _wait_timeout_s(self, time_s: float) -> float | None:
        timeouts: list[float] = []
        if self.lockstep_max_speed is not None:
            # Time held back only by the speed cap: wake when the wall clock allows it.
            blockers = [p for p in self._participants.values() if p.released_until_s <= time_s]
            if not blockers:
                wall_needed = time_s / self.lockstep_max_speed - self._wall_elapsed_s()
                timeouts.append(max(wall_needed, 0.0) + 1e-4)
        if self.participant_timeout_s is not None and self._participants:
            now_wall = self._wall_time()
            oldest = min(
                (
                    p.last_act_wall_s
                    for p in self._participants.values()
                    if p.released_until_s <= time_s
                ),
                default=now_wall,
            )
            timeouts.append(max(oldest + self.participant_timeout_s - now_wall, 0.0))
        return min(timeouts) if timeouts else None

    def _drop_stalled(self, time_s: float) -> None:
        if self.participant_timeout_s is None:
            return
        now_wall = self._wall_time()
        for name, p in list(self._participants.items()):
            stalled_for = now_wall - p.last_act_wall_s
            if p.released_until_s <= time_s and stalled_for >= self.participant_timeout_s:
                logger.warning(
                    "lockstep participant %r held time at %.3f s for %.1f wall s; dropping it",
                    name,
                    p.released_until_s,
                    stalled_for,
                )
                del self._participants[name]
