"""The operator's commands during a mission: ``hold``, ``resume``, ``land``, ``return`` and
``stop``, for the whole swarm or one vehicle.

One vocabulary (:data:`OPERATOR_COMMANDS`, :func:`operator_command`, :func:`parse_line`) for
``mission-runner control``'s arguments and the lines an operator types into a running ``ground``
or ``run``; one way to send them (:func:`publish_operator`: a :class:`MissionControl` of the
mission, on its control topic, signed by the ground role); one way to obey them
(:func:`fly_obeying`), shared by vehicle processes (:mod:`.process`) and the in-process swarm
(:mod:`.mission`). ``hold`` and ``resume`` act on the controller's next step; ``land``,
``return`` and ``stop`` end the vehicle's mission at once and the caller commands the vehicle
(:data:`ENDING_ACTIONS`).

Typed lines come from :func:`stdin_lines` through an :class:`OperatorConsole`, which a mission
serves (:func:`serving`) for as long as it runs. Standard input that cannot be read as a stream
(``/dev/null`` under nohup or in CI, a closed descriptor, a terminal of a background job) just
gives no lines: the mission never depends on it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import selectors
import sys
import time
from collections.abc import AsyncIterable, AsyncIterator, Awaitable, Callable, Collection
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, cast

from ..bus import BusError, ControlCommand, MissionControl, Topics
from ..bus.messages import MAX_REASON_CHARS, Message
from ..tasks import first_completed
from .errors import RunnerError
from .handshake import next_command, take_clock_change

if TYPE_CHECKING:
    from ..records import StepRecord
    from .controller import VehicleController
    from .ports import MessageSource
    from .timesync import MissionTime

logger = logging.getLogger(__name__)

#: What an operator may command during a mission (``prepare`` and ``start`` are the ground
#: station's handshake).
OPERATOR_COMMANDS = (
    ControlCommand.HOLD,
    ControlCommand.RESUME,
    ControlCommand.LAND,
    ControlCommand.RETURN,
    ControlCommand.STOP,
)

#: What each mission-ending command makes the vehicle do (``MavsdkVehicle.finish``).
ENDING_ACTIONS = {
    ControlCommand.LAND: "land",
    ControlCommand.RETURN: "return",
    ControlCommand.STOP: "hold",
}

HELP = (
    "commands: hold | resume | land | return | stop [VEHICLE_ID]  (no id: every vehicle); "
    "hold hovers in place, resume flies the law again, land / return (to launch) / stop "
    "(the autopilot holds) end the mission; help"
)


class OperatorInputError(RunnerError):
    """An operator command that cannot be sent: unknown, or for a vehicle not in the mission."""


@dataclass(frozen=True)
class OperatorCommand:
    """One operator command: what, for whom (None: every vehicle) and an optional note."""

    command: ControlCommand
    vehicle_id: int | None = None
    reason: str | None = None

    @property
    def target(self) -> str:
        return "every vehicle" if self.vehicle_id is None else f"vehicle {self.vehicle_id}"

    def message(self, mission_id: str | None, *, time_s: float | None = None) -> MissionControl:
        """As the bus carries it, for mission ``mission_id``."""
        return MissionControl(
            self.command,
            time.time() if time_s is None else time_s,
            reason=self.reason,
            mission_id=mission_id,
            vehicle_id=self.vehicle_id,
        )


def operator_command(
    command: str | ControlCommand,
    vehicle_ids: Collection[int],
    *,
    vehicle_id: int | None = None,
    reason: str | None = None,
) -> OperatorCommand:
    """``command`` checked against :data:`OPERATOR_COMMANDS` and the mission's ``vehicle_ids``.
    Raises :class:`OperatorInputError` naming what is allowed."""
    names = ", ".join(c.value for c in OPERATOR_COMMANDS)
    try:
        parsed = ControlCommand(command)
    except ValueError:
        raise OperatorInputError(f"unknown command {command!r}; one of {names}, or help") from None
    if parsed not in OPERATOR_COMMANDS:
        raise OperatorInputError(f"'{parsed.value}' is the ground station's; use {names}")
    if vehicle_id is not None and vehicle_id not in vehicle_ids:
        ids = ", ".join(map(str, sorted(vehicle_ids)))
        raise OperatorInputError(f"vehicle {vehicle_id} is not in the mission (ids {ids})")
    if reason is not None and len(reason) > MAX_REASON_CHARS:
        raise OperatorInputError(
            f"the reason has {len(reason)} characters; a command carries at most "
            f"{MAX_REASON_CHARS} (the vehicles would drop a larger one unread)"
        )
    return OperatorCommand(parsed, vehicle_id, reason)


#: Lines that ask for :data:`HELP`.
HELP_WORDS = ("help", "?")


def parse_line(line: str, vehicle_ids: Collection[int]) -> OperatorCommand | None:
    """A typed line: ``COMMAND [VEHICLE_ID]`` (``hold``, ``land 2``), None for an empty one.
    Raises :class:`OperatorInputError` saying what is wrong with anything else."""
    words = line.split()
    if not words:
        return None
    name = words[0].lower()
    if len(words) > 2:
        raise OperatorInputError(f"{line.strip()!r}: expected COMMAND [VEHICLE_ID]; try help")
    vehicle_id = None
    if len(words) == 2:
        try:
            vehicle_id = int(words[1])
        except ValueError:
            raise OperatorInputError(
                f"{line.strip()!r}: the vehicle id must be a number; try help"
            ) from None
    return operator_command(name, vehicle_ids, vehicle_id=vehicle_id)


class _Publisher(Protocol):
    async def publish_message(self, topic: str, message: Message, *, timeout: float) -> None: ...


async def publish_operator(
    bus: _Publisher,
    topics: Topics,
    command: OperatorCommand,
    mission_id: str | None,
    *,
    timeout_s: float = 5.0,
    time_s: float | None = None,
) -> None:
    """Send ``command`` to mission ``mission_id`` on ``bus`` (which must sign as the ground
    station: the vehicles obey no one else), stamped ``time_s`` (UNIX time; default now).
    Raises :class:`BusError` if it could not."""
    message = command.message(mission_id, time_s=time_s)
    await bus.publish_message(topics.control(), message, timeout=timeout_s)


# -- obeying ----------------------------------------------------------------------------------


async def obey(
    control: MessageSource,
    controller: VehicleController,
    *,
    mission_id: str | None,
    mission_time: MissionTime | None = None,
) -> MissionControl:
    """The operator's commands for ``controller``'s vehicle (or all) of mission ``mission_id``:
    ``hold`` and ``resume`` act on the controller's next step; the first ``land``, ``return``
    or ``stop`` is returned (it ends this vehicle's mission). With ``mission_time`` (a vehicle
    process), the ground's ``clock`` changes are taken too."""
    wanted = set(OPERATOR_COMMANDS)
    if mission_time is not None:
        wanted.add(ControlCommand.CLOCK)
    vehicle_id = controller.vehicle_id
    while True:
        command = await next_command(control, wanted, mission_id=mission_id)
        if command.vehicle_id not in (None, vehicle_id):
            continue
        if command.command is ControlCommand.CLOCK:
            assert mission_time is not None  # only then wanted
            take_clock_change(command, mission_time, unix_clock=mission_time.unix_now_s)
            continue
        # The step being flown is the last the controller decided (or is deciding) under the
        # old command; the next one is the first under this command.
        first = controller.decided_step + 1
        note = f" ({command.reason})" if command.reason else ""
        if command.command in ENDING_ACTIONS:
            logger.warning(
                "vehicle %s: %s by the operator, no step from %d%s",
                vehicle_id,
                command.command.value,
                first,
                note,
            )
            return command
        controller.operator_hold = command.command is ControlCommand.HOLD
        logger.warning(
            "vehicle %s: %s by the operator, from step %d%s",
            vehicle_id,
            command.command.value,
            first,
            note,
        )


async def fly_obeying(
    controller: VehicleController,
    flight: Awaitable[list[StepRecord]],
    control: MessageSource,
    *,
    mission_id: str | None,
    mission_time: MissionTime | None = None,
) -> MissionControl | None:
    """Await ``flight`` (``controller.run(...)``) while obeying the operator (:func:`obey`).
    Returns None when the flight ended on its own, or the ``land``, ``return`` or ``stop`` that
    ended it (the controller has stopped driving; the caller commands the vehicle: see
    :data:`ENDING_ACTIONS`). A controller failure propagates."""
    name = f"vehicle-{controller.vehicle_id}"
    watch = f"{name}-operator"
    ended_by, ended_with = await first_completed(
        {
            f"{name}-fly": cast(Awaitable[object], flight),
            watch: obey(control, controller, mission_id=mission_id, mission_time=mission_time),
        }
    )
    return cast(MissionControl, ended_with) if ended_by == watch else None


# -- typed commands -----------------------------------------------------------------------------

#: Where :class:`OperatorConsole` gets its lines: an async context manager yielding them.
LineSource = Callable[[], contextlib.AbstractAsyncContextManager[AsyncIterable[str]]]


@contextlib.asynccontextmanager
async def stdin_lines() -> AsyncIterator[AsyncIterable[str]]:
    """The lines typed on standard input, read without blocking the event loop, until EOF.

    Gives nothing (an immediately ending iteration) where standard input is not a stream the
    event loop can watch (``/dev/null``, a regular file, a closed descriptor) or is the terminal
    of a background job (reading it would stop the process with SIGTTIN)."""
    loop = asyncio.get_running_loop()
    try:
        fd = sys.stdin.fileno()
        if os.isatty(fd) and os.tcgetpgrp(fd) != os.getpgrp():
            raise OSError("a background job: its terminal is not its to read")
        blocking = os.get_blocking(fd)
    except (OSError, ValueError, AttributeError) as error:
        logger.info("typed commands off: standard input cannot be read (%s)", error)
        yield _no_lines()
        return
    try:
        # The event loop registers the descriptor only after connect_read_pipe returns, and
        # logs its refusal instead of raising it: ask a selector of our own first (epoll
        # refuses regular files and /dev/null).
        with selectors.DefaultSelector() as probe:
            probe.register(fd, selectors.EVENT_READ)
    except (OSError, ValueError) as error:
        logger.info("typed commands off: standard input cannot be watched (%s)", error)
        yield _no_lines()
        return
    reader = asyncio.StreamReader()
    # A duplicate descriptor, so that closing the transport leaves the process's stdin open.
    pipe = os.fdopen(os.dup(fd), "rb", buffering=0)
    try:
        transport, _ = await loop.connect_read_pipe(
            lambda: asyncio.StreamReaderProtocol(reader), pipe
        )
    except (OSError, ValueError) as error:
        pipe.close()
        logger.info("typed commands off: standard input cannot be watched (%s)", error)
        yield _no_lines()
        return
    try:
        yield _lines_of(reader)
    finally:
        transport.close()
        # The descriptor's blocking mode is shared with the terminal's other users (the shell
        # after this process): put it back as it was.
        with contextlib.suppress(OSError):
            os.set_blocking(fd, blocking)


async def _lines_of(reader: asyncio.StreamReader) -> AsyncIterator[str]:
    while line := await reader.readline():
        yield line.decode(errors="replace")


async def _no_lines() -> AsyncIterator[str]:
    return
    yield  # an async generator that ends at once


@dataclass
class OperatorConsole:
    """Typed operator commands: each line of ``source`` parsed (:func:`parse_line`) and sent;
    ``say`` shows what was sent (and ``help``), ``complain`` a line that was not a command or
    could not be sent (one line each). The end of the lines ends the console, never the
    mission."""

    say: Callable[[str], None]
    complain: Callable[[str], None]
    source: LineSource = stdin_lines

    async def serve(
        self,
        vehicle_ids: Collection[int],
        send: Callable[[OperatorCommand], Awaitable[None]],
    ) -> None:
        read = 0
        async with self.source() as lines:
            async for line in lines:
                read += 1
                if line.strip().lower() in HELP_WORDS:
                    self.say(HELP)
                    continue
                try:
                    command = parse_line(line, vehicle_ids)
                except OperatorInputError as error:
                    self.complain(str(error))
                    continue
                if command is None:
                    continue
                try:
                    await send(command)
                except BusError as error:
                    self.complain(f"{command.command.value} not sent: {error}")
                    continue
                self.say(f"{command.command.value} sent to {command.target}")
        if read:
            logger.info("typed commands: end of input (the mission goes on)")


@contextlib.asynccontextmanager
async def serving(
    console: OperatorConsole | None,
    vehicle_ids: Collection[int],
    send: Callable[[OperatorCommand], Awaitable[None]],
) -> AsyncIterator[None]:
    """While the block runs, ``console`` (if any) reads and sends the operator's commands; the
    console's task belongs to the block (ended with it, its failure raised)."""
    if console is None:
        yield
        return
    async with asyncio.TaskGroup() as group:
        task = group.create_task(console.serve(vehicle_ids, send), name="operator-console")
        try:
            yield
        finally:
            task.cancel()
