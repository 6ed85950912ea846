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

    def __init__(self, bus: Bus, topics: Topics, run: VehicleRun) -> None:
        self.bus, self.topics, self.run = bus, topics, run
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
            time.time(),
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
    if scenario.bus.kind != "mqtt":
        raise RunnerError("a vehicle process talks to the others over MQTT: set bus.kind: mqtt")
    ids = [v.id for v in scenario.vehicles]
    if vehicle_id not in ids:
        raise RunnerError(f"vehicle {vehicle_id} is not in the scenario (ids {ids})")
    config = scenario.vehicles[ids.index(vehicle_id)]
    url = url or config.url or default_url(scenario, vehicle_id)
    topics = scenario.bus.topics(scenario.name)
    mission_time = MissionTime()
    run = run or VehicleRun(vehicle_id)
    async with contextlib.AsyncExitStack() as stack:
        systems = await stack.enter_async_context(
            connected_vehicles(
                [url], [vehicle_id], url_setting=f"--url or vehicles[{ids.index(vehicle_id)}].url"
            )
        )
        vehicle = await stack.enter_async_context(MavsdkVehicle(systems[vehicle_id], vehicle_id))
        mapping = await vehicle.follow_clock(mission_time)
        bus = await stack.enter_async_context(
            open_bus(
                scenario.bus,
                sender=Sender.vehicle(vehicle_id),
                client_id=f"{scenario.name}-vehicle-{vehicle_id}",
                will=lost_vehicle_will(topics, vehicle_id, time_s=time.time()),
            )
        )
        control = await stack.enter_async_context(bus.subscribe(topics.control()))
        controller_bus = await stack.enter_async_context(flight_bus(scenario, vehicle_id, bus))
        report = _Reporter(bus, topics, run)
        await report(ControllerState.WAITING, detail="waiting for the ground station's prepare")
        prepare = await next_command(control, {ControlCommand.PREPARE}, timeout_s=ready_timeout_s)
        run.mission_id = prepare.mission_id
        try:
            run.params = await vehicle.apply_params(autopilot_params(scenario))
            await vehicle.take_off(altitude_of(scenario, config))
        except RunnerError as error:
            await report(ControllerState.FAILED, detail=str(error))
            with contextlib.suppress(RunnerError):
                await vehicle.finish("land", timeout_s=SAFE_STATE_TIMEOUT_S)
            raise
        controller = build_controller(
            scenario,
            config,
            link=vehicle,
            bus=controller_bus,
            clock=WallClock(mission_time),
            on_step=on_step,
        )
        report.controller = controller
        controller.autopilot_clock_rate = mapping.recent_boot_rate
        try:
            await _fly(scenario, vehicle, controller, control, report, run, mapping, mission_time)
        except BaseException as error:
            # Never leave a vehicle in the air undriven: whatever ended the mission, command the
            # configured safe state (PX4's offboard-loss failsafe covers a dead process).
            action = scenario.flight.on_lost
            logger.warning(
                "vehicle %s: mission ended (%s): %s", vehicle_id, error_reason(error), action
            )
            if vehicle.control_lost is None:  # a vehicle someone else flies is theirs
                with contextlib.suppress(RunnerError):
                    await asyncio.shield(vehicle.finish(action, timeout_s=SAFE_STATE_TIMEOUT_S))
            else:  # its setpoint stream ended when it was taken: see that it did
                await vehicle.stream_ended()
            if run.state not in FINAL_STATES:
                await report(ControllerState.LOST, detail=f"mission ended: {error_reason(error)}")
            raise
        finally:
            run.records = controller.records
            run.skipped_steps = controller.skipped_steps
            run.bus_messages = bus.auth_counters.as_dict()
            if controller.range_gate is not None:
                run.ranges_rejected = dict(controller.range_gate.rejected)
            if controller.command_gate is not None:
                run.commands_rejected = controller.command_gate.rejected["command_speed"]
            run.autopilot_clock_rate = mapping.fit.boot_rate
            run.setpoints_scale_bounded = vehicle.scale_bounded_setpoints
            run.clock_residual_s = mapping.fit.residual_s
    return run


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


async def _fly(  # noqa: PLR0917
    scenario: Scenario,
    vehicle: MavsdkVehicle,
    controller: VehicleController,
    control: Subscription,
    report: _Reporter,
    run: VehicleRun,
    mapping: ClockMapping,
    mission_time: MissionTime,
) -> None:
    steps = scenario.timing.steps
    controller.mission_id = run.mission_id
    start = asyncio.get_running_loop().create_future()
    async with asyncio.TaskGroup() as group:
        hovering = group.create_task(
            controller.hover_until(start), name=f"vehicle-{run.vehicle_id}-hover"
        )
        try:
            await vehicle.start_offboard()
            await vehicle.wait_altitude(controller.altitude_m)
            await vehicle.quiet_unread_streams()
            command = await _until_start(control, report, run, mapping, scenario)
        except BaseException:
            hovering.cancel()
            raise
        if command.command is not ControlCommand.START:
            hovering.cancel()
            await _abort(vehicle, report, run, scenario, command)
            return
        freeze_heap()
        rate = command.clock_rate or 1.0
        mission_time.set(rate, command.clock_reference_s or command.time_s)
        run.clock_rate, run.start_s = rate, command.time_s
        controller.mission_id = run.mission_id
        start.set_result(command.time_s)
    # The controller flies its steps unless the operator's land, return or stop for this vehicle
    # ends them (a controller failure propagates and lands it, see run_vehicle).
    ending = await fly_obeying(
        controller,
        controller.run(run.start_s, steps),
        control,
        mission_id=run.mission_id,
        mission_time=mission_time,
    )
    if ending is not None:
        await _abort(vehicle, report, run, scenario, ending)
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
            await vehicle.finish(scenario.flight.on_lost, timeout_s=SAFE_STATE_TIMEOUT_S)
        return
    await vehicle.finish(scenario.flight.end_action)
    await report(ControllerState.DONE, step=len(controller.records))


async def _abort(
    vehicle: MavsdkVehicle,
    report: _Reporter,
    run: VehicleRun,
    scenario: Scenario,
    command: MissionControl,
) -> None:
    detail = f"mission aborted by the ground station: {command.reason or command.command.value}"
    logger.warning("vehicle %s: %s", run.vehicle_id, detail)
    await report(ControllerState.ABORTED, detail=detail)
    action = ENDING_ACTIONS.get(command.command, scenario.flight.on_lost)
    await vehicle.finish(action, timeout_s=SAFE_STATE_TIMEOUT_S)


async def _until_start(
    control: Subscription,
    report: _Reporter,
    run: VehicleRun,
    mapping: ClockMapping,
    scenario: Scenario,
) -> MissionControl:
    """Report ready (again for every new prepare) until this mission's start, or a land, return
    or stop for this vehicle."""
    wanted = {ControlCommand.PREPARE, ControlCommand.START, *ENDING_ACTIONS}
    while True:
        await report(ControllerState.READY, clock_rate=mapping.recent_boot_rate())
        command = await next_command(control, wanted)
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
    ids = {v.id for v in scenario.vehicles}
    topics = scenario.bus.topics(scenario.name)
    step_s = scenario.timing.step_s
    duration_s = scenario.timing.steps * step_s
    mission_id = uuid.uuid4().hex[:12]
    latest: dict[int, VehicleStatus] = {}
    started: dict[str, float | None] = {"at": None}
    clock: dict[str, ClockFollower] = {}  # from the start: the mission clock following them
    wills = _Wills(rejoin_grace_s(scenario))
    async with (
        open_bus(scenario.bus, sender=Sender.ground(), client_id=f"{scenario.name}-ground") as bus,
        bus.subscribe(topics.all_status()) as heard,
    ):

        async def control(command: ControlCommand, time_s: float, **fields: Any) -> None:
            message = MissionControl(command, time_s, mission_id=mission_id, **fields)
            await bus.publish_message(
                topics.control(), message, retain=command is ControlCommand.PREPARE, timeout=5.0
            )

        def ours(status: VehicleStatus) -> bool:
            if status.mission_id == mission_id:
                return True
            # The last will has no mission id; after the start it can only be this mission's.
            return (
                status.mission_id is None
                and status.state == ControllerState.LOST
                and started["at"] is not None
                and status.vehicle_id in latest
            )

        def accept(status: VehicleStatus) -> bool:
            if _final_already(latest.get(status.vehicle_id), status):
                return False
            latest[status.vehicle_id] = status
            if "follower" in clock:
                clock["follower"].heard(status.vehicle_id, status.clock_rate, time.time())
            if on_status is not None:
                on_status(status)
            return True

        def hear(topic: str, payload: bytes, now_s: float) -> bool:
            """Take in one message; whether it changed a vehicle's status."""
            status = _vehicle_status(topics, ids, topic, payload)
            if status is None or not ours(status):
                return False
            vehicle_id = status.vehicle_id
            if status.mission_id is None:  # its last will (ours: after the start, lost)
                if latest[vehicle_id].state not in (ControllerState.DONE, *FINAL_STATES):
                    wills.add(status, now_s)
                    logger.warning(
                        "ground: vehicle %s dropped off the bus (its last will); lost unless "
                        "heard again within %.1f s",
                        vehicle_id,
                        wills.grace_s,
                    )
                return False
            # Its own status (a flying controller sends one every step): it is on the bus.
            wills.heard(vehicle_id)
            return accept(status)

        async def until(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
            loop = asyncio.get_running_loop()
            deadline_s = loop.time() + timeout_s
            while True:
                changed = False
                for will in wills.due(loop.time()):
                    changed = accept(will) or changed
                if changed and condition():
                    return
                if loop.time() >= deadline_s:
                    raise RunnerTimeoutError(what, timeout_s)
                wake_s = min(deadline_s, wills.next_due_s())
                try:
                    topic, payload = await heard.receive(timeout=max(wake_s - loop.time(), 0.0))
                except BusTimeoutError:
                    continue
                changed = hear(topic, payload, loop.time())
                await follow_clock()
                if changed and condition():
                    return

        async def follow_clock() -> None:
            change = clock["follower"].due(time.time()) if "follower" in clock else None
            if change is None:
                return
            await control(
                ControlCommand.CLOCK,
                change.mission_s,
                clock_rate=change.rate,
                clock_reference_s=change.at_unix_s,
            )
            logger.warning(
                "ground: the autopilots' clocks run at %.4fx now: so does the mission clock, "
                "from %.3f",
                change.rate,
                change.at_unix_s,
            )

        def states(*wanted: str) -> set[int]:
            return {i for i, s in latest.items() if s.state in wanted}

        async def send(command: OperatorCommand) -> None:
            await publish_operator(bus, topics, command, mission_id)

        try:
            # Typed commands from the prepare on: vehicles obey land, return and stop before
            # the start too.
            async with serving(console, ids, send):
                await control(ControlCommand.PREPARE, time.time())
                logger.info(
                    "ground: mission %s prepared; waiting for %d vehicles", mission_id, len(ids)
                )
                try:
                    await until(
                        lambda: (
                            bool(states(ControllerState.FAILED))
                            or ids <= states(ControllerState.READY)
                        ),
                        ready_timeout_s,
                        "every vehicle ready",
                    )
                except RunnerTimeoutError as error:
                    missing = sorted(ids - states(ControllerState.READY))
                    await control(ControlCommand.LAND, time.time(), reason=f"not ready: {missing}")
                    raise MissionAbortedError(
                        f"mission aborted, every vehicle told to land: vehicles {missing} not "
                        f"ready within {ready_timeout_s:g} s"
                    ) from error
                failed = sorted(states(ControllerState.FAILED))
                if failed:
                    reasons = "; ".join(latest[i].detail for i in failed)
                    await control(
                        ControlCommand.LAND, time.time(), reason=f"vehicle(s) {failed} failed"
                    )
                    raise MissionAbortedError(
                        f"mission aborted, every vehicle told to land: {reasons}"
                    )
                rate = MissionTime.rate_for([latest[i].clock_rate or 1.0 for i in ids])
                reference_s = time.time()
                start_s = math.ceil((reference_s + start_delay_s * rate) / step_s) * step_s
                started["at"] = start_s
                mission_time = MissionTime()
                mission_time.set(rate, reference_s)
                clock["follower"] = ClockFollower(mission_time)
                await control(
                    ControlCommand.START,
                    start_s,
                    clock_rate=rate,
                    clock_reference_s=reference_s,
                )
                logger.info(
                    "ground: mission %s starts at %.3f (clock rate %.4f)", mission_id, start_s, rate
                )
                try:
                    await until(
                        lambda: ids <= states(ControllerState.DONE, *FINAL_STATES),
                        (start_delay_s + duration_s) / rate + 120.0,
                        "every vehicle done",
                    )
                except asyncio.CancelledError:
                    # Ctrl-C / SIGTERM at the ground station lands the swarm. Not shielded: a
                    # second one cancels this send too, and the ground station stops at once.
                    with contextlib.suppress(BusError):
                        await control(
                            ControlCommand.LAND, time.time(), reason="ground station stopped"
                        )
                    logger.warning("ground: interrupted; every vehicle told to land")
                    raise
        finally:
            # The prepare must not start the next vehicle process that connects.
            with contextlib.suppress(BusError):
                await bus.publish(topics.control(), b"", retain=True, timeout=2.0)
            counters = bus.auth_counters.as_dict()
    follower = clock.get("follower")
    return GroundOutcome(
        mission_id,
        started["at"],
        rate,
        latest,
        counters,
        dict(wills.drops),
        0 if follower is None else follower.changes,
        None if follower is None else follower.time.latest_rate,
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
