"""Waiting for the ground station's commands on ``<prefix>/control``: the one place every
participant of a mission (vehicle processes, the range aid, the emulated world) reads the
``prepare`` / ``start`` / ``land`` / ``stop`` handshake described in :mod:`.process`.

Only the ground station's commands get here: the bus drops control messages that are not signed
by the ground role (:mod:`mission_runner.bus.auth`). A ``start`` must also make sense on this
receiver's clock: its k = 0 no more than :data:`MAX_START_LEAD_S` ahead of the mission clock it
defines and no more than :data:`MAX_START_LAG_S` behind it. Anything else (a forged or corrupted
start, or a ground station whose clock is off) would have every vehicle skip its way through
steps in the past or hover for hours: it is logged and ignored, and the wait goes on.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import math
import time
from collections.abc import Callable, Collection

from ..bus import ControlCommand, MissionControl
from ..bus.auth import RateLimitedWarnings
from .errors import RunnerError, RunnerTimeoutError
from .ports import MessageSource
from .timesync import MissionTime

logger = logging.getLogger(__name__)

#: The latest k = 0 a start may set, after now on its mission clock [s]: the ground station's
#: start delay (2 s by default) with room for a slow operator's choice.
MAX_START_LEAD_S = 120.0
#: The earliest, before now [s]: link latency and clock skew between synchronised machines,
#: with a margin; a start further in the past would make every vehicle skip its first steps.
MAX_START_LAG_S = 5.0
#: How far a ``clock`` change may move this receiver's mission clock where it takes effect [s]:
#: it is meant to be continuous there; a larger step means a forged change or a receiver that
#: missed the start, and is ignored.
MAX_CLOCK_STEP_S = 1.0

_warnings = RateLimitedWarnings(logger)


def freeze_heap() -> None:
    """Collect once and move every object alive now out of the collector's sight
    (:func:`gc.freeze`), between the start command and k = 0. What a process built to get
    there (MAVSDK, numpy, pydantic, the bus) is never garbage, yet every full collection walked
    it: 150 ms pauses in flight, two a minute in each vehicle process at speed factor 2 (more
    than a step of 62 ms of wall time)."""
    gc.collect()
    gc.freeze()


def start_problem(command: MissionControl, unix_now_s: float) -> str | None:
    """Why ``command`` (a ``start``) cannot be obeyed at UNIX time ``unix_now_s``, or None.

    The mission clock it defines is ``reference + rate * (unix - reference)``; its k = 0 must lie
    within [-:data:`MAX_START_LAG_S`, +:data:`MAX_START_LEAD_S`] of that clock's now, and its
    reference within :data:`MAX_START_LEAD_S` of now."""
    rate = command.clock_rate or 1.0
    reference_s = command.clock_reference_s
    if reference_s is None:
        reference_s = unix_now_s
    elif abs(reference_s - unix_now_s) > MAX_START_LEAD_S:
        return f"its clock reference is {reference_s - unix_now_s:+.1f} s from this clock's now"
    mission_now_s = reference_s + rate * (unix_now_s - reference_s)
    lead_s = command.time_s - mission_now_s
    if lead_s > MAX_START_LEAD_S:
        return f"k = 0 would be {lead_s:.1f} s from now (at most {MAX_START_LEAD_S:g} s)"
    if lead_s < -MAX_START_LAG_S:
        return f"k = 0 would be {-lead_s:.1f} s ago (at most {MAX_START_LAG_S:g} s)"
    return None


async def next_command(
    control: MessageSource,
    commands: Collection[ControlCommand],
    *,
    mission_id: str | None = None,
    timeout_s: float | None = None,
    unix_clock: Callable[[], float] = time.time,
) -> MissionControl:
    """The next :class:`MissionControl` on the subscription ``control`` whose command is in
    ``commands`` (and, if ``mission_id`` is given, of that mission). A ``start`` that does not
    make sense on ``unix_clock`` (:func:`start_problem`) is logged and skipped.

    Raises :class:`RunnerTimeoutError` after ``timeout_s`` (None: wait for ever) and
    :class:`RunnerError` if the bus closes first.
    """
    try:
        async with asyncio.timeout(timeout_s):
            async for _, message in control.messages(MissionControl):
                if message.command not in commands or (
                    mission_id is not None and message.mission_id != mission_id
                ):
                    continue
                if message.command is ControlCommand.START:
                    problem = start_problem(message, unix_clock())
                    if problem is not None:
                        _warnings.warn(
                            "start",
                            "ignoring a start of mission %s: %s",
                            message.mission_id,
                            problem,
                        )
                        continue
                return message
    except TimeoutError:
        names = "/".join(sorted(c.value for c in commands))
        raise RunnerTimeoutError(f"the ground station's {names}", timeout_s or math.inf) from None
    raise RunnerError("the bus closed while waiting for the ground station")


async def start_command(
    control: MessageSource, *, timeout_s: float | None = None
) -> MissionControl:
    """The next ``start``, whichever mission it belongs to (for aids that follow any mission)."""
    return await next_command(control, {ControlCommand.START}, timeout_s=timeout_s)


def clock_change_problem(
    command: MissionControl, mission_time: MissionTime, unix_now_s: float
) -> str | None:
    """Why ``command`` (a ``clock``) cannot be taken by ``mission_time`` now, or None."""
    at_unix_s, rate = command.clock_reference_s, command.clock_rate
    if at_unix_s is None or rate is None:
        return "it has no clock_rate or clock_reference_s"
    if abs(at_unix_s - unix_now_s) > MAX_START_LAG_S:
        return f"it takes effect {at_unix_s - unix_now_s:+.1f} s from this clock's now"
    step_s = command.time_s - mission_time.from_unix(at_unix_s)
    if abs(step_s) > MAX_CLOCK_STEP_S:
        return f"it would step this mission clock by {step_s:+.3f} s"
    return None


def take_clock_change(
    command: MissionControl, mission_time: MissionTime, *, unix_clock: Callable[[], float]
) -> bool:
    """Apply a ``clock`` command to ``mission_time`` (logged), or log why not; whether taken."""
    problem = clock_change_problem(command, mission_time, unix_clock())
    if problem is not None:
        _warnings.warn("clock", "ignoring a clock change: %s", problem)
        return False
    assert command.clock_rate is not None and command.clock_reference_s is not None
    mission_time.change(command.clock_rate, command.clock_reference_s, command.time_s)
    logger.info(
        "mission clock runs at %.4fx from UNIX time %.3f (mission time %.3f)",
        command.clock_rate,
        command.clock_reference_s,
        command.time_s,
    )
    return True
