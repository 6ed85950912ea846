"""The world around the emulated vehicles: a moving target, UWB ranging and a target tracker.

Published where real drivers on companion computers would publish them - on the project's bus
(see :mod:`mission_runner.bus.topics`), never through ground truth:

- ``vehicle/<id>/ranges``: :class:`RangeSet`, the 3-D distances from a live vehicle to the others
  its radio ranged at step boundary t_k = start + kT (``step = k``), one set per vehicle and step
  as a UWB tag reports a ranging round (empty when it ranged nothing), as the scenario's
  ``sensors:`` describe the radios (:class:`mission_runner.sensors.UwbRanging`: one exchange per
  pair or per direction, pair biases, multipath, NLOS bursts, dropouts, airtime, a maximum range);
  under a sparse ``algorithm.graph`` only the graph's edges among the vehicles still flying
  (:class:`mission_runner.wiring.RangingGraph`, as in the numeric simulator);
- ``vehicle/<id>/target``: :class:`TargetObservation` for vehicles that sense the target, its
  horizontal range and velocity (what a radar or vision tracker gives), at the same instants; or,
  when the tracker does not see it (beyond ``sensors.target_sensing_range_m``, a random miss, an
  occlusion, a failed tracker), an explicit "not seen", so the controller does not wait for it.

The target is not a MAVLink vehicle: it follows the scenario's path, standing at its start point
until the mission starts. Sampling runs synchronously inside the emulator's physics step (its step
listener), so in lockstep the measurements belong to exactly the simulated instant they are stamped
with; a task owned by :class:`World` moves them onto the bus.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..bus import BusError, RangeSet, TargetObservation
from ..errors import MissionRunnerError
from ..records import TruthSample
from ..scenario import target_positions
from ..sensors import UwbRanging, measure_ranges, target_seen
from ..wiring import RangingGraph

if TYPE_CHECKING:
    from sitl.emulator import Emulator, Truth

    from ..bus import Bus, BusClient, Topics
    from ..config import EventConfig, Scenario, SensorConfig, TargetPath
    from ..enclosing.graph import Adjacency
    from ..sensors import Rng

logger = logging.getLogger(__name__)

#: One step's measurements as ``(topic, message)`` pairs.
Measured = list[tuple[str, RangeSet | TargetObservation]]


class World:
    """Target + UWB + tracker around an :class:`sitl.emulator.Emulator` (its physics-step hook and
    ground truth). Use as ``async with``; it owns the task that publishes.

        vehicle_ids: the scenario id of emulator vehicle index i is ``vehicle_ids[i]``.
        time_offset_s: mission time = simulated time + offset (0 in-process; the emulator's UNIX
        epoch when vehicles in other processes keep UNIX time). Every time the world takes or
        stamps is mission time. stale_after_steps: a step's measurements not yet published when
        the world has sampled this many steps more are dropped (the bus was down: stale is worse
        than none); None: never (an emulator racing ahead in lockstep, with nobody to wait for).
        senses_target: ``(N,)`` bool. sensors: the scenario's ``SensorConfig``. The first vehicle
        position the emulator places is the scenario's frame origin, so ``target_path`` shares it.
        ranging: the pairs the radios range under a sparse graph, among the vehicles the
        emulator has alive; None: every pair.
    """

    def __init__(
        self,
        emulator: Emulator,
        *,
        bus: Bus | BusClient,
        topics: Topics,
        vehicle_ids: Sequence[int],
        senses_target: ArrayLike,
        target_path: TargetPath,
        target_altitude_m: float,
        sensors: SensorConfig,
        step_s: float,
        seed: int = 0,
        time_offset_s: float = 0.0,
        events: Sequence[EventConfig] = (),
        stale_after_steps: int | None = 2,
        ranging: RangingGraph | None = None,
    ) -> None:
        self.emulator = emulator
        self.ranging = ranging
        self.stale_after_steps = stale_after_steps
        self.bus = bus
        self.topics = topics
        self.vehicle_ids = list(vehicle_ids)
        self.senses_target = np.asarray(senses_target, dtype=bool)
        self.target_path = target_path
        self.target_altitude_m = target_altitude_m
        self.sensors = sensors
        self.step_s = step_s
        self.time_offset_s = time_offset_s
        self.events = list(events)
        self.start_s: float | None = None
        self._next_step = 0
        self._steps: int | None = None
        self._rng = np.random.default_rng([seed, 7])
        # The radios' lasting errors (pair biases, multipath, NLOS bursts) for the mission.
        frame = None if ranging is None else ranging.frame
        self._uwb = UwbRanging(sensors, len(self.vehicle_ids), step_s, graph=frame)
        # (index or None for every vehicle, sensor) -> windows [(from_s, until_s)]
        self._down: dict[tuple[int | None, str], list[tuple[float, float]]] = {}
        # One step's measurements at a time: (k, [(topic, message), ...]).
        self._queue: asyncio.Queue[tuple[int, Measured]] = asyncio.Queue()
        self._stack = contextlib.AsyncExitStack()
        self._task: asyncio.Task[None] | None = None
        self._closing = False
        self.published = 0
        self.dropped = 0  # measurements the bus did not take
        self._dropping = 0  # of them since the last one it took
        self.samples: list[TruthSample] = []  # per step, for scoring only

    async def __aenter__(self) -> Self:
        async with contextlib.AsyncExitStack() as stack:
            group = await stack.enter_async_context(asyncio.TaskGroup())
            stack.push_async_callback(self._stop_publishing)
            stack.callback(self.emulator.add_step_listener(self._on_step))
            self._task = group.create_task(self._publish(), name="world-publisher")
            self._stack = stack.pop_all()
        return self

    async def __aexit__(self, *exc_info: Any) -> bool | None:
        return await self._stack.__aexit__(*exc_info)

    async def _stop_publishing(self) -> None:
        self._closing = True
        # Python 3.11's asyncio.wait_for (inside the MQTT client's publish) can swallow a
        # cancellation that races with its completion: cancel until the task is really done.
        while self._task is not None and not self._task.done():
            self._task.cancel()
            await asyncio.wait({self._task}, timeout=0.05)

    @classmethod
    def for_scenario(
        cls,
        emulator: Emulator,
        scenario: Scenario,
        bus: Bus | BusClient,
        *,
        time_offset_s: float = 0.0,
    ) -> World:
        """The world a mission scenario describes, publishing on ``bus`` under its topics."""
        return cls(
            emulator,
            bus=bus,
            topics=scenario.bus.topics(scenario.name),
            vehicle_ids=[vehicle.id for vehicle in scenario.vehicles],
            senses_target=[vehicle.senses_target for vehicle in scenario.vehicles],
            target_path=scenario.target.path,
            target_altitude_m=scenario.target.altitude_m,
            sensors=scenario.sensors,
            step_s=scenario.timing.step_s,
            seed=scenario.seed,
            time_offset_s=time_offset_s,
            events=scenario.events,
            # In lockstep the mission waits for its measurements: none is ever stale.
            stale_after_steps=None if emulator.clock.mode == "lockstep" else 2,
            ranging=RangingGraph.of(scenario),
        )

    async def drained(self) -> None:
        """Return once every sampled measurement has been handed to the bus (or dropped)."""
        await self._queue.join()

    def start(self, start_s: float, steps: int | None = None) -> None:
        """The mission's k = 0 is at ``start_s``: the target starts moving, ranging begins (for
        ``steps`` steps; default: until the world closes), and the scenario's ``events`` are
        scheduled on the emulator and the world."""
        self.start_s = start_s
        self._next_step = 0
        self._steps = steps
        self._schedule_events(start_s)

    def _schedule_events(self, start_s: float) -> None:
        """Every event at t_k of its step: the world's own (sensors, the target hidden) on the
        mission clock, the vehicles' faults on the emulator's (``time_offset_s`` earlier)."""
        index_of = {vehicle_id: index for index, vehicle_id in enumerate(self.vehicle_ids)}
        step_s = self.step_s
        for event in self.events:
            index = None if event.vehicle is None else index_of[event.vehicle]
            at_s = start_s + event.step(step_s) * step_s
            emulator_at_s = at_s - self.time_offset_s
            # A window ends half a step before the first step it no longer covers, so that it
            # covers the same steps in flight as in simulate whatever the rounding of the sample
            # times.
            steps = event.duration_steps(step_s)
            window_s = None if steps is None else (steps - 0.5) * step_s
            if event.kind == "target_hidden":
                self.hide_target(at_s, window_s, index)
            elif index is None:  # validation gives every other event its vehicle
                raise MissionRunnerError(f"event {event.kind} names no vehicle")
            elif event.kind == "vehicle_lost":
                self.emulator.kill_vehicle(index, at_s=emulator_at_s)
            elif event.kind == "link_lost":
                self.emulator.drop_link(
                    index, "all", at_s=emulator_at_s, duration_s=event.duration_s
                )
            elif event.kind == "taken_over":
                self.emulator.take_over(
                    index, event.mode, at_s=emulator_at_s, rearm_after_s=event.rearm_after_s
                )
            elif event.kind == "sensor_lost" and event.sensor == "flow":
                self.emulator.fail_sensor(
                    index, "flow", at_s=emulator_at_s, duration_s=event.duration_s
                )
            elif event.kind == "sensor_lost" and event.sensor is not None:
                self.fail_sensor(index, event.sensor, at_s=at_s, duration_s=window_s)
            else:
                raise MissionRunnerError(
                    f"event {event.kind} cannot be flown (simulate it instead)"
                )

    def fail_sensor(
        self, index: int, sensor: str, at_s: float, duration_s: float | None = None
    ) -> None:
        """Vehicle ``index``'s ``"uwb"`` (no ranges from or to it) or ``"tracker"`` (no target
        observations) stops at ``at_s`` for ``duration_s`` seconds (default: for good)."""
        if sensor not in ("uwb", "tracker"):
            raise ValueError(f"unknown world sensor {sensor!r}; use 'uwb' or 'tracker'")
        self._add_window(index, sensor, at_s, duration_s)

    def hide_target(
        self, at_s: float, duration_s: float | None = None, index: int | None = None
    ) -> None:
        """The target is hidden from vehicle ``index``'s tracker (default: from every tracker)
        from ``at_s`` for ``duration_s`` seconds (default: for good); the trackers report it
        not seen."""
        self._add_window(index, "tracker", at_s, duration_s)

    def _add_window(
        self, index: int | None, sensor: str, at_s: float, duration_s: float | None
    ) -> None:
        until_s = math.inf if duration_s is None else at_s + duration_s
        self._down.setdefault((index, sensor), []).append((at_s, until_s))

    def target_position(self, time_s: float) -> NDArray[np.float64]:
        """The target's true ``[north, east]`` at mission time ``time_s``."""
        elapsed = 0.0 if self.start_s is None else max(0.0, time_s - self.start_s)
        return target_positions(self.target_path, np.array([elapsed]))[0]

    def target_velocity(self, time_s: float, delta_s: float = 1e-3) -> NDArray[np.float64]:
        if self.start_s is None or time_s < self.start_s:
            return np.zeros(2)
        return (self.target_position(time_s + delta_s) - self.target_position(time_s)) / delta_s

    def _working(self, index: int, sensor: str, time_s: float) -> bool:
        windows = self._down.get((index, sensor), []) + self._down.get((None, sensor), [])
        return not any(start <= time_s < until for start, until in windows)

    def _on_step(self, time_s: float, truth: Truth) -> None:
        if self.start_s is None or (self._steps is not None and self._next_step >= self._steps):
            return
        time_s += self.time_offset_s
        half_dt = 0.5 * self.emulator.dt_s
        t_k = self.start_s + self._next_step * self.step_s
        if time_s < t_k - half_dt:
            return
        self._sample(self._next_step, t_k, truth)
        self._next_step += 1

    def _sample(self, k: int, t_k: float, truth: Truth) -> None:
        position = np.array(truth.position_ned_m, dtype=float)
        alive = np.array(truth.alive)
        count = len(self.vehicle_ids)
        target = self.target_position(t_k)
        self.samples.append(TruthSample(k, t_k, target.copy(), position[:, :2].copy(), alive))
        measured = step_measurements(
            k,
            t_k,
            ids=self.vehicle_ids,
            topics=self.topics,
            positions_m=position,
            ranging=alive & [self._working(i, "uwb", t_k) for i in range(count)],
            tracking=self.senses_target & alive,
            target_hidden=[not self._working(i, "tracker", t_k) for i in range(count)],
            target_m=target,
            target_velocity_m_s=self.target_velocity(t_k),
            sensors=self.sensors,
            rng=self._rng,
            uwb=self._uwb,
            graph=None if self.ranging is None else self.ranging.among(alive),
        )
        self._queue.put_nowait((k, measured))
        self.emulator.end_batch()  # this step's measurements go out before the next is sampled

    async def _publish(self) -> None:
        """Hand each step's measurements to the bus as soon as they are sampled, without waiting
        for the bus to acknowledge the step before: one slow acknowledgement (a broker starved
        for a step on a loaded machine) held the next step back with it, so every later step
        went out late too, past the vehicles' deadlines. Each step waits for its own
        acknowledgements (for at most ``stale_after_steps`` steps) in a task of its own."""
        async with asyncio.TaskGroup() as group:
            while not self._closing:
                k, measured = await self._queue.get()
                stale = self.stale_after_steps
                if stale is not None and self._next_step - k > stale:
                    self._queue.task_done()
                    continue  # the bus was down: a stale measurement is worse than none
                # Tasks start in the order they were made: a step's messages are handed over
                # before the next step's (the bus seals and queues before its first await).
                group.create_task(self._publish_step(measured), name=f"world-step-{k}")

    async def _publish_step(self, measured: Measured) -> None:
        try:
            steps = self.stale_after_steps or 1
            errors = await publish_measurements(self.bus, measured, timeout_s=steps * self.step_s)
        finally:
            self._queue.task_done()
        for (topic, _), error in zip(measured, errors, strict=True):
            if error is None:
                self.published += 1
                if self._dropping:
                    logger.info("world: publishing again (%d dropped)", self._dropping)
                    self._dropping = 0
                continue
            # Once per outage: a warning per message (several a step) filled
            # a pipe nobody read and stopped the emulator with it.
            if not self._dropping:
                logger.warning("world: could not publish %s: %s (dropping)", topic, error)
            self._dropping += 1
            self.dropped += 1


async def publish_measurements(
    bus: Bus | BusClient, measured: Measured, *, timeout_s: float
) -> list[BusError | None]:
    """Publish one step's measurements all at once; per message, the error that dropped it
    (None: handed to the bus). One after the other, each waited for the event loop to write the
    one before: the last (the target observation, then last) came ~10 ms after the first on an
    idle machine and 35-65 ms on a loaded one, past the step's deadline."""

    async def publish(topic: str, message: RangeSet | TargetObservation) -> BusError | None:
        try:
            await bus.publish_message(topic, message, timeout=timeout_s)
        except BusError as error:
            return error
        return None

    return list(await asyncio.gather(*(publish(topic, message) for topic, message in measured)))


def step_measurements(
    k: int,
    t_k: float,
    *,
    ids: Sequence[int],
    topics: Topics,
    positions_m: ArrayLike,
    ranging: ArrayLike,
    tracking: ArrayLike,
    target_m: ArrayLike,
    target_velocity_m_s: ArrayLike,
    sensors: SensorConfig,
    rng: Rng,
    uwb: UwbRanging,
    target_hidden: ArrayLike | None = None,
    graph: Adjacency | None = None,
) -> Measured:
    """What the UWB radios and target trackers report for step ``k`` (time ``t_k``), as
    ``(topic, message)`` pairs: a :class:`TargetObservation` per tracking vehicle (the target's
    horizontal range and velocity where its tracker sees it, "not seen" where not), then a
    :class:`RangeSet` per vehicle whose radio works (``ranging``), of the ranges it read: empty
    when every one dropped out or the airtime schedule gave it no exchange this step, so that its
    controller knows no range of step k is coming (a vehicle whose radio is down sends nothing).
    Observations first: a sensing vehicle's step message waits for its own, and its neighbours'
    steps for that message, the longest chain of a step.

    positions_m: ``(n, 3)`` true NED positions [m] (NaN rows: unknown); ranging ``(n,)`` bool:
    radios that work; tracking ``(n,)`` bool: vehicles with a tracker that reports;
    target_hidden ``(n,)`` bool: trackers the target is hidden from (occluded, failed); target_m
    ``(2,)``, target_velocity_m_s ``(2,)`` north/east; sensors: the scenario's ``SensorConfig``
    (its sensing range and misses apply here, :func:`mission_runner.sensors.target_seen`);
    uwb: the mission's radios (:class:`mission_runner.sensors.UwbRanging`, stepped to ``k``).
    graph: ``(n, n)`` bool, the pairs scheduled to range this step (a sparse neighbourhood
    graph among the live vehicles, :class:`mission_runner.wiring.RangingGraph`); None: every
    pair. The noise is drawn for every pair either way (the complete graph's draws unchanged).
    """
    positions_m = np.asarray(positions_m, dtype=float)
    # Ranges first: the radios draw from ``rng`` before the trackers do.
    range_sets = _range_sets(
        k,
        t_k,
        ids=ids,
        topics=topics,
        positions_m=positions_m,
        ranging=ranging,
        rng=rng,
        uwb=uwb,
        graph=graph,
    )
    observations = _target_observations(
        t_k,
        ids=ids,
        topics=topics,
        positions_m=positions_m,
        tracking=tracking,
        target_m=target_m,
        target_velocity_m_s=target_velocity_m_s,
        sensors=sensors,
        rng=rng,
        target_hidden=target_hidden,
    )
    return observations + range_sets


def _range_sets(
    k: int,
    t_k: float,
    *,
    ids: Sequence[int],
    topics: Topics,
    positions_m: NDArray[np.float64],
    ranging: ArrayLike,
    rng: Rng,
    uwb: UwbRanging,
    graph: Adjacency | None,
) -> Measured:
    """A :class:`RangeSet` per vehicle whose radio works or that read a range (see
    :func:`step_measurements`)."""
    ranging = np.asarray(ranging, dtype=bool)
    gaps = positions_m[:, None, :] - positions_m[None, :, :]
    distances = np.sqrt(np.sum(gaps * gaps, axis=-1))
    linked = ranging[:, None] & ranging[None, :]
    if graph is not None:  # a radio ranges only with the neighbours it is scheduled with
        linked &= graph
    ranges = uwb.read(distances, rng, k=k, measured=linked)
    read = np.isfinite(ranges)
    return [
        (
            topics.ranges(ids[i]),
            RangeSet(
                ids[i],
                t_k,
                tuple((ids[j], float(ranges[i, j])) for j in np.flatnonzero(read[i]).tolist()),
                step=k,
            ),
        )
        for i in range(len(ids))
        if ranging[i] or read[i].any()
    ]


def _target_observations(
    t_k: float,
    *,
    ids: Sequence[int],
    topics: Topics,
    positions_m: NDArray[np.float64],
    tracking: ArrayLike,
    target_m: ArrayLike,
    target_velocity_m_s: ArrayLike,
    sensors: SensorConfig,
    rng: Rng,
    target_hidden: ArrayLike | None,
) -> Measured:
    """A :class:`TargetObservation` per tracking vehicle: the target's horizontal range and
    velocity where its tracker sees it, "not seen" where not (see :func:`step_measurements`)."""
    tracking = np.asarray(tracking, dtype=bool)
    hidden = np.zeros_like(tracking) if target_hidden is None else np.asarray(target_hidden, bool)
    sensing = np.flatnonzero(tracking)
    target_2d = np.asarray(target_m, dtype=float)[:2]
    horizontal = measure_ranges(positions_m[sensing, :2], sensors, rng, to_m=target_2d[None])[:, 0]
    gap = positions_m[sensing, :2] - target_2d
    seen = target_seen(
        np.sqrt(np.sum(gap * gap, axis=-1)), sensors, rng, looking=~hidden[sensing]
    ) & np.isfinite(horizontal)
    north_m_s, east_m_s = (float(v) for v in np.asarray(target_velocity_m_s, dtype=float))
    return [
        (
            topics.target(ids[i]),
            TargetObservation(ids[i], t_k, float(r), north_m_s, east_m_s)
            if visible
            else TargetObservation.not_seen(ids[i], t_k),
        )
        for i, r, visible in zip(sensing.tolist(), horizontal, seen.tolist(), strict=True)
    ]
