"""One vehicle's offboard controller: the enclosing law on a real (or emulated) vehicle.

The controller owns nothing but its loop; the vehicle link, the bus and the clock are injected, so
unit tests run it against fakes and scenario tests against the emulator through MAVSDK.

Each step k (t_k = start + kT on the mission clock):

1. wait for t_k; sample the own odometry at exactly t_k (interpolated between telemetry samples);
   if this vehicle has a tracker, take its step-k observation (seen, or an explicit "not seen")
   and integrate the target's observed velocity into its odometry;
2. publish the step message (phase theta_i(k), odometry, and the freshest target observation it
   knows of: its own, or the one relayed to it; with ``algorithm.shared_ranges`` its own step-k
   ranges too, awaited until half the step's deadline);
3. wait until every member's step-k message and this vehicle's step-k ranges are in, or the step
   deadline passes; a neighbour that is late or lost drops out of this step only;
4. track the target from the freshest observation heard (:mod:`mission_runner.enclosing.target`:
   observed, predicted at constant velocity, or lost after ``target_lost_after_s``);
5. run the law (:class:`mission_runner.enclosing.VehicleEnclosing`), clamp the velocity to the
   vehicle's limits, add the altitude-hold term and send the setpoint; with the target lost,
   hold (or orbit its last estimate: ``target_on_lost``) in state ``target_lost``.

Ranges and target observations that cannot be (:mod:`.plausibility`) are dropped and counted
where they come in, before the inbox and the estimator see them.

It uses only its own measurements and its neighbours' messages, never ground truth. If nothing
fresh is heard from any neighbour for ``silence_timeout_s``, or its own odometry stops, it stops
following the law and holds (zero velocity), resuming when data is fresh again.
"""

import asyncio
import contextlib
import dataclasses
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..bus import (
    BusError,
    Message,
    RangeSet,
    StepMessage,
    TargetObservation,
    Topics,
    VehicleStatus,
    shared_range,
)
from ..config import Scenario, VehicleConfig
from ..enclosing import (
    LOST,
    NeighbourReport,
    TargetEstimate,
    TargetReport,
    TargetTrack,
    VehicleCommand,
    VehicleEnclosing,
    track_target,
)
from ..enclosing.control import saturate
from ..enclosing.separation import separation_guard
from ..enclosing.target import STATUS_NAMES
from ..records import STALE_STATES, ControllerState, StepRecord
from ..scenario import ShapeSchedule, omega_of, shape_schedule
from ..tasks import first_completed
from ..wiring import (
    algorithm_params,
    altitude_of,
)
from .inbox import StepData, StepInbox
from .odometry import ODOMETRY_PERIOD_S
from .plausibility import CommandGate, RangeGate, RangeLimits, range_limits
from .ports import ControllerBus, ControllerClock, ControllerLink, MessageSource

logger = logging.getLogger(__name__)

#: A controller's status goes out when what it says changes (its state or detail), else at the
#: steps that are multiples of this period [mission s] (every 8th at T = 0.125 s, so on the
#: step grid the ground's progress shows): enough for the ground's progress and its watch of a
#: vehicle's will (final after 11 s without a status), an eighth of the step messages' rate.
STATUS_PERIOD_S = 1.0


@dataclass(frozen=True)
class ControllerSettings:
    """Timing and limits of one controller.

    step_deadline_s: how long after t_k (mission clock) the step's inputs are awaited before the
    law runs without the missing ones. wall_deadline_s: the same in wall seconds, for lockstep
    runs whose mission clock stands still while controllers wait. release_s: in lockstep, how far
    past t_k the world may run while the controller samples (more than one odometry period).
    odometry_extrapolate_s: in real time, how far past its newest odometry sample t_k is taken
    at that sample's velocity rather than waiting for the next (two periods: PX4 sends fewer
    than asked; lockstep waits:
    the world is there in an instant and results stay exact).
    target_lost_after_s: the longest the target is predicted without an observation [s];
    target_on_lost: then ``hold`` (hover) or ``orbit`` (the law around the last estimate).
    """

    step_s: float
    step_deadline_s: float
    wall_deadline_s: float
    target_lost_after_s: float
    target_on_lost: str
    silence_timeout_s: float
    member_timeout_steps: int
    max_horizontal_speed_m_s: float
    max_vertical_speed_m_s: float
    velocity_lead_s: float
    tracking_gain_1_s: float
    tracking_integral_gain_1_s2: float
    tracking_max_correction_m_s: float
    min_separation_m: float | None
    separation_gain_1_s: float
    separation_margin_m: float | None
    separation_braking_m_s2: float | None
    separation_latency_s: float
    separation_range_noise_std_m: float
    range_limits: RangeLimits | None
    #: The fastest any vehicle of the mission may fly [m/s]: a neighbour's step message saying
    #: it flies faster loses its command (None: every command is taken as it comes).
    fleet_speed_limit_m_s: float | None
    # The controller's own tunings, which the scenario has no setting for (every other field
    # comes from the scenario: wiring.controller_settings, defaults in the config model).
    release_s: float = 1.25 * ODOMETRY_PERIOD_S
    odometry_extrapolate_s: float = 2.0 * ODOMETRY_PERIOD_S
    odometry_timeout_s: float = 1.0
    lost_after_missed_steps: int = 3
    altitude_gain_per_s: float = 1.0


def controller_settings(scenario: Scenario, vehicle: VehicleConfig) -> ControllerSettings:
    """The :class:`ControllerSettings` of ``vehicle`` (a scenario vehicle entry)."""
    flight = scenario.flight
    return ControllerSettings(
        step_s=scenario.timing.step_s,
        step_deadline_s=flight.step_deadline_s,
        wall_deadline_s=flight.lockstep_wait_s,
        silence_timeout_s=flight.silence_timeout_s,
        member_timeout_steps=flight.member_timeout_steps,
        max_horizontal_speed_m_s=vehicle.speed_limit_m_s,
        max_vertical_speed_m_s=flight.max_vertical_speed_m_s,
        velocity_lead_s=flight.velocity_lead_s,
        tracking_gain_1_s=flight.displacement_tracking.gain_1_s,
        tracking_integral_gain_1_s2=flight.displacement_tracking.integral_gain_1_s2,
        tracking_max_correction_m_s=flight.displacement_tracking.max_correction_m_s,
        min_separation_m=scenario.safety.min_separation_m,
        separation_gain_1_s=scenario.safety.separation_gain_1_s,
        separation_margin_m=scenario.safety.separation_margin_m,
        separation_braking_m_s2=scenario.safety.separation_braking_m_s2,
        separation_latency_s=scenario.safety.separation_latency_s,
        separation_range_noise_std_m=scenario.sensors.range_noise_std_m,
        range_limits=range_limits(scenario),
        fleet_speed_limit_m_s=max(v.speed_limit_m_s for v in scenario.vehicles),
        target_lost_after_s=scenario.algorithm.target_lost_after_s,
        target_on_lost=scenario.algorithm.target_on_lost,
    )


class VehicleController:
    """The enclosing loop of vehicle ``vehicle_id``.

    law: its :class:`VehicleEnclosing`. link: the vehicle (:class:`.ports.ControllerLink`, e.g.
    :class:`.links.MavsdkVehicle`). bus + topics: the message bus. clock: the mission clock
    (:class:`.ports.ControllerClock`). shape(k): the affine shape matrix ``(3, 3)`` at step k.
    altitude_m: the altitude this vehicle holds (up, metres above home). on_step(vehicle_id,
    record) sees every step's record.
    """

    def __init__(
        self,
        *,
        vehicle_id: int,
        vehicle_ids: Iterable[int],
        law: VehicleEnclosing,
        senses_target: bool,
        link: ControllerLink,
        bus: ControllerBus,
        topics: Topics,
        clock: ControllerClock,
        settings: ControllerSettings,
        shape: Callable[[int], NDArray[np.float64]],
        altitude_m: float,
        on_step: Callable[[int, StepRecord], None] | None = None,
    ) -> None:
        self.vehicle_id = vehicle_id
        self.law = law
        self.senses_target = senses_target
        self.link = link
        self.bus = bus
        self.topics = topics
        self.clock = clock
        self.settings = settings
        self.shape = shape
        self.altitude_m = altitude_m
        self.on_step = on_step
        self.state = ControllerState.WAITING
        self.start_s: float | None = None
        self.inbox = StepInbox(
            vehicle_id,
            vehicle_ids,
            senses_target=senses_target,
            step_of=self._step_of,
            member_timeout_steps=settings.member_timeout_steps,
        )
        self._target_odometry = np.zeros(2)  # own observations only, integrated
        self._last_target: tuple[float, NDArray[np.float64]] | None = None
        self.target_track = TargetTrack.initial()
        self._last_fresh_s = -math.inf  # nothing heard yet; run() starts the silence at k = 0
        self._previous_command: NDArray[np.float64] | None = None
        # Where the law's commands so far would have taken the vehicle.
        self._reference: NDArray[np.float64] | None = None
        self._tracking_integral = np.zeros(2)
        #: The horizontal setpoint this vehicle flies (the last one sent by the law's steps;
        #: None before the first): its step messages carry it for the neighbours' guards.
        self.command_in_force: tuple[float, float] | None = None
        #: The operator's hold (ground station ``hold`` until ``resume``): hover in place, keep
        #: the oscillator on the grid, publish nothing of the law.
        self.operator_hold = False
        #: The last step whose command was chosen (where ``operator_hold`` is read): a change
        #: of the hold is first seen by the step after it.
        self.decided_step = -1
        self._missed_odometry = 0
        self.skipped_steps = 0
        #: None: every range is taken as it comes (a unit test's fake sensors).
        self.range_gate = (
            RangeGate(settings.range_limits, vehicle_id)
            if settings.range_limits is not None
            else None
        )
        self.command_gate = (
            CommandGate(settings.fleet_speed_limit_m_s, vehicle_id)
            if settings.fleet_speed_limit_m_s is not None
            else None
        )
        self.mission_id: str | None = None  # carried by every status (vehicle processes set it)
        #: Its autopilot's recent boot-clock rate, carried by every status so the ground's mission
        #: clock can follow it (vehicle processes set it; None: its clock is the mission's).
        self.autopilot_clock_rate: Callable[[], float] | None = None
        self.records: list[StepRecord] = []
        self._stale_count = (0, 0)  # (records counted, of them held or skipped)
        self._status_said: tuple[str, str] | None = None  # the last status's (state, detail)
        self._status_period_steps = max(1, round(STATUS_PERIOD_S / settings.step_s))

    @property
    def stale_steps(self) -> int:
        """Steps held or skipped so far for want of fresh data (:data:`STALE_STATES`); every
        status carries it, so the ground's verdict sees what a flood or a dropout cost."""
        counted, count = self._stale_count
        count += sum(record.state in STALE_STATES for record in self.records[counted:])
        self._stale_count = (len(self.records), count)
        return count

    def _step_of(self, time_s: float) -> int | None:
        if self.start_s is None:
            return None
        k = round((time_s - self.start_s) / self.settings.step_s)
        t_k = self.start_s + k * self.settings.step_s
        return k if k >= 0 and abs(time_s - t_k) <= self.settings.step_s / 4 else None

    async def hover_until(self, start: asyncio.Future[float]) -> float:
        """Hold altitude with zero horizontal velocity on the step grid until the mission's
        k = 0 (``start``: a future of the start time). Streams setpoints, so OFFBOARD may be
        entered meanwhile, and releases the clock step by step (lockstep)."""
        step_s = self.settings.step_s
        t = math.ceil(self.clock.now_s() / step_s) * step_s
        self.state = ControllerState.HOVERING
        while not (start.done() and t >= start.result()):
            self.clock.release(t + self.settings.release_s)
            await self.clock.sleep_until(t)
            if self.link.control_lost is None:  # never stream to a vehicle someone else flies
                sample = self.link.odometry.latest
                vertical = self._altitude_hold(
                    None if sample is None else (sample.north_m, sample.east_m, sample.down_m)
                )
                await self.link.set_velocity_ned(0.0, 0.0, vertical)
            t += step_s
        return start.result()

    async def run(self, start_s: float, steps: int) -> list[StepRecord]:
        """Fly ``steps`` steps starting at mission time ``start_s``. Returns the records."""
        self.start_s = start_s
        self._last_fresh_s = start_s
        # The other members' step topics, not the wildcard: the own messages would come back
        # (a quarter of what a vehicle of four receives, each authenticated and decoded to be
        # ignored), and so would any stranger's.
        wanted: list[tuple[str, type[Message]]] = [
            *((self.topics.step(peer), StepMessage) for peer in self.inbox.others),
            (self.topics.ranges(self.vehicle_id), RangeSet),
            (self.topics.target(self.vehicle_id), TargetObservation),
        ]
        async with contextlib.AsyncExitStack() as stack:
            subscriptions = [
                (await stack.enter_async_context(self.bus.subscribe(topic)), message_type)
                for topic, message_type in wanted
            ]
            # The inbox pump runs for ever; the step loop's end (or either's failure) ends both.
            await first_completed(
                {
                    f"vehicle-{self.vehicle_id}-inbox": self._pump(subscriptions),
                    f"vehicle-{self.vehicle_id}-steps": self._steps(start_s, steps),
                }
            )
        return self.records

    async def _steps(self, start_s: float, steps: int) -> None:
        for k in range(steps):
            if self.link.control_lost is not None:
                # A pilot, another ground station or a failsafe has the vehicle: it is no longer
                # driven (no setpoint, no step message: the others re-balance without it), and
                # the runner does not take it back.
                self.state = ControllerState.TAKEN_OVER
                logger.warning(
                    "vehicle %s: taken over at step %d: %s",
                    self.vehicle_id,
                    k,
                    self.link.control_lost,
                )
                await self._publish_status(k, start_s + k * self.settings.step_s)
                return
            await self._step(k, start_s + k * self.settings.step_s)
            if self._missed_odometry >= self.settings.lost_after_missed_steps:
                # Dead vehicle or dead link: stop driving it; PX4's offboard-loss failsafe holds
                # or lands it, and the others re-balance without it.
                self.state = ControllerState.LOST
                logger.warning("vehicle %s: lost at step %d", self.vehicle_id, k)
                await self._publish_status(k, start_s + k * self.settings.step_s)
                return

    async def _pump(self, subscriptions: Sequence[tuple[MessageSource, type[Message]]]) -> None:
        """Feed the inbox from the bus subscriptions (decode errors are dropped, not fatal)."""
        handlers: dict[type[Message], Callable[[Any], None]] = {
            StepMessage: self._add_step,
            RangeSet: self._add_ranges,
            TargetObservation: self._add_target,
        }

        async def drain(subscription: MessageSource, message_type: type[Message]) -> None:
            async for _, message in subscription.messages(message_type):
                handlers[message_type](message)

        async with asyncio.TaskGroup() as group:
            for n, (subscription, message_type) in enumerate(subscriptions):
                group.create_task(
                    drain(subscription, message_type),
                    name=f"vehicle-{self.vehicle_id}-{message_type.__name__}-{n}",
                )

    def _possible(self, vehicle_id: int, peer_id: int, range_m: float, time_s: float) -> bool:
        """Whether a range may go on to the inbox (which ignores other vehicles' anyway)."""
        gate = self.range_gate
        if gate is None or vehicle_id != self.vehicle_id:
            return True
        return gate.accept(peer_id, range_m, time_s)

    def _add_step(self, message: StepMessage) -> None:
        gate = self.command_gate
        self.inbox.add_step(message if gate is None else gate.checked(message))

    def _add_ranges(self, message: RangeSet) -> None:
        """The set goes on with its impossible ranges dropped (counted by the gate): what is left,
        even nothing, is still this step's whole round."""
        gate, time_s = self.range_gate, message.time_s
        if gate is not None and message.vehicle_id == self.vehicle_id:
            kept = tuple((p, r) for p, r in message.ranges_m if gate.accept(p, r, time_s))
            if len(kept) != len(message.ranges_m):
                message = dataclasses.replace(message, ranges_m=kept)
        self.inbox.add_ranges(message)

    def _add_target(self, observation: TargetObservation) -> None:
        seen_range_m = observation.range_m
        if seen_range_m is None or self._possible(
            observation.vehicle_id, 0, seen_range_m, observation.time_s
        ):
            self.inbox.add_target(observation)

    async def _step(self, k: int, t_k: float) -> None:
        settings = self.settings
        if not self.clock.lockstep and self.clock.now_s() >= t_k + settings.step_s:
            # Step k's instant is a whole step in the past (a stall, a slow machine): its
            # inputs are stale and a command for it would be late. Skip it, keeping the
            # oscillator on the grid, so the controller is back on the current step at once
            # instead of falling further behind every step.
            self._skip(k, t_k)
            return
        self.clock.release(t_k + settings.release_s)
        await self.clock.sleep_until(t_k)
        odometry = await self._odometry_at(t_k)
        odometry_ready_s = self.clock.now_s()
        message_sent_s = math.nan
        phase = self.law.phase_rad
        observation = None
        if odometry is not None:
            self._missed_odometry = 0
            # The target observation (and, to share, the ranges) of step k are usually in by
            # now; wait briefly if not. An observation that says "not seen" is as good as one
            # that saw: nothing more is coming.
            observation, shared = await self._own_measurements(k, t_k)
            in_force = self.command_in_force
            if observation is not None and not observation.seen:
                observation = None
            message = self._with_target(
                StepMessage(
                    self.vehicle_id,
                    k,
                    t_k,
                    phase,
                    odometry[0],
                    odometry[1],
                    odometry_down_m=float(odometry[2]),
                    ranges_m=shared,
                    command_north_m_s=None if in_force is None else in_force[0],
                    command_east_m_s=None if in_force is None else in_force[1],
                ),
                observation,
            )
            await self._publish(self.topics.step(self.vehicle_id), message)
            message_sent_s = self.clock.now_s()
        else:
            self._missed_odometry += 1
        await self._wait_inputs(k, t_k)
        inputs_ready_s = self.clock.now_s()
        data = self.inbox.take(k)
        target = self._track_target(k, data, observation)
        now = self.clock.now_s()
        if data.neighbours:
            self._last_fresh_s = now
        used: tuple[int, ...]
        gated: tuple[int, ...] = ()
        estimates: dict[int, NDArray[np.float64]]
        consensus: tuple[float, float]
        # Hold on stale data, and while the vehicle is not seen armed in OFFBOARD.
        stale_s = now - self._last_fresh_s
        holding = stale_s > settings.silence_timeout_s or not self.link.in_control
        self.decided_step = k
        target_lost = int(target.status) == LOST
        hold_for_target = target_lost and settings.target_on_lost == "hold"
        if odometry is None or holding or self.operator_hold or hold_for_target:
            velocity = (0.0, 0.0)
            if self.operator_hold and not holding:
                self.state = ControllerState.HELD
            elif odometry is None or holding:
                self.state = ControllerState.HOLDING
            else:
                self.state = ControllerState.TARGET_LOST
            # The vehicle holds: when it resumes, track afresh from where it is, and lead from
            # nothing (a command change over the whole hold is not a rate to lead).
            self._reference = None
            self._previous_command = None
            self._tracking_integral = np.zeros(2)
            used, estimates, consensus, ranges = (), {}, (0.0, 0.0), {}
            self._turn_oscillator(k)
        else:
            self.state = ControllerState.TARGET_LOST if target_lost else ControllerState.FOLLOWING
            ranges = self._horizontal_ranges(data, odometry)
            command = self.law.step(
                own_odometry_m=odometry[:2],
                neighbours={
                    peer: NeighbourReport(m.phase_rad, (m.odometry_north_m, m.odometry_east_m))
                    for peer, m in data.neighbours.items()
                },
                ranges_m=ranges,
                target=TargetReport(
                    (float(target.odometry_m[0]), float(target.odometry_m[1])),
                    (float(target.velocity_m_s[0]), float(target.velocity_m_s[1])),
                ),
                members=data.members,
                shape_now=self.shape(k),
                shape_next=self.shape(k + 1),
                peer_ranges_m=self._peer_ranges(data, odometry) if self._sharing else None,
            )
            wanted = self._lead(command.velocity_m_s) + self._tracking(
                command.velocity_m_s, odometry
            )
            if settings.min_separation_m is not None:
                wanted = self._separated(wanted, command, data, ranges)
            velocity = self._clamp(wanted)
            used, estimates, gated = command.neighbours_used, command.estimates_m, command.gated
            consensus = (float(command.consensus_m_s[0]), float(command.consensus_m_s[1]))
        vertical = self._altitude_hold(odometry)
        if self.link.control_lost is None:  # taken over during the step: never stream to it
            async with self.clock.commanding(t_k + settings.release_s):
                await self.link.set_velocity_ned(velocity[0], velocity[1], vertical)
        self.command_in_force = velocity
        sent_s = self.clock.now_s()
        record = StepRecord(
            step=k,
            time_s=t_k,
            state=self.state,
            velocity_ned_m_s=(*velocity, vertical),
            consensus_m_s=consensus,
            phase_rad=phase,
            neighbours_used=used,
            estimates_m=estimates,
            setpoint_sent_s=sent_s,
            odometry_m=(math.nan, math.nan, math.nan) if odometry is None else odometry,
            gated=gated,
            ranges_m=ranges,
            target=STATUS_NAMES[int(target.status)],
            odometry_ready_s=odometry_ready_s if odometry is not None else math.nan,
            message_sent_s=message_sent_s,
            inputs_ready_s=inputs_ready_s,
        )
        self.records.append(record)
        await self._publish_status(k, t_k)
        if self.on_step is not None:
            self.on_step(self.vehicle_id, record)

    def _separated(
        self,
        velocity: NDArray[np.float64],
        command: VehicleCommand,
        data: StepData,
        ranges: dict[int, float],
    ) -> NDArray[np.float64]:
        """The command through the separation guard: directions from this step's estimates,
        distances from the measured (horizontal) ranges, the pair's motion from the setpoints in
        force (the own, and the neighbours' from their step messages; never truth)."""
        estimates_m, bearing_std = command.estimates_m, command.bearing_std_rad
        peers = [peer for peer in estimates_m if peer != 0]
        if not peers:
            return velocity

        def in_force(peer: int) -> tuple[float, float]:
            message = data.neighbours.get(peer)
            command = None if message is None else message.command_m_s
            return (math.nan, math.nan) if command is None else command

        settings = self.settings
        return separation_guard(
            np.asarray(velocity, dtype=float),
            np.array([estimates_m[peer] for peer in peers], dtype=float),
            np.array([ranges.get(peer, math.nan) for peer in peers], dtype=float),
            np.array(self.command_in_force or (math.nan, math.nan), dtype=float),
            np.array([in_force(peer) for peer in peers], dtype=float),
            min_separation_m=settings.min_separation_m or 0.0,
            gain_1_s=settings.separation_gain_1_s,
            step_s=settings.step_s,
            margin_m=settings.separation_margin_m,
            braking_m_s2=settings.separation_braking_m_s2,
            latency_s=settings.separation_latency_s,
            range_noise_std_m=settings.separation_range_noise_std_m,
            bearing_std_rad=np.array([bearing_std.get(peer, math.nan) for peer in peers]),
        )

    def _turn_oscillator(self, k: int) -> None:
        """Advance the law through step k with no data: the oscillator keeps turning so the
        phase stays on the grid (and meaningful when data returns); no estimate changes."""
        self.law.step(
            own_odometry_m=(math.nan, math.nan),
            neighbours={},
            ranges_m={},
            target=None,
            members=[self.vehicle_id],
            shape_now=self.shape(k),
            shape_next=self.shape(k + 1),
        )

    def _skip(self, k: int, t_k: float) -> None:
        phase = self.law.phase_rad
        self._turn_oscillator(k)
        self.inbox.take(k)
        self._reference = None
        self.skipped_steps += 1
        logger.warning(
            "vehicle %s: step %d skipped (%.3f s late)",
            self.vehicle_id,
            k,
            self.clock.now_s() - t_k,
        )
        record = StepRecord(
            step=k,
            time_s=t_k,
            state=ControllerState.SKIPPED,
            velocity_ned_m_s=(0.0, 0.0, 0.0),
            consensus_m_s=(0.0, 0.0),
            phase_rad=phase,
            neighbours_used=(),
            estimates_m={},
        )
        self.records.append(record)
        if self.on_step is not None:
            self.on_step(self.vehicle_id, record)

    async def _odometry_at(self, t_k: float) -> tuple[float, float, float] | None:
        """Own odometry (north, east, down) at t_k, or None if telemetry stopped."""
        track = self.link.odometry
        ahead_s = 0.0 if self.clock.lockstep else self.settings.odometry_extrapolate_s
        try:
            async with asyncio.timeout(self.settings.odometry_timeout_s):
                while (sample := track.at(t_k, extrapolate_s=ahead_s)) is None:
                    await self.link.odometry_updated()
        except TimeoutError:
            logger.warning("vehicle %s: no odometry around t=%.3f s", self.vehicle_id, t_k)
            return None
        return sample

    @property
    def _sharing(self) -> bool:
        """Whether step messages carry ranges both ways (``algorithm.shared_ranges``)."""
        return self.law.params.shared_ranges

    async def _own_measurements(
        self, k: int, t_k: float
    ) -> tuple[TargetObservation | None, tuple[tuple[int, float], ...] | None]:
        """What this vehicle's step message relays of its own step-k measurements: the target
        observation (if it senses the target) and, when sharing, its ranges to the other vehicles
        (as :func:`.bus.shared_range` rounds them). Awaited no longer than the step's own
        deadline: what never comes must not cost more than the step has; when sharing, no longer
        than half of it, since a dropped range never comes and the neighbours stop waiting for
        this message at the deadline (measured: waiting the whole deadline, a flight with 2 %
        dropouts lost neighbours' messages, and the phases never settled). Ranges that come later
        are still the law's, only not shared."""
        if not (self.senses_target or self._sharing):
            return None, None

        def in_() -> bool:
            target = not self.senses_target or self.inbox.pending_target(k) is not None
            return target and (not self._sharing or self.inbox.own_ranges_in(k))

        await self.inbox.wait_for(in_, self._wait_s(t_k) / (2.0 if self._sharing else 1.0))
        shared = None
        if self._sharing:
            ranges = self.inbox.pending_ranges(k)
            shared = tuple(
                (peer, shared_range(ranges[peer])) for peer in sorted(ranges) if peer != 0
            )
        return self.inbox.pending_target(k), shared

    def _wait_s(self, t_k: float) -> float:
        """Wall seconds left until step k's deadline (in lockstep, where the mission clock
        stands still while controllers wait, a fixed wall-clock bound)."""
        if self.clock.lockstep:
            return self.settings.wall_deadline_s
        remaining = t_k + self.settings.step_deadline_s - self.clock.now_s()
        return max(remaining, 0.0) / self.clock.rate

    def _with_target(
        self, message: StepMessage, observation: TargetObservation | None
    ) -> StepMessage:
        """Relay the target: this vehicle's own observation of step k (its velocity integrated
        into the target's odometry, trapezoid over the time since the previous observation, so
        a gap in observations is bridged, not lost), else the freshest observation its track
        holds (made at an earlier step, by itself or relayed to it), else nothing."""
        odometry: tuple[float | None, float | None] = (None, None)
        observed_step: int | None = None
        if observation is not None:
            velocity = np.array([observation.velocity_north_m_s, observation.velocity_east_m_s])
            if self._last_target is not None:
                last_time_s, last_velocity = self._last_target
                elapsed = observation.time_s - last_time_s
                self._target_odometry = (
                    self._target_odometry + 0.5 * (last_velocity + velocity) * elapsed
                )
            self._last_target = (observation.time_s, velocity)
            odometry = (float(self._target_odometry[0]), float(self._target_odometry[1]))
        elif np.isfinite(self.target_track.observed_step):
            velocity = self.target_track.velocity_m_s
            observed_step = int(self.target_track.observed_step)
        else:
            return message
        return dataclasses.replace(
            message,
            target_odometry_north_m=odometry[0],
            target_odometry_east_m=odometry[1],
            target_velocity_north_m_s=float(velocity[0]),
            target_velocity_east_m_s=float(velocity[1]),
            target_observed_step=observed_step,
        )

    async def _wait_inputs(self, k: int, t_k: float) -> None:
        wait_s = self._wait_s(t_k)
        if wait_s > 0:
            await self.inbox.wait_complete(k, wait_s)

    def _horizontal_ranges(
        self, data: StepData, odometry: tuple[float, float, float]
    ) -> dict[int, float]:
        """UWB ranges are 3-D; the law is planar. The height difference at t_k (own odometry and
        the neighbour's step message; both odometry origins on the ground) is taken out:
        h = sqrt(d^2 - dz^2). It cancels out of the cosine law only while constant, and a real
        altitude hold wanders by decimetres (PX4 SIH: 0.11-0.14 m RMS), which between vehicles
        3 m apart in height is worth ~0.1 m of range error. The target's range is horizontal.
        When sharing, the ranges are rounded as the step message carries them."""
        ranges: dict[int, float] = {}
        for peer, measured_m in data.ranges_m.items():
            if peer != 0:
                own_m = shared_range(measured_m) if self._sharing else measured_m
                ranges[peer] = self._horizontal(own_m, data.neighbours.get(peer), odometry)
        if data.target is not None and data.target.range_m is not None:
            ranges[0] = data.target.range_m
        return ranges

    def _peer_ranges(
        self, data: StepData, odometry: tuple[float, float, float]
    ) -> dict[int, float]:
        """d_ji(k): the ranges the neighbours heard this step measured to this vehicle, from
        their step messages, made horizontal with the same height difference as the own range
        (a neighbour whose message is missing shares nothing: the own range stands alone)."""
        ranges: dict[int, float] = {}
        for peer, message in data.neighbours.items():
            for to_id, measured_m in message.ranges_m or ():
                if to_id == self.vehicle_id:
                    ranges[peer] = self._horizontal(measured_m, message, odometry)
        return ranges

    @staticmethod
    def _horizontal(
        measured_m: float, neighbour: StepMessage | None, odometry: tuple[float, float, float]
    ) -> float:
        """A 3-D range to ``neighbour`` (its step message, if heard) made horizontal."""
        height_m = 0.0
        if neighbour is not None and neighbour.odometry_down_m is not None:
            height_m = odometry[2] - neighbour.odometry_down_m
        return math.sqrt(max(measured_m * measured_m - height_m * height_m, 0.0))

    def _track_target(
        self, k: int, data: StepData, observation: TargetObservation | None
    ) -> TargetEstimate:
        """Advance the target track to step k with the freshest observation heard: this
        vehicle's own (``observation``, seen at k) or the freshest a neighbour relays in its
        step-k message. Every vehicle hears the same relays, so every track predicts alike."""
        heard = [message.relayed_target for message in data.neighbours.values()]
        north, east = (
            (None, None)
            if observation is None
            else (observation.velocity_north_m_s, observation.velocity_east_m_s)
        )
        if north is not None and east is not None:
            heard.append((k, (north, east)))
        relays = [relay for relay in heard if relay is not None]
        observed_step, velocity = max(relays, key=lambda relay: relay[0], default=(None, None))
        own_odometry = self._target_odometry if observation is not None else (math.nan, math.nan)
        self.target_track, estimate = track_target(
            self.target_track,
            k,
            velocity_m_s=(math.nan, math.nan) if velocity is None else velocity,
            observed_step=math.nan if observed_step is None else observed_step,
            own_odometry_m=own_odometry,
            step_s=self.settings.step_s,
            lost_after_s=self.settings.target_lost_after_s,
        )
        return estimate

    def _lead(self, velocity: ArrayLike) -> NDArray[np.float64]:
        """u + lead * du/dt: offsets the vehicle's velocity-loop lag and the command delay, so
        the displacement over the step is the one the law asked for."""
        velocity = np.asarray(velocity, dtype=float)
        previous, self._previous_command = self._previous_command, velocity
        if previous is None or self.settings.velocity_lead_s == 0:
            return velocity
        return (
            velocity + self.settings.velocity_lead_s * (velocity - previous) / self.settings.step_s
        )

    def _tracking(
        self, velocity: ArrayLike, odometry: tuple[float, float, float]
    ) -> NDArray[np.float64]:
        """Displacement tracking: a PI correction towards where the law's commands would have
        taken a vehicle that realised them exactly (the paper's p(k+1) = p(k) + T u(k)), from the
        own odometry. A real multicopter's velocity loop lags and loses to drag (PX4 SIH: ~30 %
        of a 3 m/s command on a circle); the law's saturated consensus cannot make that up, the
        formation then trails the target. Off when both gains are 0 (the paper's pure command)."""
        settings = self.settings
        if settings.tracking_gain_1_s == 0 and settings.tracking_integral_gain_1_s2 == 0:
            return np.zeros(2)
        here = np.asarray(odometry[:2], dtype=float)
        if self._reference is None:
            self._reference = here.copy()
        error = self._reference - here
        limit = settings.tracking_max_correction_m_s
        correction = settings.tracking_gain_1_s * error + self._tracking_integral
        if np.hypot(*correction) < limit:  # no wind-up while saturated
            self._tracking_integral = self._tracking_integral + (
                settings.tracking_integral_gain_1_s2 * error * settings.step_s
            )
        scale = min(1.0, limit / max(float(np.hypot(*correction)), 1e-12))
        self._reference = self._reference + settings.step_s * np.asarray(velocity, dtype=float)
        return correction * scale

    def _clamp(self, velocity: NDArray[np.float64]) -> tuple[float, float]:
        limit_m_s = self.settings.max_horizontal_speed_m_s
        clamped = saturate(np.asarray(velocity, dtype=float), limit_m_s)
        return (float(clamped[0]), float(clamped[1]))

    def _altitude_hold(self, odometry: tuple[float, float, float] | None) -> float:
        if odometry is None:
            return 0.0
        error = -self.altitude_m - odometry[2]  # NED: down is positive
        limit = self.settings.max_vertical_speed_m_s
        return float(np.clip(self.settings.altitude_gain_per_s * error, -limit, limit))

    async def _publish(self, topic: str, message: Message) -> None:

        try:
            await self.bus.publish_message(topic, message, timeout=self.settings.step_s / 2)
        except BusError as error:
            logger.warning("vehicle %s: could not publish %s: %s", self.vehicle_id, topic, error)

    async def _publish_status(self, k: int, t_k: float) -> None:
        detail = self.link.control_lost or ""
        if self.state == ControllerState.TARGET_LOST:
            unseen_s = (k - float(self.target_track.observed_step)) * self.settings.step_s
            detail = (
                f"target not seen for {unseen_s:.2f} s"
                if math.isfinite(unseen_s)
                else "target never seen"
            )
        said = (self.state, detail)
        if said == self._status_said and k % self._status_period_steps:
            return
        self._status_said = said
        status = VehicleStatus(
            self.vehicle_id,
            t_k,
            self.state,
            k,
            self.state == ControllerState.FOLLOWING,
            detail,
            mission_id=self.mission_id,
            clock_rate=None if self.autopilot_clock_rate is None else self.autopilot_clock_rate(),
            stale_steps=self.stale_steps,
        )
        await self._publish(self.topics.status(self.vehicle_id), status)


def build_controller(
    scenario: Scenario,
    vehicle: VehicleConfig,
    *,
    link: ControllerLink,
    bus: ControllerBus,
    clock: ControllerClock,
    on_step: Callable[[int, StepRecord], None] | None = None,
    shape: ShapeSchedule | None = None,
) -> VehicleController:
    """The controller of ``vehicle`` flying ``link`` on ``bus`` and ``clock``."""
    ids = [v.id for v in scenario.vehicles]
    law = VehicleEnclosing(
        algorithm_params(scenario, flown=True),
        vehicle.id,
        ids,
        vehicle.initial_phase_rad,
        omega_of(scenario, vehicle),
    )
    return VehicleController(
        vehicle_id=vehicle.id,
        vehicle_ids=ids,
        law=law,
        senses_target=vehicle.senses_target,
        link=link,
        bus=bus,
        topics=scenario.bus.topics(scenario.name),
        clock=clock,
        settings=controller_settings(scenario, vehicle),
        shape=shape or shape_schedule(scenario),
        altitude_m=altitude_of(scenario, vehicle),
        on_step=on_step,
    )
