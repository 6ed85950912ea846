"""Step alignment: what one vehicle has heard for step k, and who is still in the swarm.

Every k-indexed input of the law must refer to the instant t_k = start + kT on every vehicle:

- a neighbour's phase and odometry come in its step-k :class:`StepMessage` (it samples its own
  odometry at t_k, see :mod:`.odometry`);
- ranges are sampled by the UWB driver at t_k and published together, one :class:`RangeSet` per
  ranging round, with ``step = k`` (or a timestamp within a quarter step of t_k): once it is in,
  no more of this vehicle's step-k ranges are coming (one it lacks was dropped, and never comes);
- the target observation likewise.

The controller waits for step k's inputs until its deadline, then takes whatever arrived: a
neighbour whose step-k message is late or lost simply drops out of that step (the estimator's
anchor makes the next update span the gap, see :mod:`mission_runner.enclosing.rlse`). Anything for
an older step that arrives late is discarded, never applied to the wrong step. A neighbour not heard
for ``member_timeout_steps`` steps is no longer a member: n shrinks and the rest re-balance; it
becomes a member again as soon as it is heard.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..bus import RangeSet, StepMessage, TargetObservation


@dataclass
class StepData:
    """What arrived for one step: step messages by vehicle id, ranges by peer id (0 = target),
    whether this vehicle's range set came (``ranges_in``, even empty), the target observation if
    any, and the member ids (including the vehicle itself)."""

    step: int
    neighbours: dict[int, StepMessage] = field(default_factory=dict)
    ranges_m: dict[int, float] = field(default_factory=dict)
    ranges_in: bool = False
    target: TargetObservation | None = None
    members: frozenset[int] = frozenset()


class StepInbox:
    """Collects one vehicle's inputs per step.

    own_id: this vehicle. vehicle_ids: every vehicle that may take part. senses_target: whether a
    target observation is expected. step_of(time_s) -> int | None maps a timestamp to its step
    (None when it is not close to any step boundary). horizon_steps: how far ahead of the current
    step messages are kept (a fast neighbour may be a little ahead).
    """

    def __init__(
        self,
        own_id: int,
        vehicle_ids: Iterable[int],
        *,
        senses_target: bool,
        step_of: Callable[[float], int | None],
        member_timeout_steps: int,
        horizon_steps: int = 4,
    ) -> None:
        self.own_id = own_id
        self.senses_target = senses_target
        self._step_of = step_of
        self._timeout = member_timeout_steps
        self._horizon = horizon_steps
        self.others = tuple(peer for peer in vehicle_ids if peer != own_id)
        self._last_heard = {peer: 0 for peer in self.others}  # members from the start
        self._current = 0
        self._pending: dict[int, StepData] = {}
        self._changed = asyncio.Event()
        self.discarded_late = 0

    @property
    def current_step(self) -> int:
        return self._current

    def members(self) -> frozenset[int]:
        """Ids counted as live now (this vehicle included)."""
        alive = {
            peer
            for peer, heard in self._last_heard.items()
            if self._current - heard <= self._timeout
        }
        return frozenset({self.own_id, *alive})

    def _slot(self, step: int) -> StepData | None:
        if step < self._current:
            self.discarded_late += 1  # never applied to a later step
            return None
        if step > self._current + self._horizon:
            return None
        return self._pending.setdefault(step, StepData(step))

    def add_step(self, message: StepMessage) -> None:
        """A neighbour's StepMessage (own messages are ignored)."""
        if message.vehicle_id == self.own_id or message.vehicle_id not in self._last_heard:
            return
        # Even a late message proves its sender is alive: without this, a neighbour that fell
        # out of the membership and is always a little late would never be waited for again.
        heard = self._last_heard[message.vehicle_id]
        self._last_heard[message.vehicle_id] = max(heard, min(message.step, self._current))
        data = self._slot(message.step)
        if data is not None:
            data.neighbours[message.vehicle_id] = message
            self._changed.set()

    def add_ranges(self, message: RangeSet) -> None:
        """A RangeSet measured by this vehicle: its ranges of that instant are all in, even when
        the set is empty or lacks a member (that range dropped out, and never comes)."""
        if message.vehicle_id != self.own_id:
            return
        step = message.step if message.step is not None else self._step_of(message.time_s)
        data = None if step is None else self._slot(step)
        if data is not None:
            data.ranges_m.update(message.ranges_m)
            data.ranges_in = True
            self._changed.set()

    def add_target(self, observation: TargetObservation) -> None:
        """A TargetObservation made by this vehicle."""
        if observation.vehicle_id != self.own_id:
            return
        step = self._step_of(observation.time_s)
        data = None if step is None else self._slot(step)
        if data is not None:
            data.target = observation
            self._changed.set()

    def complete(self, step: int) -> bool:
        """Whether every member's message, this vehicle's ranges and (if sensed) the target are
        in for ``step``."""
        data = self._pending.get(step)
        if data is None:
            return False
        others = self.members() - {self.own_id}
        if not others <= data.neighbours.keys() or not (data.ranges_in or not others):
            return False
        return data.target is not None or not self.senses_target

    def own_ranges_in(self, step: int) -> bool:
        """Whether this vehicle's range set is in for ``step`` (needed only with other members:
        a vehicle alone has nobody to range)."""
        data = self._pending.get(step)
        return data is not None and (data.ranges_in or not self.members() - {self.own_id})

    def pending_ranges(self, step: int) -> dict[int, float]:
        """This vehicle's ranges received for ``step`` so far, by peer id (0 = target)."""
        data = self._pending.get(step)
        return {} if data is None else dict(data.ranges_m)

    def pending_target(self, step: int) -> TargetObservation | None:
        """The target observation received for ``step`` so far, or None."""
        data = self._pending.get(step)
        return None if data is None else data.target

    async def wait_for(self, condition: Callable[[], bool], timeout_s: float) -> bool:
        """Wait until ``condition()`` holds, re-checked on every arrival, for at most
        ``timeout_s`` wall seconds. Returns whether it holds."""
        try:
            async with asyncio.timeout(timeout_s):
                while not condition():
                    self._changed.clear()
                    await self._changed.wait()
        except TimeoutError:
            return condition()
        return True

    async def wait_complete(self, step: int, timeout_s: float) -> bool:
        """Wait until :meth:`complete` or ``timeout_s`` wall seconds; returns whether complete."""
        return await self.wait_for(lambda: self.complete(step), timeout_s)

    def take(self, step: int) -> StepData:
        """Close ``step``: return what arrived, update membership, drop older data."""
        data = self._pending.pop(step, None) or StepData(step)
        for peer in data.neighbours:
            self._last_heard[peer] = step
        self._current = step
        data.members = self.members()
        self._current = step + 1
        for old in [s for s in self._pending if s <= step]:
            del self._pending[old]
        return data
