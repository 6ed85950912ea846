"""Waiting for the ground station's commands on ``<prefix>/control``: the one place every
participant of a mission (vehicle processes, the range aid, the emulated world) reads the
``prepare`` / ``start`` / ``land`` / ``stop`` handshake described in :mod:`.process`.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Collection

from ..bus import ControlCommand, MissionControl, Subscription
from .errors import RunnerError, RunnerTimeoutError


async def next_command(
    control: Subscription,
    commands: Collection[ControlCommand],
    *,
    mission_id: str | None = None,
    timeout_s: float | None = None,
) -> MissionControl:
    """The next :class:`MissionControl` on the subscription ``control`` whose command is in
    ``commands`` (and, if ``mission_id`` is given, of that mission).

    Raises :class:`RunnerTimeoutError` after ``timeout_s`` (None: wait for ever) and
    :class:`RunnerError` if the bus closes first.
    """
    try:
        async with asyncio.timeout(timeout_s):
            async for _, message in control.messages(MissionControl):
                if message.command in commands and (
                    mission_id is None or message.mission_id == mission_id
                ):
                    return message
    except TimeoutError:
        names = "/".join(sorted(c.value for c in commands))
        raise RunnerTimeoutError(f"the ground station's {names}", timeout_s or math.inf) from None
    raise RunnerError("the bus closed while waiting for the ground station")


async def start_command(control: Subscription, *, timeout_s: float | None = None) -> MissionControl:
    """The next ``start``, whichever mission it belongs to (for aids that follow any mission)."""
    return await next_command(control, {ControlCommand.START}, timeout_s=timeout_s)
