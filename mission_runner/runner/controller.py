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
5. decide what the step does (:func:`.pipeline.decide`: follow, or hold on stale data, for the
   operator or for a lost target), run the law (:class:`mission_runner.enclosing.VehicleEnclosing`),
   shape its command (:mod:`.pipeline`: lead, displacement tracking, separation guard, the
   vehicle's speed limit), add the altitude-hold term and send the setpoint; with the target
   lost, hold (or orbit its last estimate: ``target_on_lost``) in state ``target_lost``.

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
from numpy.typing import NDArray

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
    NeighbourReport,
    TargetEstimate,
    TargetReport,
    TargetTrack,
    VehicleCommand,
    VehicleEnclosing,
    track_target,
)
from ..enclosing.target import STATUS_NAMES
from ..records import STALE_STATES, ControllerState, StepRecord
from ..scenario import ShapeSchedule, omega_of, shape_schedule
from ..tasks import first_completed
from ..wiring import (
    algorithm_params,
    altitude_of,
    neighbour_graph,
)
from .inbox import StepData, StepInbox
from .odometry import ODOMETRY_PERIOD_S
from .pipeline import (
    CommandShaper,
    SeparationSettings,
    StepCommand,
    StepDecision,
    altitude_hold_m_s,
    clamp_horizontal,
    decide,
    separated,
)
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


def command_shaper(settings: ControllerSettings) -> CommandShaper:
    """The lead and displacement tracking of a controller with ``settings``."""
    return CommandShaper(
        step_s=settings.step_s,
        lead_s=settings.velocity_lead_s,
        gain_1_s=settings.tracking_gain_1_s,
        integral_gain_1_s2=settings.tracking_integral_gain_1_s2,
        max_correction_m_s=settings.tracking_max_correction_m_s,
    )


def separation_settings(settings: ControllerSettings) -> SeparationSettings | None:
    """The separation guard's settings (None: no guard, no minimum separation set)."""
    if settings.min_separation_m is None:
        return None
    return SeparationSettings(
        min_separation_m=settings.min_separation_m,
        gain_1_s=settings.separation_gain_1_s,
        step_s=settings.step_s,
        margin_m=settings.separation_margin_m,
        braking_m_s2=settings.separation_braking_m_s2,
        latency_s=settings.separation_latency_s,
        range_noise_std_m=settings.separation_range_noise_std_m,
    )


def _gates(
    settings: ControllerSettings, vehicle_id: int
) -> tuple[RangeGate | None, CommandGate | None]:
    """The plausibility gates of the own ranges and the neighbours' commands (None: everything
    is taken as it comes, as a unit test's fake sensors want)."""
    limits, speed_m_s = settings.range_limits, settings.fleet_speed_limit_m_s
    return (
        None if limits is None else RangeGate(limits, vehicle_id),
        None if speed_m_s is None else CommandGate(speed_m_s, vehicle_id),
    )


@dataclass
class _OwnTargetOdometry:
    """The target's odometry from the own observations only: their velocities integrated,
    trapezoid over the time between them, so a gap in observations is bridged, not lost."""

    odometry_m: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.zeros(2))
    #: The last observation's (time [s], velocity ``(2,)`` [m/s]); None before the first.
    last: tuple[float, NDArray[np.float64]] | None = None

    def integrate(self, time_s: float, velocity_m_s: NDArray[np.float64]) -> tuple[float, float]:
        """The odometry at ``time_s`` with the target's velocity then."""
        if self.last is not None:
            last_time_s, last_velocity = self.last
            elapsed = time_s - last_time_s
            self.odometry_m = self.odometry_m + 0.5 * (last_velocity + velocity_m_s) * elapsed
        self.last = (time_s, velocity_m_s)
        return (float(self.odometry_m[0]), float(self.odometry_m[1]))


@dataclass
class _StepTimes:
    """Where a step's time went (mission clock), as its record keeps it (NaN: not reached)."""

    odometry_ready_s: float = math.nan
    message_sent_s: float = math.nan
    inputs_ready_s: float = math.nan
    setpoint_sent_s: float = math.nan


class VehicleController:
    """The enclosing loop of vehicle ``vehicle_id``.

    law: its :class:`VehicleEnclosing`. link: the vehicle (:class:`.ports.ControllerLink`, e.g.
    :class:`.links.MavsdkVehicle`). bus + topics: the message bus. clock: the mission clock
    (:class:`.ports.ControllerClock`). shape(k): the affine shape matrix ``(3, 3)`` at step k.
    altitude_m: the altitude this vehicle holds (up, metres above home). on_step(vehicle_id,
    record) sees every step's record.
    """

    #: The horizontal setpoint this vehicle flies (the last one sent by the law's steps; None
    #: before the first): its step messages carry it for the neighbours' guards.
    command_in_force: tuple[float, float] | None = None
    #: The operator's hold (ground station ``hold`` until ``resume``): hover in place, keep the
    #: oscillator on the grid, publish nothing of the law.
    operator_hold = False
    #: The last step whose command was chosen (where ``operator_hold`` is read): a change of the
    #: hold is first seen by the step after it.
    decided_step = -1
    #: The mission it flies, carried by every status (vehicle processes set it).
    mission_id: str | None = None
    #: Its autopilot's recent boot-clock rate, carried by every status so the ground's mission
    #: clock can follow it (vehicle processes set it; None: its clock is the mission's).
    autopilot_clock_rate: Callable[[], float] | None = None

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
        self.vehicle_id, self.law, self.senses_target = vehicle_id, law, senses_target
        self.link, self.bus, self.topics, self.clock = link, bus, topics, clock
        self.settings, self.shape, self.altitude_m = settings, shape, altitude_m
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
        self.target_track = TargetTrack.initial()
        self._own_target = _OwnTargetOdometry()
        self._last_fresh_s = -math.inf  # nothing heard yet; run() starts the silence at k = 0
        self.shaper = command_shaper(settings)
        self._missed_odometry = 0
        self.skipped_steps = 0
        self.range_gate, self.command_gate = _gates(settings, vehicle_id)
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
        """Step k (the module's 1-5): the I/O around :func:`.pipeline.decide` and the law's
        command chain (:meth:`_fly`)."""
        if not self.clock.lockstep and self.clock.now_s() >= t_k + self.settings.step_s:
            # Step k's instant is a whole step in the past (a stall, a slow machine): its
            # inputs are stale and a command for it would be late. Skip it, keeping the
            # oscillator on the grid, so the controller is back on the current step at once
            # instead of falling further behind every step.
            self._skip(k, t_k)
            return
        self.clock.release(t_k + self.settings.release_s)
        await self.clock.sleep_until(t_k)
        times = _StepTimes()
        odometry = await self._odometry_at(t_k)
        phase = self.law.phase_rad
        observation = await self._publish_step(k, t_k, phase, odometry, times)
        await self._wait_inputs(k, t_k)
        times.inputs_ready_s = self.clock.now_s()
        data = self.inbox.take(k)
        target = self._track_target(k, data, observation)
        decision = self._decide(k, data, target, odometry)
        self.state = decision.state
        if decision.flies and odometry is not None:
            command = self._fly(k, data, target, odometry)
        else:
            command = self._hold(k)
        vertical = self._altitude_hold(odometry)
        if self.link.control_lost is None:  # taken over during the step: never stream to it
            async with self.clock.commanding(t_k + self.settings.release_s):
                await self.link.set_velocity_ned(*command.velocity_m_s, vertical)
        self.command_in_force = command.velocity_m_s
        times.setpoint_sent_s = self.clock.now_s()
        record = self._record(
            k, t_k, command, vertical, phase=phase, odometry=odometry, target=target, times=times
        )
        await self._recorded(k, t_k, record)

    def _record(
        self,
        k: int,
        t_k: float,
        command: StepCommand,
        vertical_m_s: float,
        *,
        phase: float,
        odometry: tuple[float, float, float] | None,
        target: TargetEstimate,
        times: _StepTimes,
    ) -> StepRecord:
        """Step k's record: what it commanded (``vertical_m_s``: the altitude hold's), from
        what (the phase and own odometry at t_k, the target's track), and when."""
        return StepRecord(
            step=k,
            time_s=t_k,
            state=self.state,
            velocity_ned_m_s=(*command.velocity_m_s, vertical_m_s),
            consensus_m_s=command.consensus_m_s,
            phase_rad=phase,
            neighbours_used=command.neighbours_used,
            estimates_m=command.estimates_m,
            odometry_m=(math.nan, math.nan, math.nan) if odometry is None else odometry,
            gated=command.gated,
            ranges_m=command.ranges_m,
            target=STATUS_NAMES[int(target.status)],
            setpoint_sent_s=times.setpoint_sent_s,
            odometry_ready_s=times.odometry_ready_s,
            message_sent_s=times.message_sent_s,
            inputs_ready_s=times.inputs_ready_s,
        )

    async def _publish_step(
        self,
        k: int,
        t_k: float,
        phase: float,
        odometry: tuple[float, float, float] | None,
        times: _StepTimes,
    ) -> TargetObservation | None:
        """Publish the step-k message (none without own odometry, a step missed); returns the
        own target observation if it saw it. The observation (and, to share, the ranges) of
        step k are usually in by now; they are awaited briefly if not. One that says "not seen"
        is as good as one that saw: nothing more is coming."""
        if odometry is None:
            self._missed_odometry += 1
            return None
        times.odometry_ready_s = self.clock.now_s()
        self._missed_odometry = 0
        observation, shared = await self._own_measurements(k, t_k)
        in_force = self.command_in_force
        if observation is not None and not observation.seen:
            observation = None
        message = StepMessage(
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
        )
        await self._publish(
            self.topics.step(self.vehicle_id), self._with_target(message, observation)
        )
        times.message_sent_s = self.clock.now_s()
        return observation

    def _decide(
        self,
        k: int,
        data: StepData,
        target: TargetEstimate,
        odometry: tuple[float, float, float] | None,
    ) -> StepDecision:
        """What step k does (:func:`.pipeline.decide`), a neighbour's message heard this step
        being fresh data."""
        now_s = self.clock.now_s()
        if data.neighbours:
            self._last_fresh_s = now_s
        self.decided_step = k
        return decide(
            has_odometry=odometry is not None,
            stale_s=now_s - self._last_fresh_s,
            silence_timeout_s=self.settings.silence_timeout_s,
            in_control=self.link.in_control,
            operator_hold=self.operator_hold,
            target_status=int(target.status),
            target_on_lost=self.settings.target_on_lost,
        )

    def _hold(self, k: int) -> StepCommand:
        """Hold (zero horizontal velocity), the oscillator turning on the grid."""
        self.shaper.hold()
        self._turn_oscillator(k)
        return StepCommand()

    def _fly(
        self, k: int, data: StepData, target: TargetEstimate, odometry: tuple[float, float, float]
    ) -> StepCommand:
        """The law's command made flyable: law, lead + tracking, separation, clamp."""
        ranges = self._horizontal_ranges(data, odometry)
        command = self._law_step(k, data, target, odometry, ranges)
        wanted = self.shaper.lead(command.velocity_m_s) + self.shaper.tracking(
            command.velocity_m_s, odometry[:2]
        )
        separation = separation_settings(self.settings)
        if separation is not None:
            in_force = {peer: m.command_m_s for peer, m in data.neighbours.items()}
            wanted = separated(
                wanted,
                command,
                ranges,
                own_in_force_m_s=self.command_in_force,
                in_force_m_s=in_force,
                settings=separation,
            )
        return StepCommand(
            velocity_m_s=clamp_horizontal(wanted, self.settings.max_horizontal_speed_m_s),
            consensus_m_s=(float(command.consensus_m_s[0]), float(command.consensus_m_s[1])),
            neighbours_used=command.neighbours_used,
            estimates_m=command.estimates_m,
            gated=command.gated,
            ranges_m=ranges,
        )

    def _law_step(
        self,
        k: int,
        data: StepData,
        target: TargetEstimate,
        odometry: tuple[float, float, float],
        ranges: dict[int, float],
    ) -> VehicleCommand:
        """The law's step k on what arrived (the horizontal ``ranges`` by peer id)."""
        return self.law.step(
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

    async def _recorded(self, k: int, t_k: float, record: StepRecord) -> None:
        """Keep step k's record, report the status, and hand the record on."""
        self.records.append(record)
        await self._publish_status(k, t_k)
        if self.on_step is not None:
            self.on_step(self.vehicle_id, record)

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
        self.shaper.skip()
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
        (as :func:`.bus.shared_range` rounds them). Awaited no longer than half the step's
        deadline: the neighbours stop waiting for this message at the deadline, so a message that
        waited all of it for an input that is late or never comes reaches nobody in time
        (measured: waiting the whole deadline, a flight sharing ranges with 2 % dropouts lost
        neighbours' messages and the phases never settled; in a swarm of one process per vehicle
        over mosquitto, 12 vehicles at 1x, the target-sensing vehicle's messages missed the
        others' deadlines 189 times in 20 s, the others' 4 to 12). What comes later is still the
        law's, only not relayed."""
        if not (self.senses_target or self._sharing):
            return None, None

        def in_() -> bool:
            target = not self.senses_target or self.inbox.pending_target(k) is not None
            return target and (not self._sharing or self.inbox.own_ranges_in(k))

        await self.inbox.wait_for(in_, self._wait_s(t_k) / 2.0)
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
            odometry = self._own_target.integrate(observation.time_s, velocity)
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
        own_odometry = (
            self._own_target.odometry_m if observation is not None else (math.nan, math.nan)
        )
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

    def _altitude_hold(self, odometry: tuple[float, float, float] | None) -> float:
        return altitude_hold_m_s(
            None if odometry is None else odometry[2],
            altitude_m=self.altitude_m,
            gain_1_s=self.settings.altitude_gain_per_s,
            limit_m_s=self.settings.max_vertical_speed_m_s,
        )

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
    sparse = scenario.algorithm.graph.kind != "complete"
    law = VehicleEnclosing(
        algorithm_params(scenario, flown=True),
        vehicle.id,
        ids,
        vehicle.initial_phase_rad,
        omega_of(scenario, vehicle),
        graph=neighbour_graph(scenario) if sparse else None,
        ring=scenario.algorithm.graph.kind == "ring",
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
