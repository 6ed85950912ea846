"""``mission-runner view``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import argtypes
from ..errors import ConfigError
from .common import EXIT_OK
from .options import add_bus_arguments
from .stopping import run_async


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    view = commands.add_parser(
        "view",
        help="serve a running mission's bus (vehicle processes over MQTT) to Foxglove over its "
        "WebSocket protocol, until Ctrl-C",
    )
    view.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    view.add_argument("--host", default="127.0.0.1", help="address to serve on")
    view.add_argument(
        "--port", type=argtypes.port_or_zero, default=8765, help="port (0: any free one)"
    )
    add_bus_arguments(view)
    view.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    from ..bus.cli_options import with_bus_access  # noqa: PLC0415 - fast `--help`
    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..live import LiveLog, LiveServer, serve_bus  # noqa: PLC0415 - fast `--help`

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
    if scenario.bus.kind != "mqtt":
        raise ConfigError(
            str(arguments.config),
            [
                (
                    "bus.kind",
                    "view watches a mission's MQTT bus: set mqtt (an in-process mission is "
                    "watched with 'mission-runner run --live')",
                )
            ],
        )
    with LiveServer(scenario, host=arguments.host, port=arguments.port) as server:
        print(f"view: {server.url} (Foxglove: Open connection); Ctrl-C to stop", flush=True)
        live_log = LiveLog(server.channels)
        with live_log.attached():
            run_async(
                serve_bus(
                    scenario,
                    server.channels,
                    client_id=f"{scenario.name}-view",
                    on_time=live_log.stamp,
                )
            )
    return EXIT_OK
