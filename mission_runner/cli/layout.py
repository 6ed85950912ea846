"""``mission-runner layout``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import print_json


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    layout = commands.add_parser(
        "layout", help="print a Foxglove layout for the scenario's recording and live view"
    )
    layout.add_argument("config", type=Path, help="scenario YAML file (for its vehicle ids)")
    layout.add_argument("--out", type=Path, default=None, help="write it there instead")
    layout.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    import json  # noqa: PLC0415 - fast `--help`

    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..layout import foxglove_layout  # noqa: PLC0415 - fast `--help`

    scenario = load_scenario(arguments.config)
    layout = foxglove_layout([vehicle.id for vehicle in scenario.vehicles])
    return print_json(json.loads(layout.to_json()), arguments.out)
