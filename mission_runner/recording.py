"""A mission as Foxglove sees it: the channels, and the MCAP recording every command writes.

:class:`MissionChannels` owns one channel per topic on a foxglove-sdk ``Context``; whatever sink
subscribes to that context (an MCAP file here, a live WebSocket server in :mod:`.live`) gets the
same messages. :func:`write_recording` replays a finished run (a
:class:`~mission_runner.sim.simulator.SimulationResult`, plus the controllers' step records for a
flight) through them into ``recording.mcap``; :func:`write_vehicle_recording` does the same for
one vehicle process, which has no ground truth.

Time is the mission clock: a message about step k is logged at t_k = start + kT in that clock's
seconds (0 at k = 0 for ``simulate``, the emulator's seconds for ``run``, UNIX time for vehicle
processes), so the recordings of one mission's processes line up.

Frames: ``world`` is east-north-up (x east, y north, z up; metres from the scenario's origin),
so Foxglove's top-down view matches ``xy.png``. The formation is planar: z is 0. Each vehicle has
a frame ``vehicle_<id>`` whose parent is ``world`` where the truth is known and, in a vehicle
process's own recording, its odometry frame ``odom_<id>``; its estimates of the others are
drawn in it. Topics and what each carries: docs/seeing.md.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import foxglove
import numpy as np
from foxglove.channels import (
    FrameTransformsChannel,
    LogChannel,
    PoseInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    Point3,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.records import Schema as McapSchema
from numpy.typing import NDArray

from .enclosing.shape import desired_offsets
from .enclosing.target import LOST, STATUS_NAMES
from .records import FORMATION_STATES, ControllerState
from .scenario import shape_schedule

if TYPE_CHECKING:
    from .config import Scenario
    from .metrics import SimulationResult
    from .paths import PathName
    from .records import StepRecord

#: The recording's file name in every output folder.
RECORDING = "recording.mcap"
WORLD = "world"
#: Points on the drawn circle (closed loop).
CIRCLE_POINTS = 72
#: Vehicle colours, RGB in [0, 1]: matplotlib's tab10, as in the figures.
PALETTE = (
    (0.122, 0.467, 0.706),
    (1.0, 0.498, 0.055),
    (0.173, 0.627, 0.173),
    (0.839, 0.153, 0.157),
    (0.580, 0.404, 0.741),
    (0.549, 0.337, 0.294),
    (0.890, 0.467, 0.761),
    (0.498, 0.498, 0.498),
    (0.737, 0.741, 0.133),
    (0.090, 0.745, 0.812),
)

_LEVELS = (
    (logging.ERROR, LogLevel.Error),
    (logging.WARNING, LogLevel.Warning),
    (logging.INFO, LogLevel.Info),
    (logging.DEBUG, LogLevel.Debug),
)

_NUMBER = {"type": ["number", "null"]}
VEHICLE_STATE_SCHEMA: dict[str, Any] = {
    "title": "mission_runner.VehicleState",
    "description": "One vehicle at step k: the controller's state and what it computed. "
    "North/east/down components in metres and m/s; null where unknown.",
    "type": "object",
    "properties": {
        "step": {"type": "integer"},
        "time_s": {"type": "number", "description": "t_k on the mission clock"},
        "state": {
            "type": "string",
            "description": "following, target_lost, holding, lost, ... (controller)",
        },
        "target": {
            "type": ["string", "null"],
            "description": "the target as the vehicle knew it: observed, predicted or lost",
        },
        "live": {"type": "boolean", "description": "in the formation at step k"},
        "phase_rad": _NUMBER,
        "command_north_m_s": _NUMBER,
        "command_east_m_s": _NUMBER,
        "command_down_m_s": _NUMBER,
        "consensus_north_m_s": _NUMBER,
        "consensus_east_m_s": _NUMBER,
        "neighbours_used": {"type": ["array", "null"], "items": {"type": "integer"}},
        "setpoint_lateness_s": {
            **_NUMBER,
            "description": "setpoint handed to the link minus t_k (flights only)",
        },
        "odometry_north_m": _NUMBER,
        "odometry_east_m": _NUMBER,
        "odometry_down_m": _NUMBER,
        "position_north_m": {**_NUMBER, "description": "ground truth, where known"},
        "position_east_m": _NUMBER,
        "slot_north_m": {**_NUMBER, "description": "desired place on the circle"},
        "slot_east_m": _NUMBER,
        "ranges": {
            "type": "array",
            "description": "the (horizontal) ranges the law was given at step k (peer 0: target); "
            "gated: rejected by the estimator as an outlier (flights only)",
            "items": {
                "type": "object",
                "properties": {
                    "peer": {"type": "integer"},
                    "range_m": {"type": "number"},
                    "gated": {"type": "boolean"},
                },
            },
        },
        "estimates": {
            "type": "array",
            "description": "phat_ij = p_i - p_j as estimated by this vehicle (peer 0: target)",
            "items": {
                "type": "object",
                "properties": {
                    "peer": {"type": "integer"},
                    "north_m": {"type": "number"},
                    "east_m": {"type": "number"},
                },
            },
        },
    },
}
METRICS_SCHEMA: dict[str, Any] = {
    "title": "mission_runner.MissionMetrics",
    "description": "The swarm at step k, scored against ground truth",
    "type": "object",
    "properties": {
        "step": {"type": "integer"},
        "time_s": {"type": "number"},
        "tracking_error_m": _NUMBER,
        "localization_error_m": _NUMBER,
        "phase_spacing_error_rad": _NUMBER,
        "consensus_speed_m_s": _NUMBER,
        "live_vehicles": {"type": "integer"},
    },
}


def vehicle_topic(vehicle_id: int, leaf: str) -> str:
    """``/vehicles/<id>/<leaf>`` (leaf: pose, slot, scene, state)."""
    return f"/vehicles/{vehicle_id}/{leaf}"


@dataclass(frozen=True)
class LogLine:
    """A log line as recorded: ``time_s`` on the mission clock (None: before k = 0), the logging
    level number, the logger's name and the message."""

    time_s: float | None
    level: int
    name: str
    message: str


class LogCapture(logging.Handler):
    """Collects the log lines of a run, each stamped with the mission time the caller last told
    it (:meth:`stamp`; the mission clock is not the wall clock, and only the caller knows it)."""

    def __init__(self, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.lines: list[LogLine] = []
        self.time_s: float | None = None

    def stamp(self, time_s: float) -> None:
        self.time_s = time_s

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(LogLine(self.time_s, record.levelno, record.name, record.getMessage()))

    @contextlib.contextmanager
    def attached(self) -> Iterator[LogCapture]:
        """Capture the root logger's lines while the block runs."""
        root = logging.getLogger()
        root.addHandler(self)
        try:
            yield self
        finally:
            root.removeHandler(self)


@dataclass
class VehicleView:
    """One vehicle at step k, from whatever the run knows of it (north/east [m], NED [m/s]).

    estimates_m: phat_ij ``(2,)`` by peer id (0 = target); position_m: truth ``(2,)`` or None;
    slot_m: its desired place on the circle ``(2,)`` or None; odometry_m ``(3,)`` NED or None.
    """

    vehicle_id: int
    step: int
    time_s: float
    state: str
    live: bool
    phase_rad: float | None = None
    command_ned_m_s: tuple[float, float, float] | None = None
    consensus_m_s: tuple[float, float] | None = None
    neighbours_used: tuple[int, ...] | None = None
    setpoint_lateness_s: float | None = None
    odometry_m: tuple[float, float, float] | None = None
    position_m: NDArray[np.float64] | None = None
    slot_m: NDArray[np.float64] | None = None
    estimates_m: Mapping[int, NDArray[np.float64]] | None = None
    ranges_m: Mapping[int, float] | None = None
    gated: tuple[int, ...] = ()
    target: str | None = None

    def document(self) -> dict[str, Any]:
        """The ``mission_runner.VehicleState`` message (NaN as null)."""
        command = self.command_ned_m_s or (None, None, None)
        consensus = self.consensus_m_s or (None, None)
        odometry = self.odometry_m or (None, None, None)
        position = (None, None) if self.position_m is None else self.position_m
        slot = (None, None) if self.slot_m is None else self.slot_m
        return {
            "step": self.step,
            "time_s": self.time_s,
            "state": self.state,
            "target": self.target,
            "live": self.live,
            "phase_rad": finite_or_none(self.phase_rad),
            "command_north_m_s": finite_or_none(command[0]),
            "command_east_m_s": finite_or_none(command[1]),
            "command_down_m_s": finite_or_none(command[2]),
            "consensus_north_m_s": finite_or_none(consensus[0]),
            "consensus_east_m_s": finite_or_none(consensus[1]),
            "neighbours_used": None if self.neighbours_used is None else list(self.neighbours_used),
            "setpoint_lateness_s": finite_or_none(self.setpoint_lateness_s),
            "odometry_north_m": finite_or_none(odometry[0]),
            "odometry_east_m": finite_or_none(odometry[1]),
            "odometry_down_m": finite_or_none(odometry[2]),
            "position_north_m": finite_or_none(position[0]),
            "position_east_m": finite_or_none(position[1]),
            "slot_north_m": finite_or_none(slot[0]),
            "slot_east_m": finite_or_none(slot[1]),
            "ranges": [
                {"peer": peer, "range_m": float(value), "gated": peer in self.gated}
                for peer, value in sorted((self.ranges_m or {}).items())
                if math.isfinite(value)
            ],
            "estimates": [
                {"peer": peer, "north_m": float(value[0]), "east_m": float(value[1])}
                for peer, value in sorted((self.estimates_m or {}).items())
                if np.all(np.isfinite(value))
            ],
        }


def view_of_record(record: StepRecord, vehicle_id: int, *, live: bool) -> VehicleView:
    """A controller's :class:`StepRecord` as a :class:`VehicleView` (no truth yet)."""
    lateness = record.setpoint_sent_s - record.time_s
    odometry = record.odometry_m
    return VehicleView(
        vehicle_id=vehicle_id,
        step=record.step,
        time_s=record.time_s,
        state=record.state,
        live=live,
        phase_rad=record.phase_rad,
        command_ned_m_s=record.velocity_ned_m_s,
        consensus_m_s=record.consensus_m_s,
        neighbours_used=record.neighbours_used,
        setpoint_lateness_s=lateness if math.isfinite(lateness) else None,
        odometry_m=odometry if all(math.isfinite(v) for v in odometry) else None,
        estimates_m=record.estimates_m,
        ranges_m=record.ranges_m,
        gated=record.gated,
        target=record.target or None,
    )


class MissionChannels:
    """Every topic of a mission, on one foxglove-sdk ``context``.

    ``vehicle_ids`` fixes the per-vehicle topics; ``radius_m`` is the circle's rho. Each method
    logs one kind of message at ``time_s`` (mission clock)."""

    def __init__(
        self, context: foxglove.Context, vehicle_ids: Sequence[int], radius_m: float
    ) -> None:
        self.radius_m = radius_m
        self.tf = FrameTransformsChannel("/tf", context=context)
        self.target = PoseInFrameChannel("/target/pose", context=context)
        self.formation = SceneUpdateChannel("/formation/scene", context=context)
        self.metrics = foxglove.Channel("/mission/metrics", schema=METRICS_SCHEMA, context=context)
        self.events = LogChannel("/mission/events", context=context)
        self.log = LogChannel("/log", context=context)
        self.colours = {i: PALETTE[index % len(PALETTE)] for index, i in enumerate(vehicle_ids)}
        self.pose = {
            i: PoseInFrameChannel(vehicle_topic(i, "pose"), context=context) for i in vehicle_ids
        }
        self.slot = {
            i: PoseInFrameChannel(vehicle_topic(i, "slot"), context=context) for i in vehicle_ids
        }
        self.scene = {
            i: SceneUpdateChannel(vehicle_topic(i, "scene"), context=context) for i in vehicle_ids
        }
        self.state = {
            i: foxglove.Channel(
                vehicle_topic(i, "state"), schema=VEHICLE_STATE_SCHEMA, context=context
            )
            for i in vehicle_ids
        }
        self._last_state: dict[int, str] = {}

    def log_step(
        self,
        time_s: float,
        *,
        shape: NDArray[np.float64],
        target_m: NDArray[np.float64] | None,
        positions_m: Mapping[int, NDArray[np.float64]],
        phases_rad: Mapping[int, float],
        views: Sequence[VehicleView],
        metrics: Mapping[str, Any] | None = None,
    ) -> None:
        """Everything about one step: the truth (target and known ``positions_m`` north/east
        ``(2,)`` by id; without a target, vehicles are drawn from their odometry), the formation
        with each vehicle's slot from its phase and ``shape`` ``(3, 3)``, the metrics, every
        vehicle's ``views`` (given their truth and slot here) and their state changes as events."""
        slots: dict[int, NDArray[np.float64]] = {}
        if target_m is not None:
            self.log_truth(time_s, target_m, positions_m)
            ids = [i for i, phase in phases_rad.items() if math.isfinite(phase)]
            offsets = desired_offsets(np.array([phases_rad[i] for i in ids]), self.radius_m, shape)
            slots = {i: target_m + offset for i, offset in zip(ids, offsets, strict=True)}
            self.log_formation(time_s, target_m, shape, slots)
        else:  # no truth at all (a vehicle process, a live view of a real mission)
            self.log_odometry(time_s, views)
        if metrics is not None:
            self.log_metrics(time_s, metrics)
        for view in views:
            view.position_m = positions_m.get(view.vehicle_id)
            view.slot_m = slots.get(view.vehicle_id)
            self.log_vehicle(view)

    def log_truth(
        self,
        time_s: float,
        target_m: NDArray[np.float64],
        positions_m: Mapping[int, NDArray[np.float64]],
    ) -> None:
        """The target and every vehicle whose true position is known (north/east ``(2,)``):
        ``/tf`` (world -> target, world -> vehicle_<id>), ``/target/pose``, the vehicles'
        ``pose``."""
        stamp = _timestamp(time_s)
        frames = {"target": target_m, **{f"vehicle_{i}": p for i, p in positions_m.items()}}
        transforms = [
            FrameTransform(
                timestamp=stamp,
                parent_frame_id=WORLD,
                child_frame_id=child,
                translation=_enu(position),
                rotation=_IDENTITY,
            )
            for child, position in frames.items()
        ]
        at = _nanoseconds(time_s)
        self.tf.log(FrameTransforms(transforms=transforms), log_time=at)
        self.target.log(_pose(stamp, target_m), log_time=at)
        for vehicle_id, position in positions_m.items():
            self.pose[vehicle_id].log(_pose(stamp, position), log_time=at)

    def log_odometry(self, time_s: float, views: Sequence[VehicleView]) -> None:
        """``/tf`` odom_<id> -> vehicle_<id> from each vehicle's own odometry (NED, metres):
        where no truth is known, the vehicle is drawn in its own odometry frame."""
        stamp = _timestamp(time_s)
        transforms = [
            FrameTransform(
                timestamp=stamp,
                parent_frame_id=f"odom_{view.vehicle_id}",
                child_frame_id=f"vehicle_{view.vehicle_id}",
                translation=_enu(view.odometry_m[:2], -view.odometry_m[2]),
                rotation=_IDENTITY,
            )
            for view in views
            if view.odometry_m is not None
        ]
        if transforms:
            self.tf.log(FrameTransforms(transforms=transforms), log_time=_nanoseconds(time_s))

    def log_formation(
        self,
        time_s: float,
        target_m: NDArray[np.float64],
        shape: NDArray[np.float64],
        slots_m: Mapping[int, NDArray[np.float64]],
    ) -> None:
        """``/formation/scene``: the circle around the target shaped by ``shape`` ``(3, 3)``, the
        target and the vehicles' slots; each slot also on the vehicle's ``slot`` topic."""
        stamp = _timestamp(time_s)
        circle = circle_points(target_m, shape, self.radius_m)
        entities = [
            SceneEntity(
                timestamp=stamp,
                frame_id=WORLD,
                id="circle",
                lines=[
                    LinePrimitive(
                        type=LinePrimitiveLineType.LineLoop,
                        thickness=2.0,
                        scale_invariant=True,
                        points=[Point3(x=east, y=north, z=0.0) for north, east in circle],
                        color=Color(r=0.3, g=0.3, b=0.3, a=0.8),
                    )
                ],
            ),
            SceneEntity(
                timestamp=stamp,
                frame_id=WORLD,
                id="target",
                spheres=[_sphere(target_m, 0.5, Color(r=0.0, g=0.0, b=0.0, a=1.0))],
            ),
        ]
        at = _nanoseconds(time_s)
        for vehicle_id, slot in slots_m.items():
            colour = self.colours[vehicle_id]
            entities.append(
                SceneEntity(
                    timestamp=stamp,
                    frame_id=WORLD,
                    id=f"slot_{vehicle_id}",
                    spheres=[_sphere(slot, 0.35, _colour(colour, 0.35))],
                )
            )
            self.slot[vehicle_id].log(_pose(stamp, slot), log_time=at)
        self.formation.log(SceneUpdate(entities=entities), log_time=at)

    def log_vehicle(self, view: VehicleView) -> None:
        """``/vehicles/<id>/state`` and ``/vehicles/<id>/scene``: where this vehicle estimates
        its neighbours and the target (in its own frame) and its velocity command; a change of
        its state is an event."""
        at = _nanoseconds(view.time_s)
        self.state[view.vehicle_id].log(view.document(), log_time=at)
        before = self._last_state.get(view.vehicle_id)
        if before is not None and before != view.state:
            self.log_event(
                view.time_s,
                f"vehicle {view.vehicle_id}: {before} -> {view.state} at step {view.step}",
                logging.INFO if view.state == ControllerState.FOLLOWING else logging.WARNING,
            )
        self._last_state[view.vehicle_id] = view.state
        stamp = _timestamp(view.time_s)
        colour = self.colours[view.vehicle_id]
        spheres, texts = [], []
        for peer, estimate in sorted((view.estimates_m or {}).items()):
            if not np.all(np.isfinite(estimate)):
                continue
            where = -np.asarray(estimate)  # phat_ij = p_i - p_j: j sits at -phat_ij from i
            spheres.append(_sphere(where, 0.3, _colour(colour, 0.6)))
            label = "target" if peer == 0 else str(peer)
            texts.append(
                TextPrimitive(
                    pose=Pose(position=_enu(where, 0.4), orientation=_IDENTITY),
                    billboard=True,
                    font_size=12.0,
                    scale_invariant=True,
                    color=_colour(colour),
                    text=f"{view.vehicle_id}: {label}",
                )
            )
        arrows = []
        if view.command_ned_m_s is not None:
            north, east = view.command_ned_m_s[0], view.command_ned_m_s[1]
            speed = math.hypot(north, east)
            if math.isfinite(speed) and speed > 1e-6:
                yaw = math.atan2(north, east)  # ENU: angle from +x (east) towards +y (north)
                arrows.append(
                    ArrowPrimitive(
                        pose=Pose(
                            position=Vector3(x=0.0, y=0.0, z=0.0),
                            orientation=Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
                        ),
                        shaft_length=speed,
                        shaft_diameter=0.08,
                        head_length=0.3,
                        head_diameter=0.25,
                        color=_colour(colour),
                    )
                )
        entity = SceneEntity(
            timestamp=stamp,
            frame_id=f"vehicle_{view.vehicle_id}",
            id=f"vehicle_{view.vehicle_id}",
            spheres=spheres,
            texts=texts,
            arrows=arrows,
        )
        self.scene[view.vehicle_id].log(SceneUpdate(entities=[entity]), log_time=at)

    def log_metrics(self, time_s: float, document: Mapping[str, Any]) -> None:
        """``/mission/metrics`` (``mission_runner.MissionMetrics``)."""
        self.metrics.log(dict(document), log_time=_nanoseconds(time_s))

    def log_event(self, time_s: float, message: str, level: int = logging.INFO) -> None:
        """``/mission/events``: something that happened to the mission or a vehicle."""
        self.events.log(_log(time_s, level, "mission", message), log_time=_nanoseconds(time_s))

    def log_line(self, time_s: float, line: LogLine) -> None:
        """``/log``: a line of the run's Python logging."""
        self.log.log(
            _log(time_s, line.level, line.name, line.message), log_time=_nanoseconds(time_s)
        )


def circle_points(
    centre_m: NDArray[np.float64], shape: NDArray[np.float64], radius_m: float
) -> NDArray[np.float64]:
    """The formation's circle: centre + A [rho cos phi, rho sin phi, 1] for ``CIRCLE_POINTS``
    angles phi; ``shape`` ``(3, 3)``. Returns ``(CIRCLE_POINTS, 2)`` north/east [m]."""
    angles = np.linspace(0.0, 2 * np.pi, CIRCLE_POINTS, endpoint=False)
    return np.asarray(centre_m) + desired_offsets(angles, radius_m, shape)


def write_recording(
    result: SimulationResult,
    path: PathName,
    *,
    records: Mapping[int, Sequence[StepRecord]] | None = None,
    start_s: float = 0.0,
    logs: Sequence[LogLine] = (),
    verdict: str | None = None,
) -> None:
    """Record run 0 of ``result`` into the MCAP file ``path`` (written atomically).

    records: the flight's controllers' records ``{id: [StepRecord]}`` (None for a simulation:
    its estimates come with the result); start_s: the mission clock at k = 0; logs: the run's
    log lines; verdict: the ``expect:`` verdict, recorded as the last event."""
    with recording_of(result, path, records=records, start_s=start_s, logs=logs) as finish:
        finish((), verdict)


@contextlib.contextmanager
def recording_of(
    result: SimulationResult,
    path: PathName,
    *,
    records: Mapping[int, Sequence[StepRecord]] | None = None,
    start_s: float = 0.0,
    logs: Sequence[LogLine] = (),
) -> Iterator[Callable[[Sequence[LogLine], str | None], None]]:
    """:func:`write_recording` in two parts: run 0's steps and the ``logs`` so far are written
    on entry, and the block gets ``finish(later_logs, verdict)``, which adds the lines logged
    since (a flight's landing) and the verdict. The file is in place once the block ends; a
    block that raises leaves none."""
    scenario = result.scenario
    end_s = start_s + result.commands_m_s.shape[1] * scenario.timing.step_s
    with _mcap(path, scenario) as context:
        channels = MissionChannels(
            context, [v.id for v in scenario.vehicles], scenario.algorithm.radius_m
        )
        backlog = _Backlog(channels, start_s, _scheduled_events(scenario, start_s), logs)
        _record_steps(result, records, channels, backlog, start_s)
        backlog.until(math.inf)

        def finish(later_logs: Sequence[LogLine], verdict: str | None) -> None:
            _Backlog(channels, start_s, (), later_logs).until(math.inf)
            if verdict is not None:
                channels.log_event(end_s, verdict)

        yield finish


def _record_steps(
    result: SimulationResult,
    records: Mapping[int, Sequence[StepRecord]] | None,
    channels: MissionChannels,
    backlog: _Backlog,
    start_s: float,
) -> None:
    """Every step of run 0 (truth, formation, metrics, each vehicle's view), with the
    ``backlog``'s events and lines due before each."""
    scenario = result.scenario
    ids = [vehicle.id for vehicle in scenario.vehicles]
    step_s = scenario.timing.step_s
    shape = shape_schedule(scenario)
    by_step = {
        vehicle_id: {record.step: record for record in vehicle_records}
        for vehicle_id, vehicle_records in (records or {}).items()
    }
    for k in range(result.commands_m_s.shape[1] + 1):
        time_s = start_s + k * step_s
        backlog.until(time_s)
        positions = result.positions_m[0, k]
        views = []
        for index, vehicle_id in enumerate(ids):
            view = _vehicle_view(
                result, by_step, index=index, vehicle_id=vehicle_id, k=k, time_s=time_s
            )
            if view is not None:
                view.live = bool(result.live[0, k, index])
                views.append(view)
        channels.log_step(
            time_s,
            shape=shape(k),
            target_m=result.target_m[k],
            positions_m={
                vehicle_id: positions[index]
                for index, vehicle_id in enumerate(ids)
                if np.all(np.isfinite(positions[index]))
            },
            phases_rad=dict(zip(ids, result.phases_rad[0, k].tolist(), strict=True)),
            views=views,
            metrics=_metrics_document(result, k, time_s),
        )


def write_vehicle_recording(
    vehicle_id: int,
    records: Sequence[StepRecord],
    path: PathName,
    *,
    scenario: Scenario | None = None,
    logs: Sequence[LogLine] = (),
) -> None:
    """One vehicle process's recording (no truth): its state, estimates and command per step,
    drawn in its odometry frame ``odom_<id>``; its state changes; its log lines."""
    start_s = records[0].time_s if records else 0.0
    with _mcap(path, scenario) as context:
        radius = scenario.algorithm.radius_m if scenario is not None else 1.0
        channels = MissionChannels(context, [vehicle_id], radius)
        backlog = _Backlog(channels, start_s, (), logs)
        for record in records:
            backlog.until(record.time_s)
            view = view_of_record(record, vehicle_id, live=record.state in FORMATION_STATES)
            channels.log_odometry(record.time_s, [view])
            channels.log_vehicle(view)
        backlog.until(math.inf)


class _Backlog:
    """Events ``(time_s, text)`` and log lines waiting for the step at their time, so the
    recording stays in time order; a line from before k = 0 (no time) goes out at k = 0."""

    def __init__(
        self,
        channels: MissionChannels,
        start_s: float,
        events: Iterable[tuple[float, str]],
        logs: Iterable[LogLine],
    ) -> None:
        self.channels = channels
        items: list[tuple[float, str | LogLine]] = [*events]
        items += [
            (start_s if line.time_s is None else max(line.time_s, start_s), line) for line in logs
        ]
        self.items = collections.deque(sorted(items, key=lambda item: item[0]))

    def until(self, time_s: float) -> None:
        """Log everything due at or before ``time_s``."""
        while self.items and self.items[0][0] <= time_s:
            at_s, item = self.items.popleft()
            if isinstance(item, LogLine):
                self.channels.log_line(at_s, item)
            else:
                self.channels.log_event(at_s, item)


@dataclass(frozen=True)
class RecordedMessage:
    """A message read back: its topic, schema name, log time (mission clock, ns) and decoded
    content (a protobuf message for Foxglove's schemas, a dict for this project's JSON ones)."""

    topic: str
    schema: str
    log_time_ns: int
    message: Any

    @property
    def time_s(self) -> float:
        return self.log_time_ns / 1e9


class _JsonDecoders(McapDecoderFactory):
    def decoder_for(
        self, message_encoding: str, schema: McapSchema | None
    ) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == "json" else None


def read_recording(
    path: PathName, topics: Iterable[str] | None = None
) -> Iterator[RecordedMessage]:
    """The messages of a recording in log-time order, decoded (``topics``: only those)."""
    from mcap.reader import make_reader  # noqa: PLC0415 - only readers need these
    from mcap_protobuf.decoder import DecoderFactory  # noqa: PLC0415 - only readers need it

    with open(path, "rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory(), _JsonDecoders()])
        wanted = None if topics is None else list(topics)
        for schema, channel, message, decoded in reader.iter_decoded_messages(
            topics=wanted, log_time_order=True
        ):
            yield RecordedMessage(
                channel.topic, schema.name if schema else "", message.log_time, decoded
            )


def recording_metadata(path: PathName) -> dict[str, dict[str, str]]:
    """A recording's metadata records by name (``scenario``: name, step_s, steps, vehicles,
    radius_m)."""
    from mcap.reader import make_reader  # noqa: PLC0415 - only readers need it

    with open(path, "rb") as handle:
        return {
            record.name: dict(record.metadata) for record in make_reader(handle).iter_metadata()
        }


@contextlib.contextmanager
def _mcap(path: PathName, scenario: Scenario | None) -> Iterator[foxglove.Context]:
    """A foxglove context whose only sink is the MCAP file ``path``, renamed into place only
    once complete (as every output: a crash never leaves a file that looks whole)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.partial")
    context = foxglove.Context()
    with foxglove.open_mcap(temporary, allow_overwrite=True, context=context) as writer:
        if scenario is not None:
            writer.write_metadata(
                "scenario",
                {
                    "name": scenario.name,
                    "step_s": repr(scenario.timing.step_s),
                    "steps": str(scenario.timing.steps),
                    "vehicles": " ".join(str(v.id) for v in scenario.vehicles),
                    "radius_m": repr(scenario.algorithm.radius_m),
                },
            )
        try:
            yield context
        except BaseException:
            temporary.unlink(missing_ok=True)  # the writer then closes a file no name leads to
            raise
    os.replace(temporary, path)


def _vehicle_view(
    result: SimulationResult,
    by_step: Mapping[int, Mapping[int, StepRecord]],
    *,
    index: int,
    vehicle_id: int,
    k: int,
    time_s: float,
) -> VehicleView | None:
    """Vehicle ``index`` at step k: from its controller's record in a flight; from the result's
    arrays in a simulation (no record at the final sample K: no command was computed there)."""
    live = bool(result.live[0, k, index])
    if by_step:
        record = by_step.get(vehicle_id, {}).get(k)
        return None if record is None else view_of_record(record, vehicle_id, live=live)
    if k >= result.commands_m_s.shape[1]:
        return None
    estimates = None
    if result.estimates_m is not None:
        ids = [vehicle.id for vehicle in result.scenario.vehicles]
        row = result.estimates_m[k, index]
        estimates = {peer: row[slot] for slot, peer in enumerate([0, *ids])}
    command = result.commands_m_s[0, k, index]
    target = int(result.target_status[0, k])
    return VehicleView(
        vehicle_id=vehicle_id,
        step=k,
        time_s=time_s,
        state=_view_state(live, target),
        target=STATUS_NAMES[target] if live else None,
        live=live,
        phase_rad=float(result.phases_rad[0, k, index]),
        command_ned_m_s=(float(command[0]), float(command[1]), 0.0),
        estimates_m=estimates,
    )


def _view_state(live: bool, target: int) -> ControllerState:
    """A simulated vehicle's state at a step: in the formation (the target tracked or lost), or
    absent."""
    if not live:
        return ControllerState.ABSENT
    return ControllerState.TARGET_LOST if target == LOST else ControllerState.FOLLOWING


def _metrics_document(result: SimulationResult, k: int, time_s: float) -> dict[str, Any]:
    last = k >= result.commands_m_s.shape[1]
    return {
        "step": k,
        "time_s": time_s,
        "tracking_error_m": finite_or_none(result.tracking_error_m[0, k]),
        "localization_error_m": None if last else finite_or_none(result.localization_error_m[0, k]),
        "phase_spacing_error_rad": finite_or_none(result.phase_spacing_error_rad[0, k]),
        "consensus_speed_m_s": None if last else finite_or_none(result.consensus_speed_m_s[0, k]),
        "live_vehicles": int(result.live[0, k].sum()),
    }


def _scheduled_events(scenario: Scenario, start_s: float) -> list[tuple[float, str]]:
    """The scenario's ``events:`` as (mission time, text)."""
    step_s = scenario.timing.step_s
    events = [(start_s, f"mission {scenario.name}: k = 0")]
    for event in scenario.events:
        k = event.step(step_s)
        detail = f" ({event.sensor})" if event.kind == "sensor_lost" and event.sensor else ""
        text = f"event: {event.kind}{detail} of vehicle {event.vehicle} at step {k}"
        events.append((start_s + k * step_s, text))
    return sorted(events)


def finite_or_none(value: float | np.floating[Any] | None) -> float | None:
    """A number for JSON: NaN, infinities and None as None."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _nanoseconds(time_s: float) -> int:
    return max(0, round(time_s * 1e9))


def _timestamp(time_s: float) -> Timestamp:
    nanoseconds = _nanoseconds(time_s)
    return Timestamp(nanoseconds // 1_000_000_000, nanoseconds % 1_000_000_000)


_IDENTITY = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def _enu(north_east_m: Sequence[float] | NDArray[np.float64], up_m: float = 0.0) -> Vector3:
    """A north/east point as a ``world`` (ENU) vector."""
    return Vector3(x=float(north_east_m[1]), y=float(north_east_m[0]), z=float(up_m))


def _pose(stamp: Timestamp, north_east_m: NDArray[np.float64]) -> PoseInFrame:
    return PoseInFrame(
        timestamp=stamp,
        frame_id=WORLD,
        pose=Pose(position=_enu(north_east_m), orientation=_IDENTITY),
    )


def _sphere(north_east_m: NDArray[np.float64], diameter_m: float, colour: Color) -> SpherePrimitive:
    return SpherePrimitive(
        pose=Pose(position=_enu(north_east_m), orientation=_IDENTITY),
        size=Vector3(x=diameter_m, y=diameter_m, z=diameter_m),
        color=colour,
    )


def _colour(rgb: tuple[float, float, float], alpha: float = 1.0) -> Color:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=alpha)


def _log(time_s: float, level: int, name: str, message: str) -> Log:
    foxglove_level = next(
        (mapped for number, mapped in _LEVELS if level >= number), LogLevel.Unknown
    )
    return Log(timestamp=_timestamp(time_s), level=foxglove_level, message=message, name=name)
