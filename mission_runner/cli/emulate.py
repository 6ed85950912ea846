"""``mission-runner emulate``: the emulated vehicles and the scenario's world
(:mod:`mission_runner.world.emulated`)."""

from __future__ import annotations

import argparse

from .options import add_bus_arguments


def add_parser(
    commands: argparse._SubParsersAction[argparse.ArgumentParser], *, with_options: bool
) -> None:
    """``with_options``: the emulator's options too (they import it: only for this command)."""
    emulate = commands.add_parser(
        "emulate",
        help="emulated PX4 vehicles with the scenario's target and UWB ranging on its bus, for "
        "vehicle processes (what 'sitl --scenario' did)",
    )
    if with_options:
        from ..world import emulated  # noqa: PLC0415 - the emulator, for this command only

        emulated.add_arguments(emulate)
        add_bus_arguments(emulate)
