"""A swarm as separate processes: one controller per vehicle (one companion computer each), and a
ground station, talking only over MQTT and sharing UNIX time.

- :func:`run_vehicle` (``mission-runner vehicle CONFIG --id N``): connects to its vehicle through
  MAVSDK (the scenario's ``url``, or ``--url``), takes off, enters OFFBOARD hovering on the step
  grid, reports ``ready`` on its status topic, waits for the ground station's ``start``, flies
  the steps and lands (or holds).
- :func:`run_ground` (``mission-runner ground CONFIG``): waits until every vehicle is ready,
  publishes ``start`` with k = 0 on the step grid a little later, shows progress, and returns
  when every vehicle is done (or lost).

The vehicles may be real PX4 or the emulator started with ``sitl --scenario CONFIG`` (whose world
publishes UWB ranges and target observations on the same bus in UNIX time).
"""

import asyncio
import contextlib
import logging
import math
import time

import numpy as np

from ..bus import (
    BusError,
    ControlCommand,
    MissionControl,
    VehicleStatus,
    lost_vehicle_will,
    open_bus,
)
from ..enclosing import VehicleEnclosing
from ..scenario import shape_matrices
from ..sim.simulator import algorithm_params
from .clock import WallClock
from .controller import ControllerSettings, VehicleController
from .errors import RunnerError, RunnerTimeoutError
from .links import MavsdkVehicle, connected_vehicles

logger = logging.getLogger(__name__)

DEFAULT_API_PORT_BASE = 14540


def default_url(scenario, vehicle_id):
    """Where vehicle ``vehicle_id`` is when the scenario gives no url: PX4 SITL's (and the
    emulator's) API port for its instance."""
    index = [v.id for v in scenario.vehicles].index(vehicle_id)
    return f"udpin://0.0.0.0:{DEFAULT_API_PORT_BASE + index}"


async def run_vehicle(scenario, vehicle_id, *, url=None, ready_timeout_s=120.0, on_step=None):
    """Fly vehicle ``vehicle_id`` of ``scenario`` as its own process. Returns its step records."""
    if scenario.bus.kind != "mqtt":
        raise RunnerError("a vehicle process talks to the others over MQTT: set bus.kind: mqtt")
    ids = [v.id for v in scenario.vehicles]
    if vehicle_id not in ids:
        raise RunnerError(f"vehicle {vehicle_id} is not in the scenario (ids {ids})")
    config = scenario.vehicles[ids.index(vehicle_id)]
    url = url or config.url or default_url(scenario, vehicle_id)
    step_s = scenario.timing.step_s
    topics = scenario.bus.topics(scenario.name)
    altitude = config.altitude_m or scenario.flight.altitude_m
    shapes = shape_matrices(scenario.algorithm.shape, np.arange(scenario.timing.steps + 2) * step_s)
    async with contextlib.AsyncExitStack() as stack:
        systems = await stack.enter_async_context(connected_vehicles([url], [vehicle_id]))
        vehicle = await stack.enter_async_context(
            MavsdkVehicle(systems[vehicle_id], vehicle_id, sample_time_s=lambda ms: math.nan)
        )
        vehicle.use_time_offset(await vehicle.boot_to_unix_offset_s())
        bus = await stack.enter_async_context(
            open_bus(
                scenario.bus,
                client_id=f"{scenario.name}-vehicle-{vehicle_id}",
                will=lost_vehicle_will(topics, vehicle_id, time_s=time.time()),
            )
        )
        control = await stack.enter_async_context(bus.subscribe(topics.control()))
        await vehicle.take_off(altitude)
        clock = WallClock()
        controller = VehicleController(
            vehicle_id=vehicle_id,
            vehicle_ids=ids,
            law=VehicleEnclosing(
                algorithm_params(scenario),
                vehicle_id,
                ids,
                config.initial_phase_rad,
                config.omega_rad_s or scenario.algorithm.omega_rad_s,
            ),
            senses_target=config.senses_target,
            link=vehicle,
            bus=bus,
            topics=topics,
            clock=clock,
            settings=ControllerSettings(
                step_s=step_s,
                step_deadline_s=scenario.flight.step_deadline_s,
                silence_timeout_s=scenario.flight.silence_timeout_s,
                member_timeout_steps=scenario.flight.member_timeout_steps,
                max_horizontal_speed_m_s=config.speed_limit_m_s,
                max_vertical_speed_m_s=scenario.flight.max_vertical_speed_m_s,
                velocity_lead_s=scenario.flight.velocity_lead_s,
            ),
            shape=lambda k: shapes[min(k, len(shapes) - 1)],
            altitude_m=altitude,
            on_step=on_step,
        )
        start = asyncio.get_running_loop().create_future()
        async with asyncio.TaskGroup() as group:
            hovering = group.create_task(
                controller.hover_until(start), name=f"vehicle-{vehicle_id}-hover"
            )
            await vehicle.start_offboard()
            await _publish_status(bus, topics, vehicle_id, "ready")
            try:
                start.set_result(await _start_time(control, ready_timeout_s))
            except BaseException:
                hovering.cancel()
                raise
        records = await controller.run(start.result(), scenario.timing.steps)
        if controller.state != "lost":
            await vehicle.finish(scenario.flight.end_action)
        await _publish_status(bus, topics, vehicle_id, "done", step=len(records))
    return records


async def _start_time(control, timeout_s):
    try:
        async with asyncio.timeout(timeout_s):
            async for _, message in control.messages(MissionControl):
                if message.command is ControlCommand.START:
                    return message.time_s
    except TimeoutError:
        raise RunnerTimeoutError("the ground station's start command", timeout_s) from None
    raise RunnerError("the bus closed before the start command")


async def _publish_status(bus, topics, vehicle_id, state, step=0):
    status = VehicleStatus(vehicle_id, time.time(), state, step, state == "following", "")
    try:
        await bus.publish_message(topics.status(vehicle_id), status, retain=True, timeout=2.0)
    except BusError as error:
        logger.warning("vehicle %s: status %s not published: %s", vehicle_id, state, error)


async def run_ground(scenario, *, start_delay_s=2.0, ready_timeout_s=180.0, on_status=None):
    """Start the mission when every vehicle is ready; return ``{id: last status}`` once every
    vehicle is done or lost."""
    if scenario.bus.kind != "mqtt":
        raise RunnerError("the ground station talks to vehicle processes over MQTT")
    ids = {v.id for v in scenario.vehicles}
    topics = scenario.bus.topics(scenario.name)
    step_s = scenario.timing.step_s
    duration_s = scenario.timing.steps * step_s
    latest = {}
    async with (
        open_bus(scenario.bus, client_id=f"{scenario.name}-ground") as bus,
        bus.subscribe(topics.all_status()) as statuses,
    ):

        async def until(condition, timeout_s, what):
            try:
                async with asyncio.timeout(timeout_s):
                    async for _, status in statuses.messages(VehicleStatus):
                        latest[status.vehicle_id] = status
                        if on_status is not None:
                            on_status(status)
                        if condition():
                            return
            except TimeoutError:
                raise RunnerTimeoutError(what, timeout_s) from None

        def all_in(*states):
            return ids <= {i for i, s in latest.items() if s.state in states}

        await until(lambda: all_in("ready", "hovering"), ready_timeout_s, "every vehicle ready")
        start_s = math.ceil((time.time() + start_delay_s) / step_s) * step_s
        await bus.publish_message(
            topics.control(), MissionControl(ControlCommand.START, start_s), timeout=5.0
        )
        logger.info("ground: mission starts at UNIX %.3f", start_s)
        await until(
            lambda: all_in("done", "lost"),
            start_delay_s + duration_s + 120.0,
            "every vehicle done",
        )
    return latest
