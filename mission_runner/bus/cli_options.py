"""The command-line options of every command that talks on the bus (``run``, ``vehicle``,
``ground``, ``ranges``, ``control``, ``emulate``): where this process's bus key and broker
login are, and whether an MQTT bus may run without a key. Defined once here, so every command
reads them the same way; :func:`with_bus_access` attaches them to the scenario's bus settings.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol, Self, TypeVar

from mission_runner.bus.auth import DEFAULT_KEY_ENV
from mission_runner.bus.broker import PASSWORD_ENV, USERNAME_ENV, read_credentials
from mission_runner.bus.settings import BusAccess, BusSettings

logger = logging.getLogger(__name__)


class WithBus(Protocol):
    """What :func:`with_bus_access` needs of a scenario (the bus sits below the scenario model)."""

    @property
    def bus(self) -> BusSettings: ...

    def model_copy(self, *, update: Mapping[str, Any] | None = None, deep: bool = False) -> Self:
        """A copy with ``update``'s fields replaced (pydantic's)."""
        ...


ScenarioT = TypeVar("ScenarioT", bound=WithBus)


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """``--bus-key-file``, ``--bus-credentials`` and ``--insecure-bus``."""
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


def with_bus_access(scenario: ScenarioT, arguments: argparse.Namespace) -> ScenarioT:
    """``scenario`` with the command line's bus options attached and checked now (a missing key
    or an unreadable credentials file stops the command before anything connects or flies).
    Raises BusAuthError."""
    access = BusAccess(
        key_file=getattr(arguments, "bus_key_file", None),
        credentials_file=getattr(arguments, "bus_credentials", None),
        insecure=getattr(arguments, "insecure_bus", False),
    )
    bus = scenario.bus.with_access(access)
    credentials = access.credentials_file or bus.mqtt.credentials_file
    if bus.kind == "mqtt" and credentials is not None:
        read_credentials(credentials)
    key = bus.bus_key()
    if key.insecure:
        logger.warning("bus: NO AUTHENTICATION (--insecure-bus): anyone can forge messages")
    else:
        logger.info(
            "bus: messages signed with a key (%s; fingerprint %s)",
            key.source,
            key.fingerprint,
        )
    return scenario.model_copy(update={"bus": bus})
