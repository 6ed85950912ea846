"""``mission-runner control``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .. import argtypes
from .common import EXIT_BAD_INPUT, EXIT_OK
from .options import add_bus_arguments

#: ``runner.operator.OPERATOR_COMMANDS`` by name (tests hold the two equal), spelt out here as
#: that module loads the bus, which ``--help`` does without.
OPERATOR_COMMAND_NAMES = ("hold", "resume", "land", "return", "stop")


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    operate = commands.add_parser(
        "control",
        help="operator command to the running mission of vehicle processes: hold, resume, land, "
        "return or stop, for every vehicle or one",
    )
    operate.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    operate.add_argument("command", choices=OPERATOR_COMMAND_NAMES)
    operate.add_argument(
        "--vehicle", type=argtypes.positive_int, default=None, help="one vehicle's id"
    )
    operate.add_argument("--reason", default=None, help="a note the vehicles log and report")
    add_bus_arguments(operate)
    operate.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    import asyncio  # noqa: PLC0415 - fast `--help`

    from ..bus.cli_options import with_bus_access  # noqa: PLC0415 - fast `--help`
    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..runner.operator import OperatorInputError, operator_command  # noqa: PLC0415 - fast `--help`
    from ..runner.process import send_control  # noqa: PLC0415 - fast `--help`

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
    try:  # before connecting: a command for a vehicle not in the scenario is bad input
        operator_command(
            arguments.command,
            [v.id for v in scenario.vehicles],
            vehicle_id=arguments.vehicle,
            reason=arguments.reason,
        )
    except OperatorInputError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    mission_id = asyncio.run(
        send_control(
            scenario, arguments.command, vehicle_id=arguments.vehicle, reason=arguments.reason
        )
    )
    who = f"vehicle {arguments.vehicle}" if arguments.vehicle else "every vehicle"
    print(f"control: {arguments.command} sent to {who} of mission {mission_id}")
    return EXIT_OK
