"""``mission-runner emulate``: the emulated vehicles and the scenario's world
(:mod:`mission_runner.emulate`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import add_bus_arguments


def add_parser(
    commands: argparse._SubParsersAction[argparse.ArgumentParser], *, with_options: bool
) -> None:
    """``with_options``: the emulator's options too (``sitl``'s: only for this command)."""
    emulate = commands.add_parser(
        "emulate",
        help="emulated PX4 vehicles with the scenario's target and UWB ranging on its bus, for "
        "vehicle processes (what 'sitl --scenario' did)",
    )
    if not with_options:
        return
    from sitl import cli as sitl_cli  # noqa: PLC0415 - the emulator's options, not the emulator

    emulate.add_argument(
        "scenario", type=Path, metavar="CONFIG", help="scenario YAML file (bus.kind: mqtt)"
    )
    sitl_cli.add_emulator_options(emulate)  # its --config: emulator settings over the scenario's
    emulate.add_argument(
        "--start-after",
        type=float,
        help="k = 0 this many seconds after start (default: on the ground station's start)",
    )
    add_bus_arguments(emulate)
    emulate.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    """Run the scenario's emulated world until SIGINT/SIGTERM; exit code 0."""
    from ..emulate import command as emulate  # noqa: PLC0415 - fast `--help`

    return emulate(arguments)
