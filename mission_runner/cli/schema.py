"""``mission-runner schema``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import print_json


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    schema = commands.add_parser(
        "schema",
        help="print the scenario file's JSON Schema (for an editor's YAML language server)",
    )
    schema.add_argument("--out", type=Path, default=None, help="write it there instead")
    schema.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    from ..config import scenario_json_schema  # noqa: PLC0415 - fast `--help`

    return print_json(scenario_json_schema(), arguments.out)
