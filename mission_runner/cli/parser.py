"""The command line's parser: one module per command adds its own options. Building it imports
no command's work (no bus, MAVSDK, Foxglove, matplotlib, emulator), so ``--help`` is quick and a
vehicle process on a companion computer pays only for what its command runs."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from . import (
    broker_config,
    control,
    emulate,
    ground,
    layout,
    px4_sitl,
    ranges,
    replay,
    run,
    schema,
    simulate,
    sweep,
    vehicle,
    view,
)

#: In the order ``--help`` lists them.
COMMANDS = (
    simulate,
    sweep,
    run,
    replay,
    vehicle,
    ground,
    view,
    layout,
    ranges,
    schema,
    control,
    broker_config,
)


def command_named(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if any."""
    return next((word for word in argv if not word.startswith("-")), None)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line; ``emulate``'s and ``px4-sitl``'s options only when ``command`` is one of
    them, as they import the emulator and the PX4 launcher, half a second of every other
    command's start on a companion computer's budget."""
    parser = argparse.ArgumentParser(
        prog="mission-runner",
        description="Multi-drone moving-target enclosing: simulate or fly a scenario.",
    )
    commands = parser.add_subparsers(required=True, metavar="COMMAND")
    for module in COMMANDS:
        module.add_parser(commands)
    emulate.add_parser(commands, with_options=command == "emulate")
    px4_sitl.add_parser(commands, with_options=command == "px4-sitl")
    return parser
