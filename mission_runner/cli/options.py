"""Options several commands share: the bus's security, the live view, ``--replay``. Defined once
here, with light imports only (building the parser loads no bus, no MQTT client)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import argtypes
from ..environment import DEFAULT_KEY_ENV, PASSWORD_ENV, USERNAME_ENV


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """``--bus-key-file``, ``--bus-credentials`` and ``--insecure-bus``; the bus's
    ``with_bus_access`` attaches them to the scenario's bus settings."""
    group = parser.add_argument_group("bus security")
    group.add_argument(
        "--bus-key-file",
        type=Path,
        default=None,
        metavar="FILE",
        help="the mission's message key (the same on every process; default: the environment "
        f"variable {DEFAULT_KEY_ENV}, else bus.auth.key_file). An MQTT bus refuses to run "
        "without one; the in-process bus makes its own",
    )
    group.add_argument(
        "--bus-credentials",
        type=Path,
        default=None,
        metavar="FILE",
        help="broker logins, 'user:password' lines (broker-config writes them): this process "
        f"logs in as its role's user (default: {USERNAME_ENV}/{PASSWORD_ENV}, else "
        "bus.mqtt.credentials_file, else anonymous)",
    )
    group.add_argument(
        "--insecure-bus",
        action="store_true",
        help="let an MQTT bus run without a key: anyone on the network can then forge every "
        "message, including start and land. Closed bench networks only",
    )


def add_live_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--live",
        action="store_true",
        help="serve the mission to Foxglove over its WebSocket protocol while it flies",
    )
    parser.add_argument("--live-host", default="127.0.0.1", help="address to serve on")
    parser.add_argument(
        "--live-port", type=argtypes.port_or_zero, default=8765, help="port (0: any free one)"
    )


def add_replay_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--replay",
        action="store_true",
        help="also animate the run: replay.gif (and replay.mp4 where ffmpeg is on the PATH)",
    )
