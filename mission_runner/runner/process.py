"""A swarm as separate processes: one controller per vehicle (one companion computer each), and a
ground station, talking only over MQTT.

The handshake, as an operator expects it:

1. ``mission-runner ground CONFIG`` publishes ``prepare`` (retained) with a fresh mission id.
2. Each ``mission-runner vehicle CONFIG --id N`` connects to its autopilot, maps the autopilot's
   clock (:mod:`.timesync`), and on ``prepare`` sets the scenario's autopilot parameters, arms,
   takes off, enters OFFBOARD hovering on the step grid and reports ``ready`` with the mission id
   and its autopilot's clock rate. A refusal (PX4's own reason) is reported as ``failed``.
3. The ground station starts the mission when every vehicle is ready: ``start`` with k = 0 and
   the mission clock (UNIX time, scaled to the autopilots' measured clock rate when they run
   simulated time at another speed, PX4 SITL's speed factor). If any vehicle failed, or not all
   are ready in time, it aborts the mission for everyone (``land``): nobody is left hovering.
4. Vehicles fly the steps and land (``flight.end_action``). A vehicle someone else takes (a mode
   change or disarm by a pilot, another ground station or a failsafe) reports ``taken_over`` and is
   left to them; its setpoint stream ends at once (:meth:`.links.MavsdkVehicle.release`). A
   vehicle whose controller gives up reports ``lost`` - final, never followed by ``done`` - and
   is put in ``flight.on_lost`` by its process (and by its autopilot's offboard-loss failsafe,
   set to the same, if the process dies).

Statuses and commands carry the mission id, so retained messages of an earlier mission are never
taken for this one's.

A vehicle's last will (published by the broker when its connection ends without a goodbye) is a
drop-off, not a loss: the broker also publishes it when another connection takes the vehicle's
client id, and the vehicle reconnects and flies on. The ground station takes a will as final only
when no status of that vehicle (a flying controller sends one every step) arrives within
:func:`rejoin_grace_s` after it; a vehicle heard again is not lost, and the drop is counted
(``GroundOutcome.bus_drops``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..bus import (
    Bus,
    BusError,
    BusTimeoutError,
    ControlCommand,
    MessageDecodeError,
    MissionControl,
    Sender,
    Subscription,
    TopicError,
    Topics,
    VehicleStatus,
    lost_vehicle_will,
    open_bus,
)
from ..bus.broker import OPERATOR_USER, flight_user, read_credentials
from ..environment import USERNAME_ENV
from ..errors import error_reason
from ..records import ControllerState, StepRecord, VehicleRun
from ..wiring import altitude_of, autopilot_params
from .clock import WallClock
from .controller import VehicleController, build_controller
from .errors import RunnerError, RunnerTimeoutError
from .handshake import freeze_heap, next_command
from .links import SAFE_STATE_TIMEOUT_S, MavsdkVehicle, connected_vehicles
from .operator import (
    ENDING_ACTIONS,
    OperatorCommand,
    OperatorConsole,
    fly_obeying,
    operator_command,
    publish_operator,
    serving,
)
from .scoring import merge_mission
from .timesync import ClockFollower, ClockMapping, MissionTime

if TYPE_CHECKING:
    from ..bus.auth import AuthCounters
    from ..config import Scenario
    from ..metrics import SimulationResult
    from ..paths import PathName

logger = logging.getLogger(__name__)

#: A vehicle's states after which nothing changes: it gave up (lost), could not fly (failed), was
#: stopped by the ground station (aborted), or is flown by someone else (taken over).
FINAL_STATES = (
    ControllerState.LOST,
    ControllerState.FAILED,
    ControllerState.ABORTED,
    ControllerState.TAKEN_OVER,
)

DEFAULT_API_PORT_BASE = 14540

#: Beyond a vehicle's reconnect (its backoff and connect timeout), how long the ground station
#: waits after the vehicle's last will for its first message before taking it as lost.
REJOIN_MARGIN_S = 1.0


class MissionAbortedError(RunnerError):
    """The ground station aborted the mission (a vehicle refused, or not all were ready)."""


def default_url(scenario: Scenario, vehicle_id: int) -> str:
    """Where vehicle ``vehicle_id`` is when the scenario gives no url: PX4 SITL's (and the
    emulator's) API port for its instance."""
    index = [v.id for v in scenario.vehicles].index(vehicle_id)
    return f"udpin://0.0.0.0:{DEFAULT_API_PORT_BASE + index}"


class _Reporter:
    """Publishes this vehicle's status (retained) under the current mission id."""

    def __init__(
        self, bus: Bus, topics: Topics, run: VehicleRun, *, unix_s: Callable[[], float] = time.time
    ) -> None:
        self.bus, self.topics, self.run = bus, topics, run
        self.unix_s = unix_s
        #: Once flying: its steps held or skipped go with every report (the ground's verdict).
        self.controller: VehicleController | None = None

    async def __call__(
        self,
        state: ControllerState,
        *,
        step: int = 0,
        detail: str = "",
        clock_rate: float | None = None,
    ) -> None:
        self.run.state, self.run.detail = state, detail
        status = VehicleStatus(
            self.run.vehicle_id,
            self.unix_s(),
            state,
            step,
            state == ControllerState.FOLLOWING,
            detail,
            mission_id=self.run.mission_id,
            clock_rate=clock_rate,
            stale_steps=None if self.controller is None else self.controller.stale_steps,
        )
        try:
            await self.bus.publish_message(
                self.topics.status(self.run.vehicle_id), status, retain=True, timeout=2.0
            )
        except BusError as error:
            logger.warning(
                "vehicle %s: status %s not published: %s", status.vehicle_id, state, error
            )


async def run_vehicle(
    scenario: Scenario,
    vehicle_id: int,
    *,
    url: str | None = None,
    ready_timeout_s: float = 180.0,
    on_step: Callable[[int, StepRecord], None] | None = None,
    run: VehicleRun | None = None,
) -> VehicleRun:
    """Fly vehicle ``vehicle_id`` of ``scenario`` as its own process. Returns its
    :class:`VehicleRun` (``run``, if given, is filled in as the flight goes, so the caller has it
    even when this raises); raises :class:`RunnerError` when it could not fly (after reporting it
    and putting the vehicle in a safe state)."""
    process = VehicleProcess(scenario, vehicle_id, url=url, on_step=on_step, run=run)
    async with contextlib.AsyncExitStack() as stack:
        await process.connect(stack)
        await process.prepare(ready_timeout_s)
        await process.fly()
    return process.run


class VehicleProcess:
    """One vehicle's side of the handshake (module docstring), phase by phase: :meth:`connect`
    (autopilot, its clock, the bus), :meth:`prepare` (the ground's prepare, take-off, the
    controller), then :meth:`fly`: :meth:`wait_start` (OFFBOARD, hover, ready until the start),
    :meth:`fly_steps` and :meth:`land` (the vehicle's end, reported). ``unix_s`` is the UNIX clock
    its statuses and mission clock read (injectable for tests)."""

    vehicle: MavsdkVehicle
    mapping: ClockMapping
    bus: Bus
    control: Subscription
    controller_bus: Bus
    report: _Reporter
    controller: VehicleController

    def __init__(
        self,
        scenario: Scenario,
        vehicle_id: int,
        *,
        url: str | None = None,
        on_step: Callable[[int, StepRecord], None] | None = None,
        run: VehicleRun | None = None,
        unix_s: Callable[[], float] = time.time,
    ) -> None:
        if scenario.bus.kind != "mqtt":
            raise RunnerError("a vehicle process talks to the others over MQTT: set bus.kind: mqtt")
        ids = [v.id for v in scenario.vehicles]
        if vehicle_id not in ids:
            raise RunnerError(f"vehicle {vehicle_id} is not in the scenario (ids {ids})")
        self.scenario, self.vehicle_id, self.on_step = scenario, vehicle_id, on_step
        self.index = ids.index(vehicle_id)
        self.config = scenario.vehicles[self.index]
        self.url = url or self.config.url or default_url(scenario, vehicle_id)
        self.topics = scenario.bus.topics(scenario.name)
        self.unix_s = unix_s
        self.mission_time = MissionTime(unix=unix_s)
        self.run = run or VehicleRun(vehicle_id)

    async def connect(self, stack: contextlib.AsyncExitStack) -> None:
        """The autopilot (its clock mapped onto the mission's) and the bus, on ``stack``;
        reports ``waiting``."""
        scenario, vehicle_id = self.scenario, self.vehicle_id
        systems = await stack.enter_async_context(
            connected_vehicles(
                [self.url], [vehicle_id], url_setting=f"--url or vehicles[{self.index}].url"
            )
        )
        self.vehicle = await stack.enter_async_context(
            MavsdkVehicle(systems[vehicle_id], vehicle_id)
        )
        self.mapping = await self.vehicle.follow_clock(self.mission_time)
        self.bus = await stack.enter_async_context(
            open_bus(
                scenario.bus,
                sender=Sender.vehicle(vehicle_id),
                client_id=f"{scenario.name}-vehicle-{vehicle_id}",
                will=lost_vehicle_will(self.topics, vehicle_id, time_s=self.unix_s()),
            )
        )
        self.control = await stack.enter_async_context(self.bus.subscribe(self.topics.control()))
        self.controller_bus = await stack.enter_async_context(
            flight_bus(scenario, vehicle_id, self.bus)
        )
        self.report = _Reporter(self.bus, self.topics, self.run, unix_s=self.unix_s)
        await self.report(
            ControllerState.WAITING, detail="waiting for the ground station's prepare"
        )

    async def prepare(self, ready_timeout_s: float) -> None:
        """On the ground's prepare: the scenario's parameters and the take-off (a refusal is
        reported ``failed`` and the vehicle landed), then the controller."""
        scenario, vehicle = self.scenario, self.vehicle
        prepare = await next_command(
            self.control, {ControlCommand.PREPARE}, timeout_s=ready_timeout_s
        )
        self.run.mission_id = prepare.mission_id
        try:
            self.run.params = await vehicle.apply_params(autopilot_params(scenario))
            await vehicle.take_off(altitude_of(scenario, self.config))
        except RunnerError as error:
            await self.report(ControllerState.FAILED, detail=str(error))
            with contextlib.suppress(RunnerError):
                await vehicle.finish("land", timeout_s=SAFE_STATE_TIMEOUT_S)
            raise
        self.controller = build_controller(
            scenario,
            self.config,
            link=vehicle,
            bus=self.controller_bus,
            clock=WallClock(self.mission_time),
            on_step=self.on_step,
        )
        self.report.controller = self.controller
        self.controller.autopilot_clock_rate = self.mapping.recent_boot_rate

    async def fly(self) -> None:
        """From hover to the vehicle's end; whatever ends it early puts the vehicle in a safe
        state. ``run`` has the controller's records and counters in any case."""
        try:
            start = await self.wait_start()
            if start is not None:
                ending = await self.fly_steps(start)
                await self.land(ending)
        except BaseException as error:
            await self._safe_state(error)
            raise
        finally:
            self._collect()

    async def wait_start(self) -> float | None:
        """OFFBOARD at the vehicle's altitude, hovering on the step grid and reporting ready,
        until the start (returns k = 0's time, the mission clock set) or a land, return or stop
        for this vehicle (carried out; returns None)."""
        run, vehicle, controller = self.run, self.vehicle, self.controller
        controller.mission_id = run.mission_id
        start: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        async with asyncio.TaskGroup() as group:
            hovering = group.create_task(
                controller.hover_until(start), name=f"vehicle-{run.vehicle_id}-hover"
            )
            try:
                await vehicle.start_offboard()
                await vehicle.wait_altitude(controller.altitude_m)
                await vehicle.quiet_unread_streams()
                command = await self._until_start()
            except BaseException:
                hovering.cancel()
                raise
            if command.command is not ControlCommand.START:
                hovering.cancel()
                await self._abort(command)
                return None
            freeze_heap()
            rate = command.clock_rate or 1.0
            self.mission_time.set(rate, command.clock_reference_s or command.time_s)
            run.clock_rate, run.start_s = rate, command.time_s
            controller.mission_id = run.mission_id
            start.set_result(command.time_s)
        return run.start_s

    async def fly_steps(self, start_s: float) -> MissionControl | None:
        """The controller flies its steps unless the operator's land, return or stop for this
        vehicle ends them (returned); a controller failure propagates and lands it (:meth:`fly`)."""
        return await fly_obeying(
            self.controller,
            self.controller.run(start_s, self.scenario.timing.steps),
            self.control,
            mission_id=self.run.mission_id,
            mission_time=self.mission_time,
        )

    async def land(self, ending: MissionControl | None) -> None:
        """The vehicle's end, reported: the operator's ``ending``, left to whoever took it, put
        in ``flight.on_lost`` when lost, or ``flight.end_action`` after its steps (done)."""
        vehicle, controller, report = self.vehicle, self.controller, self.report
        if ending is not None:
            await self._abort(ending)
            return
        last = controller.records[-1].step if controller.records else 0
        if controller.state == ControllerState.TAKEN_OVER:
            # Someone else flies it now: report it and leave it be (never fight a pilot). Its
            # setpoint stream ended when the link saw it taken (MavsdkVehicle.release).
            await vehicle.stream_ended()
            await report(ControllerState.TAKEN_OVER, step=last, detail=vehicle.control_lost or "")
            return
        if controller.state == ControllerState.LOST:
            await report(
                ControllerState.LOST, step=last, detail="own odometry stopped: no longer driven"
            )
            with contextlib.suppress(RunnerError):
                await vehicle.finish(self.scenario.flight.on_lost, timeout_s=SAFE_STATE_TIMEOUT_S)
            return
        await vehicle.finish(self.scenario.flight.end_action)
        await report(ControllerState.DONE, step=len(controller.records))

    async def _safe_state(self, error: BaseException) -> None:
        """Never leave a vehicle in the air undriven: whatever ended the mission, command the
        configured safe state (PX4's offboard-loss failsafe covers a dead process)."""
        vehicle, action = self.vehicle, self.scenario.flight.on_lost
        logger.warning(
            "vehicle %s: mission ended (%s): %s", self.vehicle_id, error_reason(error), action
        )
        if vehicle.control_lost is None:  # a vehicle someone else flies is theirs
            with contextlib.suppress(RunnerError):
                await asyncio.shield(vehicle.finish(action, timeout_s=SAFE_STATE_TIMEOUT_S))
        else:  # its setpoint stream ended when it was taken: see that it did
            await vehicle.stream_ended()
        if self.run.state not in FINAL_STATES:
            await self.report(ControllerState.LOST, detail=f"mission ended: {error_reason(error)}")

    def _collect(self) -> None:
        """The controller's records and counters, the bus's and the clock fit's, into ``run``."""
        run, controller, fit = self.run, self.controller, self.mapping.fit
        run.records = controller.records
        run.skipped_steps = controller.skipped_steps
        run.bus_messages = self.bus.auth_counters.as_dict()
        if controller.range_gate is not None:
            run.ranges_rejected = dict(controller.range_gate.rejected)
        if controller.command_gate is not None:
            run.commands_rejected = controller.command_gate.rejected["command_speed"]
        run.autopilot_clock_rate = fit.boot_rate
        run.setpoints_scale_bounded = self.vehicle.scale_bounded_setpoints
        run.clock_residual_s = fit.residual_s

    async def _abort(self, command: MissionControl) -> None:
        detail = f"mission aborted by the ground station: {command.reason or command.command.value}"
        logger.warning("vehicle %s: %s", self.vehicle_id, detail)
        await self.report(ControllerState.ABORTED, detail=detail)
        action = ENDING_ACTIONS.get(command.command, self.scenario.flight.on_lost)
        await self.vehicle.finish(action, timeout_s=SAFE_STATE_TIMEOUT_S)

    async def _until_start(self) -> MissionControl:
        """Report ready (again for every new prepare) until this mission's start, or a land,
        return or stop for this vehicle."""
        run = self.run
        wanted = {ControlCommand.PREPARE, ControlCommand.START, *ENDING_ACTIONS}
        while True:
            await self.report(ControllerState.READY, clock_rate=self.mapping.recent_boot_rate())
            command = await next_command(self.control, wanted)
            if command.command is ControlCommand.PREPARE:
                run.mission_id = command.mission_id
                continue
            if command.vehicle_id not in (None, run.vehicle_id):
                continue
            if command.mission_id != run.mission_id:
                logger.warning(
                    "vehicle %s: ignoring %s of mission %s (this is %s)",
                    run.vehicle_id,
                    command.command.value,
                    command.mission_id,
                    run.mission_id,
                )
                continue
            return command


def flight_bus(
    scenario: Scenario, vehicle_id: int, control_bus: Bus
) -> contextlib.AbstractAsyncContextManager[Bus]:
    """The controller's own connection to the broker, for its neighbours' step messages, its
    ranges and its target and its own step messages; the control topic (and statuses, and the
    last will) stay on ``control_bus``. A broker sends each connection its messages in order, and
    a client reads one connection in order: on one connection, a flood on the control topic
    (40,000 garbage payloads) held genuine step messages back by seconds, and they were dropped
    as late. On two, the event loop reads both sockets in every turn. Both sign with one
    :class:`MessageAuth` (``auth``): one sequence per topic and one set of counters for the
    process.

    The second connection logs in as ``broker.flight_user`` (broker-config writes it: a broker
    that binds client ids to logins lets a login hold one connection). Without a login of its
    own (a credentials file with only the vehicle's line, or a login from the environment) the
    controller shares ``control_bus``, as a second connection on the same login would take the
    first's (and have its last will published)."""
    access = scenario.bus.access
    credentials = access.credentials_file or scenario.bus.mqtt.credentials_file
    login: str | None = None
    if credentials is not None:
        login = flight_user(vehicle_id)
        if os.environ.get(USERNAME_ENV) or login not in read_credentials(credentials):
            logger.info(
                "vehicle %s: no login %s: the controller shares the control connection",
                vehicle_id,
                login,
            )
            return contextlib.nullcontext(control_bus)
    bus = open_bus(
        scenario.bus,
        sender=Sender.vehicle(vehicle_id),
        client_id=f"{scenario.name}-vehicle-{vehicle_id}-flight",
        login=login,
    )
    bus.auth = control_bus.auth
    return bus


def rejoin_grace_s(scenario: Scenario) -> float:
    """How long after a vehicle's last will the ground station waits to hear from it again: its
    longest reconnect delay and connect timeout (``bus.mqtt``), plus :data:`REJOIN_MARGIN_S`."""
    mqtt = scenario.bus.mqtt
    return mqtt.reconnect_max_s + mqtt.connect_timeout_s + REJOIN_MARGIN_S


class _Wills:
    """Vehicles' last wills, held until they can be believed (see the module docstring).

    ``pending``: the will of each vehicle not heard from since, with when it arrived (monotonic
    seconds); ``drops``: by vehicle, the wills it outlived (heard from again after them)."""

    def __init__(self, grace_s: float) -> None:
        self.grace_s = grace_s
        self.pending: dict[int, tuple[VehicleStatus, float]] = {}
        self.drops: dict[int, int] = {}

    def add(self, will: VehicleStatus, now_s: float) -> None:
        self.pending.setdefault(will.vehicle_id, (will, now_s))

    def heard(self, vehicle_id: int) -> bool:
        """Vehicle ``vehicle_id`` spoke: its pending will (if any) is not final. Returns whether
        it had one."""
        if self.pending.pop(vehicle_id, None) is None:
            return False
        self.drops[vehicle_id] = self.drops.get(vehicle_id, 0) + 1
        logger.warning(
            "ground: vehicle %s heard again after its last will: not lost (bus drop %d)",
            vehicle_id,
            self.drops[vehicle_id],
        )
        return True

    def next_due_s(self) -> float:
        """When the oldest pending will becomes final (inf: none pending)."""
        return min((at_s + self.grace_s for _, at_s in self.pending.values()), default=math.inf)

    def due(self, now_s: float) -> list[VehicleStatus]:
        """The wills of vehicles silent for ``grace_s`` since: final now (no longer pending)."""
        final = [will for will, at_s in self.pending.values() if now_s - at_s >= self.grace_s]
        for will in final:
            del self.pending[will.vehicle_id]
        return final


@dataclass
class GroundOutcome:
    """The mission as the ground station saw it: the final status of every vehicle."""

    mission_id: str
    start_s: float | None
    clock_rate: float
    statuses: dict[int, VehicleStatus]
    #: Received bus messages accepted and dropped by reason (``AuthCounters.as_dict``).
    bus_messages: dict[str, int] = field(default_factory=dict)
    #: By vehicle, the last wills it outlived: dropped off the bus, then heard again (not lost).
    bus_drops: dict[int, int] = field(default_factory=dict)
    #: How often the mission clock changed its rate to follow the autopilots (ClockFollower).
    clock_changes: int = 0
    #: Its rate at the end (after those changes).
    clock_rate_at_end: float | None = None

    @property
    def lost(self) -> list[int]:
        return sorted(i for i, s in self.statuses.items() if s.state != ControllerState.DONE)

    @property
    def stale_steps(self) -> int | None:
        """Steps the vehicles held or skipped for want of fresh data, as their last reports
        say; None when a vehicle never said (it failed before flying, or its report was lost)."""
        counts = [status.stale_steps for status in self.statuses.values()]
        if not counts or any(count is None for count in counts):
            return None
        return sum(count for count in counts if count is not None)


async def run_ground(
    scenario: Scenario,
    *,
    start_delay_s: float = 2.0,
    ready_timeout_s: float = 180.0,
    on_status: Callable[[VehicleStatus], None] | None = None,
    console: OperatorConsole | None = None,
) -> GroundOutcome:
    """Prepare, start and watch a mission of vehicle processes. Returns a :class:`GroundOutcome`
    once every vehicle is done or lost; raises :class:`MissionAbortedError` (after commanding
    every vehicle to land) when a vehicle failed or not all were ready in time. ``console``:
    the operator's typed commands, sent to this mission while it runs."""
    if scenario.bus.kind != "mqtt":
        raise RunnerError("the ground station talks to vehicle processes over MQTT")
    topics = scenario.bus.topics(scenario.name)
    async with (
        open_bus(scenario.bus, sender=Sender.ground(), client_id=f"{scenario.name}-ground") as bus,
        bus.subscribe(topics.all_status()) as heard,
    ):
        ground = GroundStation(scenario, bus, heard, on_status=on_status)
        return await ground.run(
            console, start_delay_s=start_delay_s, ready_timeout_s=ready_timeout_s
        )


class GroundStation:
    """The ground's side of the handshake (module docstring) over ``bus``, hearing the vehicles'
    statuses on ``heard``, phase by phase: :meth:`prepare`, :meth:`wait_ready` (the verdict:
    every vehicle ready, or the mission aborted), :meth:`start` and :meth:`watch` (until every
    vehicle is done or lost, the mission clock following the autopilots'), then
    :meth:`outcome`. ``unix_s`` is the UNIX clock the mission clock and the commands' times read
    (injectable for tests)."""

    def __init__(
        self,
        scenario: Scenario,
        bus: Bus,
        heard: Subscription,
        *,
        on_status: Callable[[VehicleStatus], None] | None = None,
        unix_s: Callable[[], float] = time.time,
    ) -> None:
        self.scenario, self.bus, self.heard = scenario, bus, heard
        self.on_status, self.unix_s = on_status, unix_s
        self.ids = {v.id for v in scenario.vehicles}
        self.topics = scenario.bus.topics(scenario.name)
        self.mission_id = uuid.uuid4().hex[:12]
        #: Every vehicle's latest status of this mission.
        self.latest: dict[int, VehicleStatus] = {}
        self.start_s: float | None = None
        self.clock_rate = 1.0
        #: From the start: the mission clock following the autopilots'.
        self.follower: ClockFollower | None = None
        self.wills = _Wills(rejoin_grace_s(scenario))

    async def run(
        self, console: OperatorConsole | None, *, start_delay_s: float, ready_timeout_s: float
    ) -> GroundOutcome:
        """Every phase in order; the prepare is cleared at the end, whatever happened."""
        timing = self.scenario.timing
        try:
            # Typed commands from the prepare on: vehicles obey land, return and stop before
            # the start too.
            async with serving(console, self.ids, self._send):
                await self.prepare()
                await self.wait_ready(ready_timeout_s)
                rate = await self.start(start_delay_s)
                await self.watch((start_delay_s + timing.steps * timing.step_s) / rate + 120.0)
        finally:
            # The prepare must not start the next vehicle process that connects.
            with contextlib.suppress(BusError):
                await self.bus.publish(self.topics.control(), b"", retain=True, timeout=2.0)
            counters = self.bus.auth_counters.as_dict()
        return self.outcome(counters)

    async def prepare(self) -> None:
        """Announce the mission: a retained ``prepare`` with its id."""
        await self.control(ControlCommand.PREPARE, self.unix_s())
        logger.info(
            "ground: mission %s prepared; waiting for %d vehicles", self.mission_id, len(self.ids)
        )

    async def wait_ready(self, timeout_s: float) -> None:
        """Until every vehicle is ready; raises :class:`MissionAbortedError`, every vehicle told
        to land, when one failed or not all were ready within ``timeout_s``."""
        try:
            await self.until(
                lambda: (
                    bool(self.states(ControllerState.FAILED))
                    or self.ids <= self.states(ControllerState.READY)
                ),
                timeout_s,
                "every vehicle ready",
            )
        except RunnerTimeoutError as error:
            missing = sorted(self.ids - self.states(ControllerState.READY))
            await self.control(ControlCommand.LAND, self.unix_s(), reason=f"not ready: {missing}")
            raise MissionAbortedError(
                f"mission aborted, every vehicle told to land: vehicles {missing} not "
                f"ready within {timeout_s:g} s"
            ) from error
        failed = sorted(self.states(ControllerState.FAILED))
        if failed:
            reasons = "; ".join(self.latest[i].detail for i in failed)
            await self.control(
                ControlCommand.LAND, self.unix_s(), reason=f"vehicle(s) {failed} failed"
            )
            raise MissionAbortedError(f"mission aborted, every vehicle told to land: {reasons}")

    async def start(self, start_delay_s: float) -> float:
        """``start``: k = 0 on the step grid ``start_delay_s`` (scaled) from now, the mission
        clock at the ready vehicles' autopilots' rate. Returns that rate."""
        step_s = self.scenario.timing.step_s
        rate = MissionTime.rate_for([self.latest[i].clock_rate or 1.0 for i in self.ids])
        reference_s = self.unix_s()
        start_s = math.ceil((reference_s + start_delay_s * rate) / step_s) * step_s
        self.start_s, self.clock_rate = start_s, rate
        mission_time = MissionTime(unix=self.unix_s)
        mission_time.set(rate, reference_s)
        self.follower = ClockFollower(mission_time)
        await self.control(
            ControlCommand.START, start_s, clock_rate=rate, clock_reference_s=reference_s
        )
        logger.info(
            "ground: mission %s starts at %.3f (clock rate %.4f)", self.mission_id, start_s, rate
        )
        return rate

    async def watch(self, timeout_s: float) -> None:
        """Until every vehicle is done or final. Ctrl-C / SIGTERM at the ground station lands
        the swarm. Not shielded: a second one cancels this send too, and the ground station
        stops at once."""
        try:
            await self.until(
                lambda: self.ids <= self.states(ControllerState.DONE, *FINAL_STATES),
                timeout_s,
                "every vehicle done",
            )
        except asyncio.CancelledError:
            with contextlib.suppress(BusError):
                await self.control(
                    ControlCommand.LAND, self.unix_s(), reason="ground station stopped"
                )
            logger.warning("ground: interrupted; every vehicle told to land")
            raise

    def outcome(self, counters: dict[str, int]) -> GroundOutcome:
        follower = self.follower
        return GroundOutcome(
            self.mission_id,
            self.start_s,
            self.clock_rate,
            self.latest,
            counters,
            dict(self.wills.drops),
            0 if follower is None else follower.changes,
            None if follower is None else follower.time.latest_rate,
        )

    async def control(self, command: ControlCommand, time_s: float, **fields: Any) -> None:
        """Publish ``command`` for this mission (retained: the prepare only)."""
        message = MissionControl(command, time_s, mission_id=self.mission_id, **fields)
        await self.bus.publish_message(
            self.topics.control(), message, retain=command is ControlCommand.PREPARE, timeout=5.0
        )

    async def _send(self, command: OperatorCommand) -> None:
        await publish_operator(
            self.bus, self.topics, command, self.mission_id, time_s=self.unix_s()
        )

    def states(self, *wanted: str) -> set[int]:
        return {i for i, s in self.latest.items() if s.state in wanted}

    def ours(self, status: VehicleStatus) -> bool:
        if status.mission_id == self.mission_id:
            return True
        # The last will has no mission id; after the start it can only be this mission's.
        return (
            status.mission_id is None
            and status.state == ControllerState.LOST
            and self.start_s is not None
            and status.vehicle_id in self.latest
        )

    def accept(self, status: VehicleStatus) -> bool:
        """Take ``status`` as its vehicle's latest (its clock rate to the follower); whether it
        changed anything (a final status stays, :func:`_final_already`)."""
        if _final_already(self.latest.get(status.vehicle_id), status):
            return False
        self.latest[status.vehicle_id] = status
        if self.follower is not None:
            self.follower.heard(status.vehicle_id, status.clock_rate, self.unix_s())
        if self.on_status is not None:
            self.on_status(status)
        return True

    def hear(self, topic: str, payload: bytes, now_s: float) -> bool:
        """Take in one message; whether it changed a vehicle's status."""
        status = _vehicle_status(self.topics, self.ids, topic, payload)
        if status is None or not self.ours(status):
            return False
        vehicle_id = status.vehicle_id
        if status.mission_id is None:  # its last will (ours: after the start, lost)
            if self.latest[vehicle_id].state not in (ControllerState.DONE, *FINAL_STATES):
                self.wills.add(status, now_s)
                logger.warning(
                    "ground: vehicle %s dropped off the bus (its last will); lost unless "
                    "heard again within %.1f s",
                    vehicle_id,
                    self.wills.grace_s,
                )
            return False
        # Its own status (a flying controller sends one every step): it is on the bus.
        self.wills.heard(vehicle_id)
        return self.accept(status)

    async def until(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Hear statuses (and believe wills once due) until ``condition`` holds after a change;
        raises :class:`RunnerTimeoutError` after ``timeout_s``. The timeout and the wills' grace
        count this process's own monotonic time (the event loop's), not the mission clock."""
        loop = asyncio.get_running_loop()
        deadline_s = loop.time() + timeout_s
        while True:
            changed = False
            for will in self.wills.due(loop.time()):
                changed = self.accept(will) or changed
            if changed and condition():
                return
            if loop.time() >= deadline_s:
                raise RunnerTimeoutError(what, timeout_s)
            wake_s = min(deadline_s, self.wills.next_due_s())
            try:
                topic, payload = await self.heard.receive(timeout=max(wake_s - loop.time(), 0.0))
            except BusTimeoutError:
                continue
            changed = self.hear(topic, payload, loop.time())
            await self.follow_clock()
            if changed and condition():
                return

    async def follow_clock(self) -> None:
        """Send the mission clock's change, if the follower has one due now."""
        change = self.follower.due(self.unix_s()) if self.follower is not None else None
        if change is None:
            return
        await self.control(
            ControlCommand.CLOCK,
            change.mission_s,
            clock_rate=change.rate,
            clock_reference_s=change.at_unix_s,
        )
        logger.warning(
            "ground: the autopilots' clocks run at %.4fx now: so does the mission clock, from %.3f",
            change.rate,
            change.at_unix_s,
        )


def _vehicle_status(
    topics: Topics, ids: set[int], topic: str, payload: bytes
) -> VehicleStatus | None:
    """The status of one of ``ids`` on its status ``topic``; None for an empty payload, or a
    status that does not decode or is about another vehicle than its topic's (the bus checked
    who signed for the topic, not what the body says)."""
    try:
        vehicle_id = topics.parse(topic).vehicle_id
    except TopicError:
        return None
    if vehicle_id not in ids or not payload:
        return None
    try:
        status = VehicleStatus.from_payload(payload)
    except MessageDecodeError as error:
        logger.warning("ground: skipping a status on %s: %s", topic, error)
        return None
    if status.vehicle_id != vehicle_id:
        logger.warning("ground: skipping a status of vehicle %s on %s", status.vehicle_id, topic)
        return None
    return status


def _final_already(last: VehicleStatus | None, status: VehicleStatus) -> bool:
    """Whether ``last`` was final (:data:`FINAL_STATES`) so ``status`` changes nothing: a lost
    vehicle stays lost; only its reason may still arrive (the controller's own status first)."""
    if last is None or last.state not in FINAL_STATES:
        return False
    return status.state != last.state or not status.detail or bool(last.detail)


async def wait_and_merge(
    scenario: Scenario, mission_dir: PathName, outcome: GroundOutcome, *, timeout_s: float = 20.0
) -> SimulationResult | None:
    """After the mission: wait (up to ``timeout_s``) for every vehicle that finished to write its
    ``steps.csv`` and for the range aid's truth under ``mission_dir``, then score the mission
    (:func:`.scoring.merge_mission`); None when there is no truth to score against.
    ``vehicles_disarmed_at_end`` counts the vehicles that reported done after landing."""

    mission_dir = Path(mission_dir)
    wanted = [mission_dir / "truth" / "truth.csv"] + [
        mission_dir / f"vehicle_{i}" / "summary.json"
        for i, status in outcome.statuses.items()
        if status.state == ControllerState.DONE
    ]
    # This process's own monotonic clock: a timeout on files other processes write.
    deadline = time.monotonic() + timeout_s
    while not all(path.exists() for path in wanted) and time.monotonic() < deadline:
        await asyncio.sleep(0.2)  # files written by other processes: nothing to wait on but disk
    result = merge_mission(scenario, mission_dir)
    if result is not None and scenario.flight.end_action == "land":
        landed = sum(status.state == ControllerState.DONE for status in outcome.statuses.values())
        result.extra_metrics["vehicles_disarmed_at_end"] = np.array([landed])
    return result


async def send_control(
    scenario: Scenario,
    command: ControlCommand | str,
    *,
    vehicle_id: int | None = None,
    reason: str | None = None,
    timeout_s: float = 5.0,
) -> str:
    """Send an operator command (hold, resume, land, return, stop) to the running mission of
    ``scenario`` (its id from the ground station's retained ``prepare``), for one vehicle or
    all. Returns the mission id; raises :class:`RunnerError` if no mission is running
    (:class:`.operator.OperatorInputError` if the command is not one)."""
    operator = operator_command(
        command, [v.id for v in scenario.vehicles], vehicle_id=vehicle_id, reason=reason
    )
    topics = scenario.bus.topics(scenario.name)
    async with (
        # The operator's commands are the ground station's (same role), under a login of their
        # own: with client ids bound to logins, the ground's would take the ground's connection.
        open_bus(
            scenario.bus,
            sender=Sender.ground(),
            client_id=f"{scenario.name}-operator",
            login=OPERATOR_USER,
        ) as bus,
        bus.subscribe(topics.control()) as control,
    ):
        try:
            prepare = await next_command(control, {ControlCommand.PREPARE}, timeout_s=timeout_s)
        except RunnerTimeoutError:
            raise RunnerError(_no_prepare(scenario, topics, bus.auth_counters, timeout_s)) from None
        await publish_operator(bus, topics, operator, prepare.mission_id, timeout_s=timeout_s)
    return prepare.mission_id or ""


def _no_prepare(
    scenario: Scenario, topics: Topics, counters: AuthCounters, timeout_s: float
) -> str:
    """Why no ground station's prepare came: none was there, or one was, signed with another key
    (the operator's then cannot command the mission either: the vehicles would drop it too)."""
    if counters.forged:
        return (
            f"the bus key does not match the mission's: {counters.forged} message(s) on "
            f"{topics.control()} were signed with another key and dropped; give control the "
            "mission's key (--bus-key-file, MISSION_BUS_KEY or bus.auth.key_file)"
        )
    return (
        f"no mission of {scenario.name} is running (no ground station's prepare on "
        f"{topics.control()} within {timeout_s:g} s)"
    )
