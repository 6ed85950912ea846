"""``mission-runner px4-sitl``: real PX4 SITL (SIH), one instance per vehicle
(:mod:`mission_runner.px4sitl`)."""

from __future__ import annotations

import argparse


def add_parser(
    commands: argparse._SubParsersAction[argparse.ArgumentParser], *, with_options: bool
) -> None:
    """``with_options``: the launcher's options too (only for this command)."""
    px4 = commands.add_parser(
        "px4-sitl",
        help="start real PX4 SITL (SIH), one instance per vehicle of the scenario, until Ctrl-C",
    )
    if with_options:
        from .. import px4sitl  # noqa: PLC0415 - the PX4 launcher, for this command only

        px4sitl.add_arguments(px4)
