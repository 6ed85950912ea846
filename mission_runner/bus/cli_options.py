"""The bus options of every command that talks on the bus (``run``, ``vehicle``, ``ground``,
``ranges``, ``control``, ``emulate``; defined in :mod:`mission_runner.cli.options`): where this
process's bus key and broker login are, and whether an MQTT bus may run without a key.
:func:`with_bus_access` attaches them to the scenario's bus settings, so every command reads them
the same way.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Mapping
from typing import Any, Protocol, Self, TypeVar

from mission_runner.bus.broker import read_credentials
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
