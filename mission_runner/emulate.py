"""``mission-runner emulate CONFIG``: the emulated vehicles, the target and the UWB ranging of a
mission scenario, for controllers that run in other processes (``mission-runner vehicle``) and
talk over MQTT.

Vehicles are placed as the scenario says; the world publishes on the scenario's bus in UNIX time
(the emulator's SYSTEM_TIME epoch), so controllers on other machines share its clock. k = 0 is set
by the ground station's ``start`` (:mod:`mission_runner.runner.handshake`), or by
``--start-after S`` seconds from launch.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import sys
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING

import yaml
from pydantic import ValidationError

from sitl import cli as sitl_cli
from sitl.emulator import Emulator

from .bus import Sender, open_bus
from .bus.cli_options import with_bus_access
from .checks import load_scenario
from .errors import ConfigError
from .metrics import tracking_error
from .runner.handshake import start_command
from .wiring import emulator_config
from .world.world import World

if TYPE_CHECKING:
    from sitl.config import EmulatorConfig

    from .bus import Subscription
    from .config import Scenario

logger = logging.getLogger(__name__)


@contextlib.asynccontextmanager
async def emulated_world(
    scenario: Scenario, config: EmulatorConfig, *, start_after_s: float | None = None
) -> AsyncIterator[tuple[Emulator, World]]:
    """Emulator (``config``, an ``EmulatorConfig``) + world for ``scenario``; yields
    ``(emulator, world)``. Owns its tasks."""
    step_s = scenario.timing.step_s
    topics = scenario.bus.topics(scenario.name)
    async with contextlib.AsyncExitStack() as stack:
        emulator = await stack.enter_async_context(Emulator(config))
        offset_s = emulator.autopilot(0).unix_epoch_start_us / 1e6
        bus = await stack.enter_async_context(
            open_bus(
                scenario.bus, sender=Sender.ranges(), client_id=f"{scenario.name}-emulated-world"
            )
        )
        world = await stack.enter_async_context(
            World.for_scenario(emulator, scenario, bus, time_offset_s=offset_s)
        )
        if start_after_s is not None:
            world.start(math.ceil((emulator.time_s + offset_s + start_after_s) / step_s) * step_s)
        else:
            control = await stack.enter_async_context(bus.subscribe(topics.control()))
            group = await stack.enter_async_context(asyncio.TaskGroup())
            starter = group.create_task(_start_on_command(control, world), name="world-start")
            stack.callback(starter.cancel)
        yield emulator, world


async def _start_on_command(control: Subscription, world: World) -> None:
    start = await start_command(control)
    start_s = math.ceil(start.time_s / world.step_s - 1e-9) * world.step_s
    logger.info("world: mission k = 0 at UNIX time %.3f", start_s)
    world.start(start_s)


def command(arguments: argparse.Namespace) -> int:
    """Run the scenario's emulated world until SIGINT/SIGTERM; exit code 0."""
    scenario = with_bus_access(load_scenario(arguments.scenario, flying=True), arguments)
    source = f"emulator settings ({arguments.config or 'command line'})"
    try:
        options = sitl_cli.load_config(arguments)
        config = emulator_config(
            scenario,
            ports=options.ports.model_dump(),
            clock=options.clock.model_dump(),
            tlog_dir=options.tlog_dir,
            **sitl_cli.fidelity_overrides(options, dict(scenario.flight.emulator or {})),
        )
    except ValidationError as error:
        problems = [(".".join(map(str, e["loc"])), e["msg"]) for e in error.errors()]
        raise ConfigError(source, problems) from None
    except (OSError, ValueError, yaml.YAMLError) as error:
        raise ConfigError(source, [("", str(error))]) from None
    asyncio.run(_serve(scenario, config, arguments.start_after))
    return 0


async def _serve(scenario: Scenario, config: EmulatorConfig, start_after_s: float | None) -> None:
    async with emulated_world(scenario, config, start_after_s=start_after_s) as (emulator, world):
        prefix = scenario.bus.topics(scenario.name).prefix
        _say(f"emulate: scenario {scenario.name}: world on the {scenario.bus.kind} bus, {prefix}/")
        sitl_cli.describe(emulator, config)
        await sitl_cli.until_stopped()
        _say("emulate: stopping")
        in_mission = [s for s in world.samples if s.step <= scenario.timing.steps]
        if in_mission:
            last = in_mission[-1]
            error = float(tracking_error(last.positions_m, last.alive, last.target_m))
            _say(
                f"emulate: mission step {last.step}: formation centre {error:.3f} m from the target"
            )
    sitl_cli.describe_stop(emulator)


def _say(text: str) -> None:
    """A line for the user at the terminal (this module is a command's body)."""
    sys.stdout.write(text + "\n")
    sys.stdout.flush()
