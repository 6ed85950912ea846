"""One place that turns a scenario into what the layers below the runner need: the algorithm's
and the filter's parameters (simulator and controllers), the autopilot parameters every vehicle
gets, and the bundled emulator's config (a vehicle's frequency and the shape schedule are the
scenario's geometry, :mod:`.scenario`; a controller's settings the runner's own). The simulator
(:mod:`.sim`), the in-process mission and the vehicle processes (:mod:`.runner`) and the emulated
world (:mod:`.world`) all build from here, so a default lives once, in the config model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .config import Scenario, SensorConfig, VehicleConfig
from .enclosing import EnclosingParams
from .enclosing.ekf import FilterSettings
from .enclosing.graph import (
    Adjacency,
    complete_graph,
    edge_graph,
    k_nearest_graph,
    live_adjacency,
    ring_graph,
)
from .sensors import SPEED_OF_LIGHT_M_S

if TYPE_CHECKING:
    from sitl.config import EmulatorConfig


#: PX4's COM_OBL_RC_ACT (offboard-loss failsafe) for each ``flight.on_lost``.
OFFBOARD_LOSS_ACTION = {"return": 3, "land": 4, "hold": 5}


def algorithm_params(scenario: Scenario, *, flown: bool = False) -> EnclosingParams:
    """The scenario's :class:`EnclosingParams`; ``flown``: for a vehicle's controller (see
    :func:`filter_settings`), else for the numeric simulator."""
    algorithm = scenario.algorithm
    return EnclosingParams(
        step_s=scenario.timing.step_s,
        beta=algorithm.beta,
        saturation_m_s=algorithm.saturation_m_s,
        forgetting_factor=algorithm.forgetting_factor,
        coupling_gain=algorithm.coupling_gain,
        coupling_gain_last=algorithm.coupling_gain_last,
        radius_m=algorithm.radius_m,
        initial_gain=algorithm.initial_gain,
        estimator=algorithm.estimator,
        filter=filter_settings(scenario, flown=flown) if algorithm.estimator == "ekf" else None,
        shared_ranges=algorithm.shared_ranges,
        # The guard's bearings need a bound of the estimates' error; without it none is kept.
        bound_range_noise_std_m=(
            None if scenario.safety.min_separation_m is None else scenario.sensors.range_noise_std_m
        ),
    )


def neighbour_graph(scenario: Scenario) -> Adjacency:
    """The scenario's neighbourhood graph ``(N, N)`` (``algorithm.graph``), fixed at load: the
    k nearest by the vehicles' initial positions. Assumes a validated scenario (the edges'
    problems are :func:`.checks.load_scenario`'s to report)."""
    graph, n = scenario.algorithm.graph, len(scenario.vehicles)
    if graph.kind == "ring":
        return ring_graph(n)
    if graph.kind == "k_nearest":
        positions = [vehicle.initial_position_m for vehicle in scenario.vehicles]
        return k_nearest_graph(positions, graph.k or 1)
    if graph.kind == "edges":
        return edge_graph(n, graph.edges or [])
    return complete_graph(n)


def live_schedule(scenario: Scenario) -> Callable[[int], NDArray[np.bool_]]:
    """live_at(k) -> ``(N,)`` bool: the vehicles the scenario's ``events`` have in the swarm at
    step k (from their ``vehicle_joins``, until their ``vehicle_lost``): the plan, not what
    happens in a flight."""
    ids = [v.id for v in scenario.vehicles]
    step_s = scenario.timing.step_s
    joins = {e.vehicle: e.step(step_s) for e in scenario.events if e.kind == "vehicle_joins"}
    losses = {e.vehicle: e.step(step_s) for e in scenario.events if e.kind == "vehicle_lost"}
    start = np.array([joins.get(i, 0) for i in ids])
    stop = np.array([losses.get(i, np.iinfo(np.int64).max) for i in ids])
    return lambda k: (start <= k) & (k < stop)


@dataclass(frozen=True)
class RangingGraph:
    """Which pairs the UWB radios range under a sparse ``algorithm.graph``: a radio ranges only
    with the neighbours it is scheduled with, and the schedule is the graph among the vehicles
    still flying (a ring closes over a loss, :func:`.enclosing.graph.live_adjacency`). The
    numeric simulator, the emulated world and the range aid all range by it.

    graph: the scenario's ``(N, N)``; ring: it closes over losses; frame ``(N, N)``: every edge
    the plan's live graphs have over the run (a ring's closing edges included), the pairs an
    airtime schedule's round serves (:func:`.sensors.range_slots`).
    """

    graph: Adjacency
    ring: bool
    frame: Adjacency

    @classmethod
    def of(cls, scenario: Scenario) -> RangingGraph | None:
        """The scenario's ranging graph; None for the complete graph (every pair ranges)."""
        if scenario.algorithm.graph.kind == "complete":
            return None
        graph, ring = neighbour_graph(scenario), scenario.algorithm.graph.kind == "ring"
        live_at, steps = live_schedule(scenario), scenario.timing.steps
        # The live set changes only at the events' steps: the union over those is the run's.
        changes = {0} | {
            e.step(scenario.timing.step_s)
            for e in scenario.events
            if e.kind in {"vehicle_joins", "vehicle_lost"}
        }
        frame = np.zeros_like(graph)
        for k in sorted(step for step in changes if step <= steps):
            frame |= live_adjacency(graph, live_at(k), ring=ring)
        return cls(graph=graph, ring=ring, frame=frame)

    def among(self, live: ArrayLike) -> Adjacency:
        """The pairs ranged while the vehicles ``live`` ``(N,)`` bool fly ``(N, N)``."""
        return live_adjacency(self.graph, live, ring=self.ring)


def range_error_std_m(sensors: SensorConfig) -> float:
    """The std of one range's error the UWB model gives outside NLOS [m]: timestamp noise,
    pair bias, multipath and single-sided TWR's clock error (1/2 c t_reply (e_i - e_j)) in
    quadrature. A filter treats them as white: the lasting ones are its error floor."""
    clock_m = (
        0.5 * SPEED_OF_LIGHT_M_S * sensors.range_reply_time_s * math.sqrt(2.0) * 1e-6
    ) * sensors.range_clock_offset_std_ppm
    return math.sqrt(
        sensors.range_noise_std_m**2
        + sensors.range_bias_std_m**2
        + sensors.range_multipath_std_m**2
        + clock_m**2
    )


#: Gated ranges in a row after which an edge restarts, without NLOS bursts to outlast.
GATE_PATIENCE = 10


def gate_patience(scenario: Scenario) -> int:
    """How many rejected ranges in a row mean an edge has lost track: with NLOS bursts of mean
    duration D, 5 D of steps (a burst lasts longer with probability e^-5 < 1 %), since an
    edge that restarts on a burst's biased ranges starts from the bias (docs/algorithm.md, "Relative
    localization with noise": 0.43 m per edge at 10 with 2 s bursts in 0.1 s steps)."""
    sensors = scenario.sensors
    if sensors.range_outlier_probability == 0 or sensors.range_nlos_duration_s == 0:
        return GATE_PATIENCE
    burst_steps = sensors.range_nlos_duration_s / scenario.timing.step_s
    return max(GATE_PATIENCE, math.ceil(5.0 * burst_steps))


def gate_chi2(scenario: Scenario) -> float | None:
    """The gate: ``gate_chi2``, or where the sensors have NLOS bursts the smaller of it and
    ``nlos_gate_chi2`` (measured on the bench's UWB model with 5 % bursts, 100 runs: per edge
    p95 0.094 m at 10.83, 0.070 m at 6.63, 0.063 m without NLOS; 36 good ranges gated a run
    instead of 4). None: no gate."""
    given, sensors = scenario.algorithm.estimator_settings, scenario.sensors
    bursts = sensors.range_outlier_probability > 0 and sensors.range_nlos_duration_s > 0
    if given.gate_chi2 is None or not bursts:
        return given.gate_chi2
    return min(given.gate_chi2, given.nlos_gate_chi2)


def filter_settings(scenario: Scenario, *, flown: bool = False) -> FilterSettings:
    """The filter estimator's settings: ``algorithm.estimator_settings``, with the noise figures
    it leaves unset taken from the model of the sensors that produce the measurements: ranges
    from ``sensors:`` (the UWB model of the simulator and of the emulated world alike);
    displacements from ``sensors:`` in the simulator, and, ``flown``, from the emulator's
    odometry model (``flight.emulator.odometry``: what produces a flight's odometry), see
    :func:`odometry_noise_std_m`. A real autopilot's odometry has no model here: on hardware,
    give both figures in ``algorithm.estimator_settings``."""
    given, sensors = scenario.algorithm.estimator_settings, scenario.sensors
    range_std, common_std = given.range_noise_std_m, given.range_common_std_m
    if range_std is None:
        range_std = range_error_std_m(sensors)
    if common_std is None and sensors.range_scheme == "one_exchange_per_pair":
        common_std = range_std  # both ends read one number: averaging them removes nothing
    elif common_std is None:
        common_std = math.hypot(sensors.range_bias_std_m, sensors.range_multipath_std_m)
    displacement_std = given.displacement_noise_std_m
    if displacement_std is None and flown:
        displacement_std = odometry_noise_std_m(scenario)
    elif displacement_std is None:
        # A drift is a displacement error too: its share of one step, in quadrature.
        drift_m = sensors.displacement_drift_m_s * scenario.timing.step_s
        displacement_std = math.hypot(sensors.displacement_noise_std_m, drift_m)
    return FilterSettings(
        range_noise_std_m=range_std,
        displacement_noise_std_m=displacement_std,
        gate_chi2=gate_chi2(scenario),
        gate_patience=gate_patience(scenario)
        if given.gate_patience is None
        else given.gate_patience,
        initial_forgetting_factor=given.initial_forgetting_factor,
        handover_updates=given.handover_updates,
        handover_std_m=given.handover_std_m,
        range_common_std_m=common_std,
        gate_long_only=given.gate_long_only,
    )


def odometry_noise_std_m(scenario: Scenario) -> float:
    """Per-axis std of one vehicle's displacement over one step [m] in a flight on the emulator,
    from its odometry model: white position noise at both ends of the step (sqrt 2 of it; the
    controller's interpolation to t_k only lessens it), plus one step of the drift velocity, whose
    random walk is taken at the end of the mission. In quadrature."""
    odometry = emulator_config(scenario).odometry
    step_s = scenario.timing.step_s
    mission_s = scenario.timing.steps * step_s
    drift_m_s = math.hypot(
        odometry.drift_bias_std_m_s,
        odometry.drift_random_walk_m_s_per_sqrt_s * math.sqrt(mission_s),
    )
    return math.hypot(math.sqrt(2.0) * odometry.position_noise_std_m, drift_m_s * step_s)


def altitude_of(scenario: Scenario, vehicle: VehicleConfig) -> float:
    """The altitude ``vehicle`` holds [m above home]."""
    return vehicle.altitude_m or scenario.flight.altitude_m


def autopilot_params(scenario: Scenario) -> dict[str, float | int]:
    """The parameters every vehicle gets before take-off: the offboard-loss failsafe matching
    ``flight.on_lost``, then ``flight.autopilot_params`` (which win)."""
    return {
        "COM_OBL_RC_ACT": OFFBOARD_LOSS_ACTION[scenario.flight.on_lost],
        **scenario.flight.autopilot_params,
    }


def emulator_config(scenario: Scenario, **overrides: Any) -> EmulatorConfig:
    """The bundled emulator's config for this scenario: ``flight.emulator``, then ``overrides``,
    then what the scenario implies (vehicle count, placement, seed, a physics rate whose step
    divides T)."""
    from sitl.config import EmulatorConfig  # noqa: PLC0415 - the simulator does not need sitl

    return EmulatorConfig.model_validate(emulator_settings(scenario, **overrides))


#: The physics rate a flight's emulator runs at least at, by clock [Hz]. Real time: PX4's
#: rate-controller-like 200 Hz, so that a setpoint takes effect within 5 ms as on PX4 and the
#: 25 Hz odometry and 50 Hz autopilot fall on steps. Lockstep: 40 Hz, a fifth of the work (the
#: emulator was about half of the demo's CPU at 200 Hz); the velocity and tilt lags are
#: discretised exactly (sitl/physics.py), so the motion does not depend on the rate.
MIN_PHYSICS_RATE_HZ = {"realtime": 200.0, "lockstep": 40.0}


def physics_rate_hz(step_s: float, clock_mode: str) -> float:
    """The lowest rate >= the clock's minimum whose step divides T, so that the sensors sample
    at t_k exactly."""
    return math.ceil(MIN_PHYSICS_RATE_HZ[clock_mode] * step_s) / step_s


def emulator_settings(scenario: Scenario, **overrides: Any) -> dict[str, Any]:
    """What :func:`emulator_config` validates, as plain data."""
    data = {**scenario.flight.emulator, **overrides}
    physics = dict(data.get("physics") or {})
    clock = {"mode": scenario.flight.clock, **(data.get("clock") or {})}
    physics.setdefault("rate_hz", physics_rate_hz(scenario.timing.step_s, clock["mode"]))
    data["physics"] = physics
    data.setdefault("vehicles", len(scenario.vehicles))
    data.setdefault("seed", scenario.seed)
    data.setdefault(
        "placement",
        {
            "positions": [
                {"north_m": v.initial_position_m[0], "east_m": v.initial_position_m[1]}
                for v in scenario.vehicles
            ]
        },
    )
    return data
