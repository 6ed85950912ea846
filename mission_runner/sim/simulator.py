"""The numeric simulator: the paper's discrete-time model around the algorithm.

p_i(k+1) = p_i(k) + T sat_{U_i}(u_i(k)) (first-order dynamics with a speed bound), ranges and
odometry synthesised from the true positions with optional noise, dropout and drift, and the
algorithm run as :class:`~mission_runner.enclosing.SwarmEnclosing` - the same step function a
flying vehicle runs. Runs are batched on a leading axis: ``runs=N`` simulates N initial conditions
at once. Ground truth is used here only to make measurements and to score the run.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..config import FLIGHT_ONLY_EVENTS, FLIGHT_ONLY_SENSORS, Scenario
from ..enclosing import (
    LOST,
    StepOutputs,
    SwarmEnclosing,
    TargetEstimate,
    TargetTrack,
    track_target,
)
from ..enclosing.control import saturate
from ..enclosing.edges import EdgeIndex
from ..enclosing.graph import Adjacency, components, live_adjacency, slot_mask
from ..enclosing.separation import separation_guard
from ..errors import ConfigError, SimulationError
from ..metrics import SimulationResult, closest_live_pair, closest_pair, edge_rms, score
from ..scenario import omega_of, shape_matrices, target_positions
from ..sensors import (
    UwbRanging,
    odometry_drift,
    odometry_error_step,
    range_readings,
    target_seen,
)
from ..wiring import RangingGraph, algorithm_params, live_schedule, neighbour_graph

logger = logging.getLogger(__name__)


def initial_conditions(
    scenario: Scenario, runs: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Initial positions ``(B, N, 2)`` and phases ``(B, N)``: run 0 as pinned, the rest drawn."""
    positions = np.array([v.initial_position_m for v in scenario.vehicles], dtype=float)
    phases = np.array([v.initial_phase_rad for v in scenario.vehicles], dtype=float)
    positions = np.repeat(positions[None], runs, axis=0)
    phases = np.repeat(phases[None], runs, axis=0)
    if runs > 1:
        rng = np.random.default_rng([scenario.seed, 1])
        extra, n = runs - 1, positions.shape[1]
        radius = scenario.batch.position_spread_m * np.sqrt(rng.uniform(size=(extra, n)))
        angle = rng.uniform(0, 2 * np.pi, size=(extra, n))
        positions[1:] += radius[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1)
        if scenario.batch.randomize_phases:
            phases[1:] = rng.uniform(0, 2 * np.pi, size=(extra, n))
    return positions, phases


class _Noise:
    """Measurement noise for a batch; run 0 draws from its own stream so it equals a single run."""

    def __init__(self, seed: int, runs: int) -> None:
        self._first = np.random.default_rng([seed, 0])
        self._rest = np.random.default_rng([seed, 2]) if runs > 1 else None

    def normal(self, scale: float = 1.0, size: tuple[int, ...] = ()) -> NDArray[np.float64]:
        return self._draw("normal", size, scale=scale)

    def uniform(
        self, low: float = 0.0, high: float = 1.0, size: tuple[int, ...] = ()
    ) -> NDArray[np.float64]:
        return self._draw("uniform", size, low=low, high=high)

    def _draw(self, method: str, shape: tuple[int, ...], **kwargs: float) -> NDArray[np.float64]:
        """``shape`` ``(B, ...)``: run 0 from its own stream, the other B - 1 runs from the rest."""
        first = getattr(self._first, method)(size=(1, *shape[1:]), **kwargs)
        if self._rest is None:
            return first
        rest = getattr(self._rest, method)(size=(shape[0] - 1, *shape[1:]), **kwargs)
        return np.concatenate([first, rest], axis=0)


def flight_only_events(scenario: Scenario) -> list[str]:
    """The scenario's events the numeric model cannot play (empty: it can simulate them all)."""
    kinds = {e.kind for e in scenario.events} & FLIGHT_ONLY_EVENTS
    sensors = {
        f"sensor_lost ({e.sensor})" for e in scenario.events if e.sensor in FLIGHT_ONLY_SENSORS
    }
    return sorted(kinds | sensors)


def _sensor_windows(scenario: Scenario, sensor: str) -> Callable[[int], NDArray[np.bool_]]:
    """down(k) -> ``(N,)`` bool: whose ``sensor`` is out at step k (``sensor_lost`` events, and
    for the tracker ``target_hidden`` occlusions, of one vehicle or of every one)."""
    ids = [v.id for v in scenario.vehicles]
    step_s = scenario.timing.step_s
    windows: list[tuple[NDArray[np.bool_], int, float]] = []
    for event in scenario.events:
        hides = event.kind == "target_hidden" and sensor == "tracker"
        if not (hides or (event.kind == "sensor_lost" and event.sensor == sensor)):
            continue
        who = np.array([event.vehicle in (None, i) for i in ids])
        first, steps = event.step(step_s), event.duration_steps(step_s)
        windows.append((who, first, np.inf if steps is None else first + steps))

    def down(k: int) -> NDArray[np.bool_]:
        out = np.zeros(len(ids), dtype=bool)
        for who, first, end in windows:
            if first <= k < end:
                out |= who
        return out

    return down


@dataclass
class _GraphSchedule:
    """The live vehicles' neighbourhood graph at step k (``algorithm.graph``), worked out once
    per set of live vehicles: ``graph`` the scenario's ``(N, N)``, None for the complete graph
    (every live vehicle a neighbour of every other, the code path without masks)."""

    graph: Adjacency | None
    ring: bool
    live_at: Callable[[int], NDArray[np.bool_]]
    _cache: dict[bytes, tuple[Adjacency, NDArray[np.bool_], bool]] = field(default_factory=dict)

    @classmethod
    def of(cls, scenario: Scenario, live_at: Callable[[int], NDArray[np.bool_]]) -> _GraphSchedule:
        sparse = scenario.algorithm.graph.kind != "complete"
        graph = neighbour_graph(scenario) if sparse else None
        return cls(graph=graph, ring=scenario.algorithm.graph.kind == "ring", live_at=live_at)

    def at(self, k: int) -> tuple[Adjacency, NDArray[np.bool_], bool] | None:
        """The live graph at step k ``(N, N)``, its slot mask ``(N, N+1)`` and whether the live
        vehicles are connected; None for the complete graph."""
        if self.graph is None:
            return None
        live = self.live_at(k)
        key = live.tobytes()
        if key not in self._cache:
            adjacency = live_adjacency(self.graph, live, ring=self.ring)
            connected = len(components(adjacency, live)) <= 1
            # A lost vehicle's row keeps its own neighbours: its phase goes on as with the
            # complete graph's (recorded, though nobody hears it).
            rows = np.where(live[:, None], adjacency, self.graph)
            self._cache[key] = (adjacency, slot_mask(rows), connected)
        return self._cache[key]

    def slot_frame(self, steps: int) -> NDArray[np.bool_] | None:
        """Every (vehicle, slot) pair the step's masks have over steps 0..steps ``(N, N+1)``
        (the edges a swarm kept per edge needs), if they are few enough for that to pay:
        at most :data:`PER_EDGE_MAX_DENSITY` of the entries; None otherwise (and for the
        complete graph)."""
        if self.graph is None:
            return None
        union = np.zeros((self.graph.shape[0], self.graph.shape[0] + 1), dtype=bool)
        for k in range(steps + 1):
            union |= self.at(k)[1]  # type: ignore[index]  # not None with a graph
        return union if union.sum() <= PER_EDGE_MAX_DENSITY * union.size else None

    def disconnected_step(self, steps: int) -> int:
        """The first step in 0..steps at which the live graph is disconnected, -1 if none."""
        for k in range(steps + 1):
            now = self.at(k)
            if now is not None and not now[2]:
                return k
        return -1


#: A sparse graph's swarm is kept per edge (:class:`~mission_runner.enclosing.edges.EdgeIndex`)
#: when its edges are at most this fraction of the (vehicle, slot) pairs: the per-edge step
#: gathers and sums by row, which costs more per entry than the planes. Denser graphs (a
#: handful of vehicles on a ring, the complete graph given as edges) stay on the planes and
#: simulate as before.
PER_EDGE_MAX_DENSITY = 0.25
#: The most memory a simulation may need for its results [bytes]: a scenario that needs more is
#: refused before anything is allocated (``timing.steps: 10000000`` with ``--runs 100`` once grew
#: until the machine swapped).
MEMORY_LIMIT_BYTES = 4 << 30
#: Run 0's estimates (for the recording) are kept up to this size [bytes]: they grow as N^2 K
#: (paper scenario 0.2 MB, 32 vehicles x 300 steps 5 MB; 256 vehicles x 600 steps would be 630 MB).
ESTIMATES_LIMIT_BYTES = 8 << 20


def estimates_bytes(steps: int, vehicles: int) -> int:
    """Size of run 0's estimates ``(K, N, N+1, 2)`` as float64."""
    return 16 * steps * vehicles * (vehicles + 1)


def memory_estimate_bytes(steps: int, vehicles: int, runs: int) -> int:
    """About how much memory :func:`simulate` and the outputs of its result need: the recorded
    series ``(B, K, N)`` and the metrics' copies of them, the per-step working arrays
    ``(B, N, N+1)``, the shape and target schedules ``(K,)`` and run 0's timeseries.csv text
    (measured within 15 % on paper_tracking)."""
    series = 2 * runs * (steps + 1) * (41 * vehicles + 56)
    working = 32 * 8 * runs * vehicles * (vehicles + 1)
    schedules = 96 * (steps + 2)
    text = 2 * (steps + 1) * (80 + 60 * vehicles)
    estimates = estimates_bytes(steps, vehicles)
    return (
        series
        + working
        + schedules
        + text
        + (estimates if estimates <= ESTIMATES_LIMIT_BYTES else 0)
    )


def check_memory(scenario: Scenario, runs: int, source: str) -> None:
    """Raise :class:`ConfigError` (at ``timing.steps``, naming the fields that multiply) if
    simulating ``scenario`` ``runs`` times would need more than :data:`MEMORY_LIMIT_BYTES`."""
    steps, vehicles = scenario.timing.steps, len(scenario.vehicles)
    needed = memory_estimate_bytes(steps, vehicles, runs)
    if needed > MEMORY_LIMIT_BYTES:
        problem = (
            f"{steps} steps x {vehicles} vehicles x {runs} run(s) need about "
            f"{needed / (1 << 30):.1f} GiB of memory, more than {MEMORY_LIMIT_BYTES >> 30} GiB: "
            "lower timing.steps, the number of vehicles or --runs"
        )
        raise ConfigError(source, [("timing.steps", problem)])


def simulate(
    scenario: Scenario, runs: int = 1, on_step: Callable[[int, int], None] | None = None
) -> SimulationResult:
    """Run ``scenario`` ``runs`` times (vectorised). ``on_step(k, total)`` reports progress.

    Raises :class:`ConfigError` before any work if the result would not fit in memory
    (:func:`check_memory`)."""
    if runs < 1:
        raise SimulationError(f"runs must be >= 1, got {runs}")
    check_memory(scenario, runs, f"scenario {scenario.name}")
    flying_only = flight_only_events(scenario)
    if flying_only:
        raise SimulationError(
            f"events {flying_only} need real links and sensors: fly the scenario with "
            "'mission-runner run' (the numeric model has neither)"
        )
    plan = _Plan.of(scenario)
    state = _State.initial(scenario, runs, plan)
    steps = scenario.timing.steps
    out = _allocate(runs, steps, len(scenario.vehicles))
    for k in range(steps):
        _step(scenario, plan, state, out, k)
        if on_step is not None:
            on_step(k + 1, steps)

    position = state.position
    out["positions_m"][:, steps] = position
    out["phases_rad"][:, steps] = state.swarm.phase_rad
    out["live"][:, steps] = plan.live_at(steps)
    if state.swarm.edge_index is None:
        gaps = position[:, :, None, :] - position[:, None, :, :]
        out["separation_m"][:, steps] = closest_pair(
            np.sqrt(np.sum(gaps * gaps, axis=-1)), out["live"][:, steps]
        )
    else:
        out["separation_m"][:, steps] = closest_live_pair(position, out["live"][:, steps])
    _record_graph(scenario, plan, out, runs)
    return score(scenario, plan.times, plan.target[: steps + 1], out)


def _record_graph(scenario: Scenario, plan: _Plan, out: dict[str, NDArray[Any]], runs: int) -> None:
    """A sparse graph's ``graph_disconnected_step`` into ``out`` (and a warning if a loss cut
    it); nothing for the complete graph, whose summary stays as it was."""
    if plan.graph.graph is None:
        return
    step = plan.graph.disconnected_step(scenario.timing.steps)
    cut = plan.graph.at(step) if step >= 0 else None
    if cut is not None:
        parts = components(cut[0], plan.live_at(step))
        named = " and ".join("{" + ",".join(map(str, part)) + "}" for part in parts)
        logger.warning(
            "algorithm.graph: the live vehicles' graph is disconnected from step %d on "
            "(vehicles %s, indices in vehicles:): a loss cut it",
            step,
            named,
        )
    out["graph_disconnected_step"] = np.full(runs, step, dtype=np.int64)


@dataclass(frozen=True)
class _Plan:
    """What a scenario fixes for every run and step: the step times ``(K+1,)``, the target's
    positions ``(K+2, 2)`` and the shape matrices at them, the vehicles' frequencies,
    target sensing and speed bounds ``(N,)`` / ``(N, 1)``, and who is live and whose tracker
    and radio are out at step k."""

    times: NDArray[np.float64]
    target: NDArray[np.float64]
    shapes: NDArray[np.float64]
    omega: NDArray[np.float64]
    senses: NDArray[np.bool_]
    speed_limit: NDArray[np.float64]
    live_at: Callable[[int], NDArray[np.bool_]]
    tracker_down: Callable[[int], NDArray[np.bool_]]
    radio_down: Callable[[int], NDArray[np.bool_]]
    graph: _GraphSchedule

    @classmethod
    def of(cls, scenario: Scenario) -> _Plan:
        step_s, steps = scenario.timing.step_s, scenario.timing.steps
        times = np.arange(steps + 1, dtype=np.float64) * step_s
        live_at = live_schedule(scenario)
        return cls(
            times=times,
            target=target_positions(scenario.target.path, np.append(times, times[-1] + step_s)),
            shapes=shape_matrices(scenario.algorithm.shape, np.append(times, times[-1] + step_s)),
            omega=np.array([omega_of(scenario, v) for v in scenario.vehicles]),
            senses=np.array([v.senses_target for v in scenario.vehicles]),
            speed_limit=np.array([v.speed_limit_m_s for v in scenario.vehicles])[:, None],
            live_at=live_at,
            tracker_down=_sensor_windows(scenario, "tracker"),
            radio_down=_sensor_windows(scenario, "uwb"),
            graph=_GraphSchedule.of(scenario, live_at),
        )


@dataclass
class _State:
    """The batch of runs as it goes: true positions ``(B, N, 2)`` and where they started, the
    algorithm, the sensors and their errors, the commands in force ``(B, N, 2)`` (as each
    vehicle's step message carries them; NaN before k = 0) and the target's track."""

    position: NDArray[np.float64]
    origin: NDArray[np.float64]
    swarm: SwarmEnclosing
    noise: _Noise
    drift: NDArray[np.float64]
    uwb: UwbRanging
    odometry_error: NDArray[np.float64]
    in_force: NDArray[np.float64]
    track: TargetTrack

    @classmethod
    def initial(cls, scenario: Scenario, runs: int, plan: _Plan) -> _State:
        n = len(scenario.vehicles)
        position, phase = initial_conditions(scenario, runs)
        swarm = SwarmEnclosing(
            algorithm_params(scenario),
            phase,
            np.broadcast_to(plan.omega, phase.shape),
            edges=plan.graph.slot_frame(scenario.timing.steps),
        )
        noise = _Noise(scenario.seed, runs)
        drift = odometry_drift(scenario.sensors, noise, (runs, n))
        ranging = RangingGraph.of(scenario)  # the pairs a round of ranging serves
        return cls(
            position=position,
            origin=position.copy(),
            swarm=swarm,
            noise=noise,
            drift=drift,
            uwb=UwbRanging(
                scenario.sensors,
                n,
                scenario.timing.step_s,
                batch=(runs,),
                graph=None if ranging is None else ranging.frame,
            ),
            odometry_error=np.zeros((runs, n, 2)),
            in_force=np.full((runs, n, 2), np.nan),
            # One track of the target per run: every vehicle hears every observation at once
            # (the relay of a complete graph without loss), so every vehicle's track is this one.
            track=TargetTrack.initial((runs,)),
        )


def _allocate(runs: int, steps: int, n: int) -> dict[str, NDArray[Any]]:
    """The recorded series of ``runs`` runs of ``steps`` steps of ``n`` vehicles, unfilled."""
    out: dict[str, NDArray[Any]] = {
        "positions_m": np.empty((runs, steps + 1, n, 2)),
        "phases_rad": np.empty((runs, steps + 1, n)),
        "commands_m_s": np.empty((runs, steps, n, 2)),
        "live": np.empty((runs, steps + 1, n), dtype=bool),
        "localization_error_m": np.empty((runs, steps)),
        "localization_rms_m": np.empty((runs, steps)),
        "gated_ranges": np.empty((runs, steps), dtype=np.int64),
        "nlos_ranges": np.empty((runs, steps), dtype=np.int64),
        "false_rejections": np.empty((runs, steps), dtype=np.int64),
        "consensus_speed_m_s": np.empty((runs, steps)),
        "separation_m": np.empty((runs, steps + 1)),
        "target_status": np.empty((runs, steps), dtype=np.int8),
    }
    # Run 0 only (a 1000-run batch would hold 1000 times as much for nobody to look at), and only
    # while small: they grow as N^2.
    if estimates_bytes(steps, n) <= ESTIMATES_LIMIT_BYTES:
        out["estimates_m"] = np.empty((steps, n, n + 1, 2))
    return out


@dataclass(frozen=True)
class _Measured:
    """Step k's truth and measurements, on ``(B, N, N+1)`` planes (slot 0 the target) or, for
    a swarm kept per edge, ``(B, E)``: the true p_i - p_j north and east, the ranges, the
    UWB radios' ranges (``(B, N, N)``, or ``(B, E_v)`` on the edges between vehicles), the
    target's ranges ``(B, N)`` and the step's neighbour mask (None: the complete graph)."""

    truth_north: NDArray[np.float64]
    truth_east: NDArray[np.float64]
    ranges: NDArray[np.float64]
    radio_ranges: NDArray[np.float64]
    target_range: NDArray[np.float64]
    neighbours: NDArray[np.bool_] | None


def _step(
    scenario: Scenario,
    plan: _Plan,
    state: _State,
    out: dict[str, NDArray[Any]],
    k: int,
) -> None:
    """Step ``k`` of every run: measure, estimate, command, record into ``out`` and move."""
    runs, n = state.position.shape[:2]
    live = np.broadcast_to(plan.live_at(k), (runs, n))
    swarm = state.swarm
    if swarm.edge_index is None:
        measured = _measure(scenario, plan, state, out, k, live)
    else:
        measured = _measure_edges(scenario, plan, state, out, k, live)
    odometry, target_estimate, holding = _inputs(
        scenario, plan, state, measured.target_range, k, live
    )
    out["phases_rad"][:, k] = swarm.phase_rad
    step = swarm.step(
        odometry_m=odometry,
        range_m=measured.ranges,
        live=live,
        target_velocity_m_s=target_estimate.velocity_m_s,
        shape_now=plan.shapes[k],
        shape_next=plan.shapes[k + 1],
        neighbours=measured.neighbours,
    )
    _record_estimates(out, k, step, swarm)
    _record_estimation(out, k, step, measured, odometry, live, swarm, state.uwb)

    command = step.velocity_m_s
    if scenario.safety.min_separation_m is not None:
        command = _guarded(command, step, measured.ranges, state.in_force, live, scenario)
    command = saturate(command, plan.speed_limit)
    command = np.where(live[..., None] & ~holding[:, None, None], command, 0.0)
    state.in_force = np.where(live[..., None], command, np.nan)
    out["target_status"][:, k] = target_estimate.status
    out["commands_m_s"][:, k] = command
    out["positions_m"][:, k] = state.position
    out["live"][:, k] = live
    state.position = state.position + scenario.timing.step_s * command
    state.odometry_error = odometry_error_step(scenario.sensors, state.noise, state.odometry_error)


def _record_estimates(
    out: dict[str, NDArray[Any]], k: int, step: StepOutputs, swarm: SwarmEnclosing
) -> None:
    """Run 0's estimates at step ``k`` into ``out`` ``(K, N, N+1, 2)``, if it keeps them."""
    if "estimates_m" not in out:
        return
    north, east = step.estimate_north_m[0], step.estimate_east_m[0]
    if swarm.edge_index is not None:
        north, east = (swarm.edge_index.scatter(plane, np.nan) for plane in (north, east))
    out["estimates_m"][k, ..., 0] = north
    out["estimates_m"][k, ..., 1] = east


def _measure(  # noqa: PLR0917 - the step's pieces, each named
    scenario: Scenario,
    plan: _Plan,
    state: _State,
    out: dict[str, NDArray[Any]],
    k: int,
    live: NDArray[np.bool_],
) -> _Measured:
    """The true relative positions and the ranges on ``(B, N, N+1)`` planes; records the
    closest pair."""
    runs, sensors, noise = state.position.shape[0], scenario.sensors, state.noise
    position = state.position
    ranged = np.concatenate([np.broadcast_to(plan.target[k], (runs, 1, 2)), position], axis=1)
    truth_north = position[:, :, None, 0] - ranged[:, None, :, 0]
    truth_east = position[:, :, None, 1] - ranged[:, None, :, 1]
    true_ranges = _distance(truth_north, truth_east)
    out["separation_m"][:, k] = closest_pair(true_ranges[..., 1:], live)
    radio = live & ~plan.radio_down(k)
    linked = radio[:, :, None] & radio[:, None, :]
    graph = plan.graph.at(k)
    if graph is not None:  # only the graph's edges are ranged
        linked = linked & graph[0]
    seen = target_seen(
        true_ranges[..., 0], sensors, noise, looking=live & plan.senses & ~plan.tracker_down(k)
    )
    # The target's range comes from the tracker, the others' from the UWB radios.
    target_range = range_readings(true_ranges[..., :1], sensors, noise, measured=seen[..., None])
    radio_ranges = state.uwb.read(true_ranges[..., 1:], noise, k=k, measured=linked)
    ranges = np.concatenate([target_range, radio_ranges], axis=-1)
    return _Measured(
        truth_north=truth_north,
        truth_east=truth_east,
        ranges=ranges,
        radio_ranges=radio_ranges,
        target_range=ranges[..., 0],
        neighbours=None if graph is None else graph[1],
    )


def _measure_edges(  # noqa: PLR0917 - the step's pieces, each named
    scenario: Scenario,
    plan: _Plan,
    state: _State,
    out: dict[str, NDArray[Any]],
    k: int,
    live: NDArray[np.bool_],
) -> _Measured:
    """:func:`_measure` on the edges of a swarm kept per edge ``(B, E)``: the same readings
    (and draws) on the edges, O(E) for a model that draws nothing."""
    index, sensors, noise = state.swarm.edge_index, scenario.sensors, state.noise
    if index is None:
        raise SimulationError("_measure_edges needs a swarm kept per edge")
    runs, position = state.position.shape[0], state.position
    ranged = np.concatenate([np.broadcast_to(plan.target[k], (runs, 1, 2)), position], axis=1)
    truth_north = index.difference(position[..., 0], ranged[..., 0])
    truth_east = index.difference(position[..., 1], ranged[..., 1])
    true_ranges = np.sqrt(truth_north * truth_north + truth_east * truth_east)
    out["separation_m"][:, k] = closest_live_pair(position, live)
    adjacency, neighbours, _ = plan.graph.at(k)  # type: ignore[misc]  # a graph: not None
    radio = live & ~plan.radio_down(k)
    to_target, pairs = _edge_kinds(index)
    rows, cols, _ = pairs
    linked = radio[:, rows] & radio[:, cols] & adjacency[rows, cols]
    looking = live & plan.senses & ~plan.tracker_down(k)
    seen = target_seen(true_ranges[:, to_target], sensors, noise, looking=looking)
    target_range = range_readings(
        true_ranges[:, to_target, None], sensors, noise, measured=seen[..., None]
    )[..., 0]
    vehicle = index.slot > 0
    radio_ranges = state.uwb.read_edges(true_ranges[:, vehicle], noise, k, pairs, linked)
    ranges = np.empty(true_ranges.shape)
    ranges[:, to_target], ranges[:, vehicle] = target_range, radio_ranges
    return _Measured(
        truth_north=truth_north,
        truth_east=truth_east,
        ranges=ranges,
        radio_ranges=radio_ranges,
        target_range=target_range,
        neighbours=index.gather(neighbours),
    )


def _distance(
    north_m: NDArray[np.float64], east_m: NDArray[np.float64], *, in_place: bool = False
) -> NDArray[np.float64]:
    """``sqrt(north^2 + east^2)`` elementwise with two arrays made instead of four, or with
    ``in_place`` none (the arrays given, temporaries of the caller's, are overwritten): on a
    256-vehicle swarm's planes each one is a fresh 0.5 MB, which costs about as much as the
    operation that fills it."""
    square = np.multiply(north_m, north_m, out=north_m if in_place else None)
    square += np.multiply(east_m, east_m, out=east_m if in_place else None)
    return np.sqrt(square, out=square)


def _edge_kinds(
    index: EdgeIndex,
) -> tuple[NDArray[np.intp], tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]]:
    """The edges to the target, one per vehicle in vehicle order ``(N,)``, and the edges
    between vehicles as ``(rows, cols, reverse)`` ``(E_v,)``: reader, read vehicle, and the
    index among them of the edge back (-1 if none)."""
    to_target = np.flatnonzero(index.slot == 0)
    if not np.array_equal(index.row[to_target], np.arange(index.n_rows)):
        raise SimulationError("a swarm kept per edge needs every vehicle's edge to the target")
    vehicle = np.flatnonzero(index.slot > 0)
    among = np.full(index.size, -1)
    among[vehicle] = np.arange(vehicle.size)
    back = index.reverse[vehicle]
    reverse = np.where(back >= 0, among[back], -1)
    return to_target, (index.row[vehicle], index.slot[vehicle] - 1, reverse)


def _inputs(  # noqa: PLR0917 - the step's pieces, each named
    scenario: Scenario,
    plan: _Plan,
    state: _State,
    target_range: NDArray[np.float64],
    k: int,
    live: NDArray[np.bool_],
) -> tuple[NDArray[np.float64], TargetEstimate, NDArray[np.bool_]]:
    """The algorithm's odometry ``(B, N+1, 2)`` (slot 0 the target's), the target as tracked
    from the vehicles' ranges to it ``(B, N)`` (the track moves on) and which runs hold for a
    lost target ``(B,)``."""
    step_s, target = scenario.timing.step_s, plan.target
    odometry = state.position - state.origin + state.drift * plan.times[k] + state.odometry_error
    observed = np.asarray(np.isfinite(target_range).any(axis=-1))
    state.track, target_estimate = track_target(
        state.track,
        k,
        velocity_m_s=np.where(observed[:, None], (target[k + 1] - target[k]) / step_s, np.nan),
        observed_step=np.where(observed, float(k), np.nan),
        own_odometry_m=np.where(observed[:, None], target[k] - target[0], np.nan),
        step_s=step_s,
        lost_after_s=scenario.algorithm.target_lost_after_s,
    )
    lost = target_estimate.status == LOST
    holding = lost & (scenario.algorithm.target_on_lost == "hold")
    # A formation holding for a lost target does not estimate (it does not move: the
    # regressors would be zero), as a flying controller that holds does not.
    odometry = np.where(live[..., None] & ~holding[:, None, None], odometry, np.nan)
    odometry = np.concatenate([target_estimate.odometry_m[:, None, :], odometry], axis=1)
    return odometry, target_estimate, holding


def _record_estimation(  # noqa: PLR0917 - the step's pieces, each named
    out: dict[str, NDArray[Any]],
    k: int,
    step: StepOutputs,
    measured: _Measured,
    odometry: NDArray[np.float64],
    live: NDArray[np.bool_],
    swarm: SwarmEnclosing,
    uwb: UwbRanging,
) -> None:
    """Step ``k``'s localization errors against the truth, gated and NLOS ranges and the
    consensus speed, into ``out``."""
    error = _distance(
        step.estimate_north_m - measured.truth_north,
        step.estimate_east_m - measured.truth_east,
        in_place=True,
    )
    # NaN: an edge not estimated (never ranged, or an end lost), which does not count. But an
    # anchored edge between two live ends without a finite estimate has diverged (absurd
    # noise or gains), which must read as infinitely wrong, not as 0.
    index, anchored = swarm.edge_index, swarm.state.edges.anchored
    if index is None:
        diverged = anchored & live[..., None] & np.isfinite(odometry[:, None, :, 0])
        nlos, radio_gated = uwb.nlos, step.gated[..., 1:]
    else:  # per edge: (B, E), one plane for the sums over (-1, -2)
        diverged = anchored & live[:, index.row] & np.isfinite(odometry[:, index.slot, 0])
        vehicle = index.slot > 0
        nlos = uwb.nlos[..., index.row[vehicle], index.slot[vehicle] - 1][:, None, :]
        radio_gated = step.gated[:, None, vehicle]
        error, diverged = error[:, None, :], diverged[:, None, :]
    np.copyto(error, np.inf, where=diverged & ~np.isfinite(error))
    # The largest error, NaN (not estimated) counted as 0: fmax passes over NaN, and every
    # error is >= 0.
    out["localization_error_m"][:, k] = np.fmax.reduce(error, axis=(-1, -2), initial=0.0)
    out["localization_rms_m"][:, k] = edge_rms(error)
    radio_ranges = measured.radio_ranges.reshape(nlos.shape)
    _count_ranges(out, k, step.gated, (nlos, radio_gated), radio_ranges)
    speed = np.sqrt(np.sum(step.consensus_m_s**2, axis=-1))
    out["consensus_speed_m_s"][:, k] = np.where(live, speed, 0.0).max(axis=-1)


def _count_ranges(
    out: dict[str, NDArray[Any]],
    k: int,
    gated: NDArray[np.bool_],
    radio: tuple[NDArray[np.bool_], NDArray[np.bool_]],
    radio_ranges: NDArray[np.float64],
) -> None:
    """Step ``k``'s gated ranges, NLOS ranges read and the gate's false rejections (good ranges
    gated) into ``out``: ``gated`` ``(B, ...)``, and ``radio`` the NLOS and gated marks of the
    ranges between vehicles, ``radio_ranges`` ``(B, R, S)`` (or ``(B, 1, E_v)``). A count whose
    marks are all False is 0 without a pass over the plane (the RLSE gates nothing, and most
    models have no NLOS)."""
    nlos, radio_gated = radio
    runs = gated.shape[0]
    out["gated_ranges"][:, k] = gated.reshape(runs, -1).sum(axis=-1) if gated.any() else 0
    out["nlos_ranges"][:, k] = out["false_rejections"][:, k] = 0
    some_nlos, some_gated = bool(nlos.any()), bool(radio_gated.any())
    if not (some_nlos or some_gated):
        return
    read = np.isfinite(radio_ranges)
    if some_nlos:
        out["nlos_ranges"][:, k] = (nlos & read).sum(axis=(-1, -2))
    if some_gated:
        out["false_rejections"][:, k] = (radio_gated & ~nlos & read).sum(axis=(-1, -2))


def _guarded(  # noqa: PLR0917 - the step's pieces, each named
    command: NDArray[np.float64],
    step: StepOutputs,
    ranges: NDArray[np.float64],
    in_force: NDArray[np.float64],
    live: NDArray[np.bool_],
    scenario: Scenario,
) -> NDArray[np.float64]:
    """The law's commands ``(B, N, 2)`` through the separation guard: each vehicle's estimates of
    the live others (RLSE, p_i - p_j) for directions, trusted within how far their bearing may
    be off, its measured ranges for distances, and the
    commands in force ``(B, N, 2)`` (set at the last step, as the step messages carry them; NaN
    at k = 0 and for vehicles not live)."""
    others = live[:, None, :] & ~np.eye(live.shape[-1], dtype=bool)
    relative = np.stack([step.estimate_north_m[..., 1:], step.estimate_east_m[..., 1:]], axis=-1)
    relative = np.where(others[..., None], relative, np.nan)
    safety = scenario.safety
    return separation_guard(
        command,
        relative,
        np.where(others, ranges[..., 1:], np.nan),
        in_force,
        np.broadcast_to(in_force[:, None, :, :], relative.shape),
        min_separation_m=safety.min_separation_m or 0.0,
        gain_1_s=safety.separation_gain_1_s,
        step_s=scenario.timing.step_s,
        margin_m=safety.separation_margin_m,
        braking_m_s2=safety.separation_braking_m_s2,
        latency_s=safety.separation_latency_s,
        range_noise_std_m=scenario.sensors.range_noise_std_m,
        bearing_std_rad=step.bearing_std_rad[..., 1:],
    )
