"""Fly a scenario: the bundled emulator (or real vehicles), the bus, the world's sensors and one
controller per vehicle, from take-off to landing.

Sequence: start the emulator and the world; connect every vehicle through one MAVSDK instance;
take off (each to its own altitude); every controller joins the mission clock and hovers on the
step grid, streaming setpoints, while OFFBOARD is entered; k = 0 is set on the grid
``flight.start_delay_s`` later; the controllers fly ``timing.steps`` steps; then every vehicle
still alive lands (or holds). Scenario events are scheduled relative to k = 0.

The operator commands the swarm as a ground station would (:mod:`.operator`): lines typed into
the process, and over an MQTT bus ``mission-runner control`` too (the mission is announced with
a retained ``prepare``, as ``ground`` does). ``hold`` / ``resume`` act on the controllers' next
step; ``land``, ``return`` and ``stop`` end a vehicle's mission. Whatever ends the flight early
(Ctrl-C cancelling it, an error) lands every vehicle still in the air first; a second
cancellation while they land stops at once.

Ground truth (the world's samples at every t_k) is used only to score the flight afterwards, into
the same :class:`mission_runner.sim.simulator.SimulationResult` the numeric simulator produces.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
import uuid
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..bus import (
    Bus,
    BusError,
    ControlCommand,
    MissionControl,
    Sender,
    lost_vehicle_will,
    open_bus,
)
from ..metrics import tracking_error
from ..outputs import bus_security
from ..records import ControllerState, Progress, StepRecord
from ..scenario import shape_schedule
from ..wiring import altitude_of, autopilot_params, emulator_config
from ..world import World
from .clock import EmulatorClock
from .controller import VehicleController, build_controller
from .errors import RunnerError
from .links import SAFE_STATE_TIMEOUT_S, MavsdkVehicle, connected_vehicles
from .operator import (
    ENDING_ACTIONS,
    OperatorCommand,
    OperatorConsole,
    fly_obeying,
    publish_operator,
    serving,
)
from .ports import ControllerBus, ControllerClock, ControllerLink, MessageSource
from .scoring import score_flight, worst_estimate

if TYPE_CHECKING:
    from sitl.clock import Clock, Participant
    from sitl.emulator import Emulator, EmulatorStats

    from ..config import Scenario
    from ..metrics import SimulationResult

#: Sees every controller step: ``(vehicle_id, record)``.
StepCallback = Callable[[int, StepRecord], None]
#: Sees the mission's end before the landing: ``(result, records, start_s)``, the score so far
#: (its series are final; what it says of the landing is not in yet), every controller's step
#: records and the mission clock at k = 0.
MissionEndCallback = Callable[["SimulationResult", Mapping[int, Sequence[StepRecord]], float], None]

logger = logging.getLogger(__name__)

LOCKSTEP_MAX_SPEED = 25.0
#: Lockstep speed while no controller holds the clock (take-off, hover, landing). MAVSDK hands
#: every telemetry message to Python in a callback that needs the GIL; with the emulator keeping
#: the event loop thread busy, those callbacks drain at a few hundred per second, and telemetry
#: sped up beyond that queues in front of the health and altitude updates the take-off waits for
#: (observed: 10 to 50 s stalls, or the 60 s take-off timeout, at 25x on a loaded 2-core machine).
PACED_SPEED = 10.0
PACE_PERIOD_S = 0.02
#: Above :data:`PACED_SPEED`, take-off and landing time may run ahead of the newest odometry the
#: runner has taken from every vehicle by this much simulated time: as fast as MAVSDK delivers,
#: never further ahead of it than a few telemetry periods.
PACE_LEAD_S = 0.25
#: The pacer's period while it follows what the runner has heard (its speed is at most
#: ``PACE_LEAD_S / HEARD_PACE_PERIOD_S`` beyond what the vehicles' telemetry allows).
HEARD_PACE_PERIOD_S = 0.004


class _ProgressAggregator:
    """Turns the controllers' per-vehicle step records into one :class:`Progress` per step."""

    def __init__(
        self,
        scenario: Scenario,
        world: World,
        emulator: Emulator,
        callback: Callable[[Progress], None],
    ) -> None:
        self.ids = [vehicle.id for vehicle in scenario.vehicles]
        self.steps = scenario.timing.steps
        self.world, self.emulator, self.callback = world, emulator, callback
        self.pending: dict[int, dict[int, StepRecord]] = {}  # step -> {vehicle_id: record}
        #: Vehicles no longer flown (lost, taken over, ended by the operator): no step awaits
        #: them, though the emulator still has them alive.
        self.left: set[int] = set()

    def leave(self, vehicle_id: int) -> None:
        self.left.add(vehicle_id)

    def __call__(self, vehicle_id: int, record: StepRecord) -> None:
        step = self.pending.setdefault(record.step, {})
        step[vehicle_id] = record
        alive = {i for i, a in zip(self.ids, self.emulator.truth.alive, strict=True) if a}
        if not alive - self.left <= step.keys():
            return
        records = self.pending.pop(record.step)
        sample = next((s for s in reversed(self.world.samples) if s.step == record.step), None)
        tracking = localization = float("nan")
        if sample is not None and sample.alive.any():
            tracking = float(tracking_error(sample.positions_m, sample.alive, sample.target_m))
            localization = worst_estimate(self.ids, records, sample)
        self.callback(
            Progress(
                record.step,
                self.steps,
                record.time_s,
                {i: r.state for i, r in sorted(records.items())},
                tracking,
                localization,
                sample,
            )
        )


@dataclass
class FlightOutcome:
    """A flown mission: the scored result, every controller's records, timings."""

    result: SimulationResult
    records: dict[int, list[StepRecord]]
    start_s: float
    wall_time_s: float
    mission_wall_time_s: float
    emulator_stats: EmulatorStats
    #: How each vehicle ended, as its controller saw it: ``{id: {"state", "detail"}}`` (state
    #: ``done``, ``lost``, ``taken_over``, or ``aborted`` by the operator's land, return or stop;
    #: the detail says why and what the runner saw of it last: landed and disarmed, or disarmed
    #: in the air at what height, :meth:`.links.MavsdkVehicle.ending`).
    vehicles: dict[int, dict[str, str]]
    #: What the bus and the controllers dropped (``outputs.bus_security``).
    bus_security: dict[str, Any] = field(default_factory=dict)


async def fly(
    scenario: Scenario,
    *,
    emulator_overrides: Mapping[str, Any] | None = None,
    on_step: StepCallback | None = None,
    on_progress: Callable[[Progress], None] | None = None,
    on_mission_end: MissionEndCallback | None = None,
    console: OperatorConsole | None = None,
) -> FlightOutcome:
    """Fly ``scenario`` on the bundled emulator. Returns a :class:`FlightOutcome`.

    on_step(vehicle_id, record) sees every controller step; on_progress(Progress) every step of
    the whole swarm; on_mission_end once the last step is flown (:data:`MissionEndCallback`);
    ``console`` gives the operator's typed commands (:mod:`.operator`).
    """
    if any(vehicle.url for vehicle in scenario.vehicles):
        raise RunnerError("vehicles with a url fly on real PX4: use 'mission-runner vehicle'")
    flight = InProcessFlight(
        scenario,
        emulator_overrides=emulator_overrides,
        on_step=on_step,
        on_progress=on_progress,
        on_mission_end=on_mission_end,
    )
    return await flight.fly(console)


class InProcessFlight:
    """One flight of :func:`fly`, phase by phase: :meth:`connect` (emulator, bus, world and the
    vehicles), :meth:`take_off`, :meth:`build_controllers`, :meth:`start_and_fly` (OFFBOARD, k = 0
    and the steps), :meth:`land`, then :meth:`score` and :meth:`outcome`. Its attributes are what
    one phase hands to the next; :meth:`fly` runs them in order and lands every vehicle still in
    the air when one fails."""

    emulator: Emulator
    bus: Bus
    ground: ControllerBus
    world: World

    def __init__(
        self,
        scenario: Scenario,
        *,
        emulator_overrides: Mapping[str, Any] | None = None,
        on_step: StepCallback | None = None,
        on_progress: Callable[[Progress], None] | None = None,
        on_mission_end: MissionEndCallback | None = None,
        unix_s: Callable[[], float] = time.time,
    ) -> None:
        self.scenario = scenario
        #: The UNIX clock the ground station's messages are stamped with (injectable for tests).
        self.unix_s = unix_s
        self.ids = [vehicle.id for vehicle in scenario.vehicles]
        overrides = {
            # Capped so that lockstep never floods MAVSDK (whose timers and callback queues run
            # on wall time) with telemetry; take-off and landing are held lower still (_paced).
            "clock": {
                "mode": scenario.flight.clock,
                "speed": scenario.flight.speed,
                "lockstep_max_speed": LOCKSTEP_MAX_SPEED,
            },
            **(emulator_overrides or {}),
        }
        self.config = emulator_config(scenario, **overrides)
        self.topics = scenario.bus.topics(scenario.name)
        self.mission_id = uuid.uuid4().hex[:12]
        self.on_step = on_step
        self.aggregator: _ProgressAggregator | None = None
        self.on_progress = on_progress
        self.on_mission_end = on_mission_end
        self.vehicles: list[MavsdkVehicle] = []
        self.controllers: list[VehicleController] = []
        #: Every bus that checks what it receives (their counters go into ``bus_security``).
        self.receivers: list[Bus] = []
        self.endings: dict[int, MissionControl | None] = {}
        self.records: dict[int, list[StepRecord]] = {}
        self.start_s = math.nan
        self.mission_wall_s = math.nan

    async def fly(self, console: OperatorConsole | None = None) -> FlightOutcome:
        """Every phase in order; a flight that fails or is cancelled lands its vehicles first."""
        # This process's own wall time, for the outcome's timings (not the mission's clock).
        started = time.perf_counter()
        async with contextlib.AsyncExitStack() as stack:
            before_mission = await self.connect(stack)
            try:
                await self.take_off()
                controls, clocks = await self.build_controllers(stack)
                await self.start_and_fly(console, before_mission, controls, clocks)
                if self.on_mission_end is not None:
                    self.on_mission_end(self.score(), self.records, self.start_s)
                await self.land()
            except BaseException as error:
                # Never leave a vehicle in the air undriven: whatever ended the flight (Ctrl-C
                # cancelling it, a failure), land every vehicle still ours first.
                await _land_everyone(self.emulator.clock, self.vehicles, self.controllers, error)
                raise
            stats = self.emulator.stats()
            result = self.score()
        return self.outcome(result, stats, time.perf_counter() - started)

    async def connect(self, stack: contextlib.AsyncExitStack) -> contextlib.AsyncExitStack:
        """The emulator, the bus, the ground station, the world and a link to every vehicle, on
        ``stack``. Returns the stack that paces the clock until the mission starts."""
        from sitl.emulator import Emulator  # noqa: PLC0415 - real-vehicle runs do not need it

        scenario = self.scenario
        self.emulator = emulator = await stack.enter_async_context(Emulator(self.config))
        before_mission = await stack.enter_async_context(contextlib.AsyncExitStack())
        await before_mission.enter_async_context(_paced(emulator.clock, heard=self.heard))
        # In-process, the one bus is the whole network: each member signs as itself through
        # its own view of it. Over MQTT the world is the range aid's client.
        in_process = scenario.bus.kind == "inprocess"
        self.bus = await stack.enter_async_context(
            open_bus(
                scenario.bus,
                sender=None if in_process else Sender.ranges(),
                client_id=f"{scenario.name}-world",
            )
        )
        self.receivers = [self.bus]
        self.ground = await stack.enter_async_context(
            _ground_station(self.bus, scenario, self.mission_id, self.unix_s)
        )
        self.world = await stack.enter_async_context(
            World.for_scenario(emulator, scenario, self.bus.as_sender(Sender.ranges()))
        )
        sysids = [endpoint.sysid for endpoint in emulator.endpoints]
        systems = await stack.enter_async_context(
            connected_vehicles(
                [e.mavsdk_url for e in emulator.endpoints],
                sysids,
                url_setting="flight.emulator.ports.api_remote_base",
            )
        )
        self.vehicles = [
            await stack.enter_async_context(MavsdkVehicle(systems[sysid], sysid))
            for sysid in sysids
        ]
        return before_mission

    def heard(self) -> float | None:
        """The vehicle time up to which the runner has every vehicle's odometry (pacing)."""
        return heard_until(self.vehicles) if self.vehicles else None

    async def take_off(self) -> None:
        """The scenario's autopilot parameters, then every vehicle to its own altitude."""
        params = autopilot_params(self.scenario)
        async with asyncio.TaskGroup() as group:
            for vehicle, vehicle_config in zip(self.vehicles, self.scenario.vehicles, strict=True):
                group.create_task(
                    _prepare(vehicle, params, altitude_of(self.scenario, vehicle_config)),
                    name=f"takeoff-{vehicle.system_id}",
                )

    async def build_controllers(
        self, stack: contextlib.AsyncExitStack
    ) -> tuple[list[MessageSource], list[EmulatorClock]]:
        """A controller per vehicle, each with its own bus and clock. Returns each one's control
        topic subscription and clock, in the vehicles' order."""
        if self.on_progress is not None:
            self.aggregator = _ProgressAggregator(
                self.scenario, self.world, self.emulator, self.on_progress
            )
        buses = await self._vehicle_buses(stack)
        # Each vehicle hears the operator as a vehicle process does: on its control topic.
        controls: list[MessageSource] = [
            await stack.enter_async_context(b.subscribe(self.topics.control())) for b in buses
        ]
        # Each controller's own view of the emulator's clock: a lockstep participant while
        # its controller flies.
        clocks = [
            EmulatorClock(
                self.emulator.clock,
                f"vehicle-{vehicle_id}",
                setpoints=self.emulator.autopilot(index),
            )
            for index, vehicle_id in enumerate(self.ids)
        ]
        self.controllers += _controllers(
            self.scenario, self.vehicles, buses, clocks, self._step_callback
        )
        return controls, clocks

    async def _vehicle_buses(self, stack: contextlib.AsyncExitStack) -> list[ControllerBus]:
        """Over MQTT every vehicle has its own client, as on a real swarm (one companion
        computer each, with its last will on its status topic); in-process each has its own
        view of the one bus (its own losses and delays under a link model)."""
        scenario = self.scenario
        if scenario.bus.kind != "mqtt":
            return [self.bus.as_sender(Sender.vehicle(i)) for i in self.ids]
        clients = [
            await stack.enter_async_context(
                open_bus(
                    scenario.bus,
                    sender=Sender.vehicle(vehicle_id),
                    client_id=f"{scenario.name}-vehicle-{vehicle_id}",
                    will=lost_vehicle_will(self.topics, vehicle_id, time_s=self.emulator.time_s),
                )
            )
            for vehicle_id in self.ids
        ]
        self.receivers += clients
        return list(clients)

    def _step_callback(self, vehicle_id: int, record: StepRecord) -> None:
        if self.on_step is not None:
            self.on_step(vehicle_id, record)
        if self.aggregator is not None:
            self.aggregator(vehicle_id, record)

    async def start_and_fly(
        self,
        console: OperatorConsole | None,
        before_mission: contextlib.AsyncExitStack,
        controls: Sequence[MessageSource],
        clocks: Sequence[EmulatorClock],
    ) -> None:
        """OFFBOARD for all, then k = 0 on the step grid ``flight.start_delay_s`` later; returns
        when every controller is done (its steps flown, or ended early)."""
        start: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        flight, step_s = self.scenario.flight, self.scenario.timing.step_s
        async with serving(console, self.ids, self._send), asyncio.TaskGroup() as group:
            flying = [
                group.create_task(
                    self._fly_vehicle(controller, vehicle, clock, control, start),
                    name=f"controller-{controller.vehicle_id}",
                )
                for controller, vehicle, clock, control in zip(
                    self.controllers, self.vehicles, clocks, controls, strict=True
                )
            ]
            async with asyncio.TaskGroup() as entering:
                for vehicle, controller in zip(self.vehicles, self.controllers, strict=True):
                    entering.create_task(
                        _enter_offboard(vehicle, controller.altitude_m),
                        name=f"offboard-{vehicle.system_id}",
                    )
            self.start_s = (
                math.ceil((self.emulator.time_s + flight.start_delay_s) / step_s) * step_s
            )
            self.world.start(self.start_s)
            mission_started = time.perf_counter()  # wall time, for the outcome's timings
            start.set_result(self.start_s)
            await before_mission.aclose()  # from here on the controllers pace the clock
        self.endings = {
            c.vehicle_id: task.result() for c, task in zip(self.controllers, flying, strict=True)
        }
        self.records = {c.vehicle_id: c.records for c in self.controllers}
        self.mission_wall_s = time.perf_counter() - mission_started

    async def _send(self, command: OperatorCommand) -> None:
        await publish_operator(
            self.ground, self.topics, command, self.mission_id, time_s=self.unix_s()
        )

    async def _fly_vehicle(
        self,
        controller: VehicleController,
        vehicle: MavsdkVehicle,
        clock: EmulatorClock,
        control: MessageSource,
        start: asyncio.Future[float],
    ) -> MissionControl | None:
        """One controller's flight (:func:`_fly_one`), then its vehicle's end if it ended
        early: what the operator commanded, or ``flight.on_lost`` for a lost one."""
        ending = await _fly_one(
            controller, clock, start, self.scenario.timing.steps, control, self.mission_id
        )
        if self.aggregator is not None:
            self.aggregator.leave(controller.vehicle_id)
        if ending is not None:
            await _end_vehicle(self.emulator.clock, vehicle, ENDING_ACTIONS[ending.command])
        elif controller.state == ControllerState.LOST:
            # Its setpoint stream ends with it (MAVSDK would re-send the last one for ever),
            # and it is put where a vehicle process puts a lost one.
            await _end_vehicle(self.emulator.clock, vehicle, self.scenario.flight.on_lost)
        return ending

    async def land(self) -> None:
        """``flight.end_action`` for every vehicle that flew its steps (not one lost, taken over
        or already ended by the operator), at take-off's pace."""
        async with _paced(self.emulator.clock, heard=self.heard), asyncio.TaskGroup() as group:
            for vehicle, controller in zip(self.vehicles, self.controllers, strict=True):
                if controller.state in (
                    ControllerState.LOST,
                    ControllerState.TAKEN_OVER,
                ):  # leave those be
                    continue
                if self.endings[controller.vehicle_id] is not None:  # the operator's already
                    continue
                group.create_task(
                    vehicle.finish(self.scenario.flight.end_action),
                    name=f"finish-{vehicle.system_id}",
                )

    def score(self) -> SimulationResult:
        """The flight against the world's truth (:func:`.scoring.score_flight`)."""
        emulator = self.emulator
        # Truth, for the score: a vehicle disarmed in the air fell; it did not land.
        fell = np.array([bool(emulator.autopilot(i).disarms_in_air) for i in range(len(self.ids))])
        landed = int(np.sum(~np.asarray(emulator.truth.armed) & ~fell))
        return score_flight(
            self.scenario,
            self.world.samples,
            self.records,
            landed,
            final_phases={c.vehicle_id: c.law.phase_rad for c in self.controllers},
            disarmed_in_air=int(np.sum(fell)),
        )

    def outcome(
        self, result: SimulationResult, stats: EmulatorStats, wall_time_s: float
    ) -> FlightOutcome:
        """The :class:`FlightOutcome`: the score, what the buses and gates dropped, how each
        vehicle ended."""
        messages: dict[str, int] = {}
        for receiver in self.receivers:
            for reason, count in receiver.auth_counters.as_dict().items():
                messages[reason] = messages.get(reason, 0) + count
        controllers = self.controllers
        security = bus_security(
            messages,
            {c.vehicle_id: c.range_gate.rejected for c in controllers if c.range_gate is not None},
            {
                c.vehicle_id: c.command_gate.rejected["command_speed"]
                for c in controllers
                if c.command_gate is not None
            },
        )
        ended = {
            c.vehicle_id: _how_it_ended(c, vehicle, self.endings[c.vehicle_id])
            for c, vehicle in zip(controllers, self.vehicles, strict=True)
        }
        return FlightOutcome(
            result=result,
            records=self.records,
            start_s=self.start_s,
            wall_time_s=wall_time_s,
            mission_wall_time_s=self.mission_wall_s,
            emulator_stats=stats,
            vehicles=ended,
            bus_security=security,
        )


def _how_it_ended(
    controller: VehicleController, vehicle: MavsdkVehicle, ending: MissionControl | None
) -> dict[str, str]:
    """The controller's end, and what the runner saw of the vehicle (:meth:`.ending`)."""
    seen = vehicle.ending()
    if ending is not None:
        reason = f" ({ending.reason})" if ending.reason else ""
        detail = f"{ending.command.value} by the operator{reason}"
        return {"state": ControllerState.ABORTED, "detail": f"{detail}; {seen}"}
    if controller.state in (ControllerState.LOST, ControllerState.TAKEN_OVER):
        why = vehicle.control_lost or "own odometry stopped"
        return {"state": controller.state, "detail": f"{why}; seen last: {seen}"}
    return {"state": ControllerState.DONE, "detail": seen}


@contextlib.asynccontextmanager
async def _ground_station(
    bus: Bus, scenario: Scenario, mission_id: str, unix_s: Callable[[], float] = time.time
) -> AsyncIterator[ControllerBus]:
    """Where the operator's commands are published from, signed as the ground station: this
    process's bus in-process; over MQTT a client of the ground's own (its broker login), which
    announces the mission with a retained ``prepare`` (how ``mission-runner control`` finds its
    id) and clears it at the end."""
    if scenario.bus.kind == "inprocess":
        yield bus.as_sender(Sender.ground())
        return
    topics = scenario.bus.topics(scenario.name)
    async with open_bus(
        scenario.bus, sender=Sender.ground(), client_id=f"{scenario.name}-ground"
    ) as ground:
        prepare = MissionControl(ControlCommand.PREPARE, unix_s(), mission_id=mission_id)
        await ground.publish_message(topics.control(), prepare, retain=True, timeout=5.0)
        try:
            yield ground
        finally:
            with contextlib.suppress(BusError):
                await ground.publish(topics.control(), b"", retain=True, timeout=2.0)


async def _end_vehicle(clock: Clock, vehicle: MavsdkVehicle, action: str) -> None:
    """This vehicle's mission ended early (the operator's land, return or stop, or its
    controller gave it up): command ``action``. Its controller has left the lockstep clock;
    while it lands, time is paced for MAVSDK as at take-off."""
    async with _paced(
        clock, name=f"pace-{vehicle.system_id}", heard=lambda: heard_until([vehicle])
    ):
        try:
            await vehicle.finish(action, timeout_s=SAFE_STATE_TIMEOUT_S)
        except RunnerError as error:
            logger.warning("vehicle %s: %s not done: %s", vehicle.system_id, action, error)


async def _land_everyone(
    clock: Clock,
    vehicles: Sequence[MavsdkVehicle],
    controllers: Sequence[VehicleController],
    error: BaseException,
) -> None:
    """Land every vehicle seen armed that is still the runner's (not taken over, not lost),
    each at most :data:`SAFE_STATE_TIMEOUT_S`. A cancellation while they land ends this at once:
    the vehicles are left to PX4's offboard-loss failsafe."""
    gone = {
        c.vehicle_id
        for c in controllers
        if c.state in (ControllerState.LOST, ControllerState.TAKEN_OVER)
    }
    landing = [
        v for v in vehicles if v.armed and v.control_lost is None and v.system_id not in gone
    ]
    if not landing:
        return
    why = "interrupted" if isinstance(error, asyncio.CancelledError) else f"{error!r}"
    logger.warning(
        "flight ended (%s): landing vehicles %s", why, ", ".join(str(v.system_id) for v in landing)
    )

    landed: list[int] = []

    async def land(vehicle: MavsdkVehicle) -> None:
        try:
            await vehicle.finish("land", timeout_s=SAFE_STATE_TIMEOUT_S)
        except RunnerError as failure:
            logger.warning("vehicle %s: not landed: %s", vehicle.system_id, failure)
        else:
            landed.append(vehicle.system_id)

    async with (
        _paced(clock, name="pace-landing", heard=lambda: heard_until(landing)),
        asyncio.TaskGroup() as group,
    ):
        for vehicle in landing:
            group.create_task(land(vehicle), name=f"land-{vehicle.system_id}")
    logger.warning("flight ended: landed and disarmed: %s", ", ".join(map(str, sorted(landed))))


async def _enter_offboard(vehicle: MavsdkVehicle, altitude_m: float) -> None:
    """OFFBOARD, then the climb to the vehicle's own altitude (its controller's altitude hold):
    ranges are 3-D, and a height difference cancels out of the estimator only while constant.
    Then the streams nobody reads stop, as in a vehicle process (each message costs the
    autopilot's encoding, MAVSDK's parsing and, in lockstep, this process's time)."""
    await vehicle.start_offboard()
    await vehicle.wait_altitude(altitude_m)
    await vehicle.quiet_unread_streams()


async def _prepare(
    vehicle: MavsdkVehicle, params: Mapping[str, float | int], altitude_m: float
) -> None:
    await vehicle.apply_params(params)
    await vehicle.take_off(altitude_m)


@contextlib.asynccontextmanager
async def _paced(
    clock: Clock,
    speed: float = PACED_SPEED,
    *,
    name: str = "pace",
    heard: Callable[[], float | None] | None = None,
) -> AsyncIterator[None]:
    """While the block runs, lockstep time advances at ``speed`` x wall time (a clock
    participant releasing ``speed * PACE_PERIOD_S`` beyond the current time every period; a late
    period slows it down, never bursts it), or faster while ``heard()`` (the vehicle time up to
    which the runner has taken every vehicle's telemetry) keeps up: then up to
    :data:`PACE_LEAD_S` beyond it. A no-op in real time."""
    if clock.mode != "lockstep":
        yield
        return
    period_s = PACE_PERIOD_S if heard is None else HEARD_PACE_PERIOD_S

    async def pace(participant: Participant) -> None:
        released = clock.now_s()
        while True:
            floor_s = clock.now_s() + speed * period_s
            seen_s = heard() if heard is not None else None
            following = floor_s if seen_s is None else seen_s + PACE_LEAD_S
            released = max(released, floor_s, following)
            participant.acted(released)
            await asyncio.sleep(period_s)

    # The group owns the pacer: should it fail (a ClockError: dropped after a stall), the block
    # is cancelled and the error raised, not lost with the task while time runs unpaced.
    async with clock.participant(name) as participant, asyncio.TaskGroup() as group:
        task = group.create_task(pace(participant), name="lockstep-pace")
        try:
            yield
        finally:
            task.cancel()


def heard_until(vehicles: Sequence[MavsdkVehicle]) -> float | None:
    """The vehicle time up to which the runner has taken odometry from every one of
    ``vehicles`` (the oldest of their newest samples); None before each has sent one."""
    oldest: float | None = None
    for vehicle in vehicles:
        sample = vehicle.track.latest
        if sample is None:
            return None
        oldest = sample.time_s if oldest is None else min(oldest, sample.time_s)
    return oldest


async def _fly_one(  # noqa: PLR0917
    controller: VehicleController,
    clock: EmulatorClock,
    start: asyncio.Future[float],
    steps: int,
    control: MessageSource,
    mission_id: str,
) -> MissionControl | None:
    """One controller from hover to the end, obeying the operator from k = 0; returns the land,
    return or stop that ended it early, if any. It leaves the mission clock (``clock``, the one
    it was built with) as soon as it is done, so a lost vehicle (or one the operator ended)
    never holds the others' lockstep time."""
    async with clock:
        start_s = await controller.hover_until(start)
        return await fly_obeying(
            controller, controller.run(start_s, steps), control, mission_id=mission_id
        )


def _controllers(
    scenario: Scenario,
    vehicles: Sequence[ControllerLink],
    buses: Sequence[ControllerBus],
    clocks: Sequence[ControllerClock],
    on_step: StepCallback,
) -> list[VehicleController]:
    shape = shape_schedule(scenario)
    return [
        build_controller(
            scenario,
            config,
            link=vehicle,
            bus=bus,
            clock=clock,
            on_step=on_step,
            shape=shape,
        )
        for config, vehicle, bus, clock in zip(
            scenario.vehicles, vehicles, buses, clocks, strict=True
        )
    ]
