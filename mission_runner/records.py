"""The records every layer shares: the controller's state names, what a controller did at a
step, what a vehicle process did, a flight's progress as views show it, and the ground truth a
flight is scored against. Plain data (numpy arrays at most), so outputs, recordings and live views
read them without the runner."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


class ControllerState(enum.StrEnum):
    """What a vehicle is doing, as its step records, its status (:attr:`VehicleStatus.state`) and
    the outputs name it. A :class:`enum.StrEnum`: each member is its string, so what is written
    (CSV, JSON, MCAP, bus messages) is the bare name, and names read back compare equal."""

    # The vehicle process, around the flight.
    CONNECTING = "connecting"  # to its vehicle, the bus
    WAITING = "waiting"  # for the ground station's prepare (a controller: not started)
    READY = "ready"  # prepared: armed, in the air, streaming setpoints
    FAILED = "failed"  # could not get ready
    ABORTED = "aborted"  # stopped by the ground station
    DONE = "done"  # flew every step
    # The controller, step by step.
    HOVERING = "hovering"  # holding on the step grid until the mission's k = 0
    FOLLOWING = "following"  # the law on fresh data, the target observed or predicted
    TARGET_LOST = "target_lost"  # the law's formation with no target estimate left
    HOLDING = "holding"  # no fresh data (neighbours, own odometry) or not in OFFBOARD
    HELD = "held"  # the operator's hold
    SKIPPED = "skipped"  # the step's instant had passed before it could run
    TAKEN_OVER = "taken_over"  # someone else flies the vehicle: no longer driven
    LOST = "lost"  # its odometry or its bus connection stopped: no longer driven
    # Views only: a vehicle of which a frame has nothing.
    ABSENT = "absent"


#: Controller states (:attr:`VehicleStatus.state`) in which a vehicle flies the law on fresh data
#: as part of the formation: ``following`` the target (observed, or predicted while hidden), or
#: ``target_lost`` (no estimate of the target left: it holds or orbits the last estimate).
FORMATION_STATES = frozenset({ControllerState.FOLLOWING, ControllerState.TARGET_LOST})
#: Controller states of a step not flown by the law for want of fresh data: held (no fresh
#: neighbour message within the silence timeout, no own odometry, or not in OFFBOARD) or skipped
#: (its instant had passed before it could run).
STALE_STATES = frozenset({ControllerState.HOLDING, ControllerState.SKIPPED})


@dataclass(frozen=True)
class TruthSample:
    """Ground truth at t_k, for scoring only (never given to a controller): target_m ``(2,)``,
    positions_m ``(n, 2)`` north/east [m], alive ``(n,)`` (False where the vehicle's position is
    unknown at t_k)."""

    step: int
    time_s: float
    target_m: NDArray[np.float64]
    positions_m: NDArray[np.float64]
    alive: NDArray[np.bool_]


@dataclass
class StepRecord:
    """What the controller did at one step (for logs and progress views).

    setpoint_sent_s: mission-clock time at which the step's setpoint had been handed to the
    vehicle link (after ``set_velocity_ned`` returned); ``setpoint_sent_s - time_s`` is the
    step's lateness, for timing figures only (NaN if not measured). odometry_m: the own odometry
    (north, east, down) sampled at t_k (NaN if none). estimates_m: phat_ij ``(2,)`` [m] by peer
    id (0 = target). gated: peer ids whose range the estimator rejected as an outlier.
    ranges_m: the (horizontal) ranges the law was given, by peer id (0 = target).
    target: what the vehicle knew of the target at the step: ``observed`` (by itself or a
    neighbour), ``predicted`` or ``lost`` (``""``: not tracked, a skipped step).
    """

    step: int
    time_s: float
    state: ControllerState
    velocity_ned_m_s: tuple[float, float, float]
    consensus_m_s: tuple[float, float]
    phase_rad: float
    neighbours_used: tuple[int, ...]
    estimates_m: dict[int, NDArray[np.float64]]
    setpoint_sent_s: float = math.nan
    odometry_m: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    gated: tuple[int, ...] = ()
    ranges_m: dict[int, float] = field(default_factory=dict)
    target: str = ""
    #: Where the step's time went (mission clock): when the own odometry at t_k was in, when
    #: the own step message had been published, when the step's inputs were complete (or the
    #: deadline passed). NaN where the step did not get that far.
    odometry_ready_s: float = math.nan
    message_sent_s: float = math.nan
    inputs_ready_s: float = math.nan


@dataclass
class VehicleRun:
    """What one vehicle process did: its step records, final state and clock fit."""

    vehicle_id: int
    mission_id: str | None = None
    state: ControllerState = ControllerState.CONNECTING
    detail: str = ""
    records: list[StepRecord] = field(default_factory=list)
    start_s: float | None = None
    clock_rate: float = 1.0
    autopilot_clock_rate: float | None = None
    clock_residual_s: float | None = None
    skipped_steps: int = 0
    params: dict[str, float | int] = field(default_factory=dict)
    #: Received bus messages accepted and dropped by reason (``AuthCounters.as_dict``).
    bus_messages: dict[str, int] = field(default_factory=dict)
    #: Ranges the controller found impossible, by reason (``RangeGate.rejected``).
    ranges_rejected: dict[str, int] = field(default_factory=dict)
    #: Neighbours' setpoints in force dropped as impossible (``CommandGate.rejected``).
    commands_rejected: int = 0
    #: Setpoints whose mission-to-autopilot scale was bounded (``MavsdkVehicle.velocity_scale``).
    setpoints_scale_bounded: int = 0


@dataclass(frozen=True)
class Progress:
    """One step of a flight as a progress view shows it (truth-based errors: emulator only)."""

    step: int
    steps: int
    time_s: float
    states: dict[int, str]
    tracking_error_m: float
    localization_error_m: float
    #: The emulator's truth at t_k, for views (None if the world had no sample of step k).
    truth: TruthSample | None = None
