"""``sitl --scenario FILE``: the vehicles, the target and the UWB ranging of a mission scenario,
for controllers that run in other processes (``mission-runner vehicle``) and talk over MQTT.

Vehicles are placed as the scenario says; the world publishes on the scenario's bus in UNIX time
(the emulator's SYSTEM_TIME epoch), so controllers on other machines share its clock. k = 0 is set
by a ``start`` :class:`MissionControl` on ``<prefix>/control`` (its ``time_s``), or by
``--start-after S`` seconds from launch.
"""

import asyncio
import contextlib
import logging
import math

from mission_runner.bus import ControlCommand, MissionControl, open_bus
from mission_runner.config import emulator_config

from .emulator import Emulator
from .world import World

logger = logging.getLogger(__name__)


@contextlib.asynccontextmanager
async def scenario_world(scenario, *, overrides=None, start_after_s=None):
    """Emulator + world for ``scenario``; yields ``(emulator, world)``. Owns its tasks."""
    step_s = scenario.timing.step_s
    config = emulator_config(scenario, **(overrides or {}))
    topics = scenario.bus.topics(scenario.name)
    async with contextlib.AsyncExitStack() as stack:
        emulator = await stack.enter_async_context(Emulator(config))
        offset_s = emulator.autopilot(0).unix_epoch_start_us / 1e6
        bus = await stack.enter_async_context(
            open_bus(scenario.bus, client_id=f"{scenario.name}-sitl-world")
        )
        world = await stack.enter_async_context(
            World.for_scenario(emulator, scenario, bus, time_offset_s=offset_s)
        )
        control = await stack.enter_async_context(bus.subscribe(topics.control()))
        async with asyncio.TaskGroup() as group:
            starter = None
            if start_after_s is not None:
                start_s = math.ceil((emulator.time_s + offset_s + start_after_s) / step_s) * step_s
                world.start(start_s)
            else:
                starter = group.create_task(
                    _start_on_command(control, world, step_s), name="world-start"
                )
            try:
                yield emulator, world
            finally:
                if starter is not None:
                    starter.cancel()


async def _start_on_command(control, world, step_s):
    async for _, message in control.messages(MissionControl):
        if message.command is ControlCommand.START and world.start_s is None:
            start_s = math.ceil(message.time_s / step_s - 1e-9) * step_s
            logger.info("world: mission k = 0 at UNIX time %.3f", start_s)
            world.start(start_s)
