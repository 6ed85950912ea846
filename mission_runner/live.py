"""Watch a mission while it flies: the recording's channels served over the Foxglove WebSocket
protocol (foxglove-sdk's server), for Foxglove's "Open connection" (``ws://host:port``).

:class:`LiveServer` owns the server and a :class:`~.recording.MissionChannels` on their own
foxglove context. Two feeds publish into it:

- :class:`FlightFeed`, for the in-process flight (``run --live``): the controllers' step records
  and, once every vehicle has done step k, the emulator's truth: the same messages as
  ``recording.mcap``, as they happen.
- :func:`serve_bus`, for a mission of vehicle processes (``ground --live``, ``view``): what the
  mission's bus carries - every vehicle's step message (phase, odometry) and status. The bus has
  no truth and no estimates, so this view draws each vehicle in its own odometry frame with its
  phase and state; the recordings have the rest after the mission.

Log lines go out as they are written (:class:`LiveLog`). Publishing is a few hundred
microseconds per step, in the caller's thread; the server sends from its own threads.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

import foxglove
import numpy as np

from .bus import Sender, StepMessage, VehicleStatus, open_bus
from .bus.broker import VIEWER_USER
from .enclosing import splay_spacing_error
from .recording import (
    LogCapture,
    LogLine,
    MissionChannels,
    VehicleView,
    finite_or_none,
    view_of_record,
)
from .records import FORMATION_STATES, ControllerState
from .scenario import shape_schedule

if TYPE_CHECKING:
    from foxglove.websocket import ServerListener, WebSocketServer

    from .bus import StepMessage, Subscription, VehicleStatus
    from .config import Scenario
    from .records import Progress, StepRecord

logger = logging.getLogger(__name__)

DEFAULT_PORT = 8765

T = TypeVar("T")


class LiveServer:
    """A Foxglove WebSocket server with the mission's channels, from ``with`` to its end.

    port 0 takes a free one (read :attr:`port`); backlog: messages buffered per client before
    the oldest are dropped (a slow client loses data, never slows the mission)."""

    def __init__(
        self,
        scenario: Scenario,
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        backlog: int = 4096,
        listener: ServerListener | None = None,
    ) -> None:
        self.scenario = scenario
        self.context = foxglove.Context()
        self.channels = MissionChannels(
            self.context, [v.id for v in scenario.vehicles], scenario.algorithm.radius_m
        )
        self._options: dict[str, Any] = {
            "name": f"mission-runner {scenario.name}",
            "host": host,
            "port": port,
            "message_backlog_size": backlog,
            "server_listener": listener,
        }
        self._server: WebSocketServer | None = None

    def __enter__(self) -> LiveServer:
        self._server = foxglove.start_server(context=self.context, **self._options)
        logger.info("live view on ws://%s:%d (Foxglove: Open connection)", self.host, self.port)
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if self._server is not None:
            self._server.stop()
            self._server = None

    @property
    def host(self) -> str:
        return str(self._options["host"])

    @property
    def port(self) -> int:
        if self._server is None:
            raise RuntimeError("the live server is not running: use it in a with block")
        return self._server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"


class LiveLog(LogCapture):
    """Sends log lines to ``/log`` as they are written (instead of keeping them), stamped with
    the mission time last seen (lines before any: at 0)."""

    def __init__(self, channels: MissionChannels, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.channels = channels

    def emit(self, record: logging.LogRecord) -> None:
        time_s = 0.0 if self.time_s is None else self.time_s
        line = LogLine(time_s, record.levelno, record.name, record.getMessage())
        self.channels.log_line(time_s, line)


class FlightFeed:
    """``fly``'s callbacks as live messages: ``on_step`` keeps each controller's record until
    ``on_progress`` says every vehicle has done the step (and brings the truth); then the step
    goes out as in the recording."""

    def __init__(self, scenario: Scenario, channels: MissionChannels) -> None:

        self.scenario, self.channels = scenario, channels
        self.ids = [vehicle.id for vehicle in scenario.vehicles]
        self.shape = shape_schedule(scenario)
        self.pending: dict[int, dict[int, StepRecord]] = {}
        self.on_time: Callable[[float], None] | None = None

    def on_step(self, vehicle_id: int, record: StepRecord) -> None:
        self.pending.setdefault(record.step, {})[vehicle_id] = record
        if self.on_time is not None:
            self.on_time(record.time_s)

    def on_progress(self, progress: Progress) -> None:
        records = self.pending.pop(progress.step, {})
        for stale in [k for k in self.pending if k < progress.step]:
            del self.pending[stale]  # steps whose vehicle died before finishing them
        truth = progress.truth
        alive = {i: bool(a) for i, a in zip(self.ids, truth.alive, strict=True)} if truth else {}
        views = [
            view_of_record(
                record,
                vehicle_id,
                live=alive.get(vehicle_id, True) and record.state in FORMATION_STATES,
            )
            for vehicle_id, record in sorted(records.items())
        ]
        phases = {v.vehicle_id: v.phase_rad for v in views if v.phase_rad is not None}
        live = np.array([view.live for view in views], dtype=bool)
        spacing = splay_spacing_error(np.array([v.phase_rad or math.nan for v in views]), live)
        metrics = {
            "step": progress.step,
            "time_s": progress.time_s,
            "tracking_error_m": finite_or_none(progress.tracking_error_m),
            "localization_error_m": finite_or_none(progress.localization_error_m),
            "phase_spacing_error_rad": finite_or_none(float(spacing)),
            "consensus_speed_m_s": max(
                (math.hypot(*v.consensus_m_s) for v in views if v.consensus_m_s), default=None
            ),
            "live_vehicles": int(live.sum()),
        }
        positions = {}
        if truth is not None:
            positions = {
                i: truth.positions_m[index]
                for index, i in enumerate(self.ids)
                if truth.alive[index] and np.all(np.isfinite(truth.positions_m[index]))
            }
        self.channels.log_step(
            progress.time_s,
            shape=self.shape(progress.step),
            target_m=None if truth is None else truth.target_m,
            positions_m=positions,
            phases_rad=phases,
            views=views,
            metrics=metrics,
        )


@dataclass
class _BusState:
    """What the bus said last about each vehicle: its state, by id."""

    states: dict[int, str]


async def serve_bus(
    scenario: Scenario,
    channels: MissionChannels,
    *,
    client_id: str,
    on_time: Callable[[float], None] | None = None,
) -> None:
    """Publish what the mission's bus carries until cancelled: each vehicle's step message as
    its state (phase, odometry) and its frame in its odometry, each status change as an event."""

    topics = scenario.bus.topics(scenario.name)
    known = {vehicle.id for vehicle in scenario.vehicles}
    state = _BusState({})

    async def steps(subscription: Subscription) -> None:
        async for _, message in subscription.messages(StepMessage):
            if message.vehicle_id in known:
                _publish_step(channels, state, message)
                if on_time is not None:
                    on_time(message.time_s)

    async def statuses(subscription: Subscription) -> None:
        async for _, status in subscription.messages(VehicleStatus):
            if status.vehicle_id in known:
                _publish_status(channels, state, status)

    # Both subscriptions are in place before either is read: a retained status seen means the
    # steps are heard too.
    async with (
        # A viewer publishes nothing; it checks the messages with the mission's key, under a
        # read-only login of its own (client ids are bound to logins: the ground's would take
        # the ground station's connection).
        open_bus(
            scenario.bus, sender=Sender.ground(), client_id=client_id, login=VIEWER_USER
        ) as bus,
        bus.subscribe(topics.all_steps()) as step_messages,
        bus.subscribe(topics.all_status()) as status_messages,
        asyncio.TaskGroup() as group,
    ):
        group.create_task(steps(step_messages), name="live-steps")
        group.create_task(statuses(status_messages), name="live-statuses")


async def alongside(
    main: Awaitable[T],
    scenario: Scenario,
    channels: MissionChannels,
    *,
    client_id: str,
    on_time: Callable[[float], None] | None = None,
) -> T:
    """Await ``main`` while :func:`serve_bus` publishes the mission's bus; the bus view ends with
    it (and a failure of either ends both)."""
    async with asyncio.TaskGroup() as group:
        watcher = group.create_task(
            serve_bus(scenario, channels, client_id=client_id, on_time=on_time), name="live-bus"
        )
        try:
            return await main
        finally:
            watcher.cancel()


def _publish_step(channels: MissionChannels, state: _BusState, message: StepMessage) -> None:
    current = state.states.get(message.vehicle_id, ControllerState.FOLLOWING)
    down = message.odometry_down_m
    view = VehicleView(
        vehicle_id=message.vehicle_id,
        step=message.step,
        time_s=message.time_s,
        state=current,
        live=current in FORMATION_STATES,
        phase_rad=message.phase_rad,
        odometry_m=(
            message.odometry_north_m,
            message.odometry_east_m,
            0.0 if down is None else down,
        ),
    )
    channels.log_step(
        message.time_s,
        shape=np.eye(3),
        target_m=None,
        positions_m={},
        phases_rad={},
        views=[view],
    )


def _publish_status(channels: MissionChannels, state: _BusState, status: VehicleStatus) -> None:
    before = state.states.get(status.vehicle_id)
    if before != status.state:
        detail = f": {status.detail}" if status.detail else ""
        channels.log_event(
            status.time_s,
            f"vehicle {status.vehicle_id}: {status.state} (step {status.step}){detail}",
        )
    state.states[status.vehicle_id] = status.state
