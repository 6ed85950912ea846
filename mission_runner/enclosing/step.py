"""One step of the enclosing algorithm for any number of computing vehicles.

This is the single implementation of the paper's law. A flying vehicle calls it with one row
(itself, see :mod:`.vehicle`); the simulator calls it with every vehicle as a row and, for batches,
extra leading axes (see :mod:`.swarm`). Nothing here knows about time, I/O or ground truth: the
inputs are what a vehicle measures and hears at step k.

Slots index everything a vehicle can relate to: slot 0 is the target, slots 1..N the vehicles.
Order of one step k (every k-indexed input refers to the same instant kT):

1. Estimator update of every edge from the ranges and odometries at k: the paper's RLSE (eqs.
   cosinelaw, estimator) or, by ``EnclosingParams.estimator``, the per-edge filter of :mod:`.ekf`;
   then phat_ij(k) carried to now by odometry.
2. Oscillator: theta_i(k+1) from the phases at k of the neighbours heard this step (eq. osc).
3. Desired offsets r(k), r_i(k+1) through the affine shape at k and k+1 (eq. desipos).
4. Command u_i(k) = sat(ubar_i) + delta_r_i / T + u_0 (eq. formationtrackingcontrol).

A neighbour that is not heard at step k (no phase, no odometry) simply drops out of this step's
sums, whose weights are re-normalised over the neighbours that are there.

Neighbours are every other vehicle (and the target) unless ``StepInputs.neighbours`` restricts
each row to its graph's (:mod:`.graph`); the three stages that relate slots use the same mask.
With an :class:`.edges.EdgeIndex` (sparse graphs) everything that relates a row to a slot is kept
per directed edge ``(..., E)`` instead of on ``(..., R, S)`` planes: the same sums over the same
neighbours, in O(E) work and memory.
"""

from dataclasses import dataclass
from typing import Literal, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .control import consensus_velocity, row_normalised, saturate
from .edges import EdgeIndex
from .ekf import FilterEdges, FilterSettings, filter_update
from .errors import EnclosingError
from .oscillator import advance_phase, coupling_rate, harmonic_gains, pair_coupling
from .rlse import EdgeEstimates, rlse_update
from .shape import desired_offsets

TARGET_SLOT = 0
#: With a bound kept for the separation guard (``EnclosingParams.bound_range_noise_std_m``), the
#: RLSE uses a range only over a relative displacement of at least this many range-noise stds
#: (:func:`.rlse.rlse_update`): a pair the guard has slowed otherwise feeds it updates that turn
#: a good bearing into garbage. 5 cm noise, 200 random starts of separation_guard.yaml with the
#: guard: the 90th percentile of the tracking error over the last quarter fell from 41 m (pairs
#: frozen for good) to 2.1 m.
MIN_DISPLACEMENT_SIGMAS = 3.0


@dataclass(frozen=True)
class EnclosingParams:
    """The paper's parameters (ALGORITHM.md's table), shared by every vehicle.

    step_s: T [s]. beta: consensus gain, 0 < beta < 1/T. saturation_m_s: Ubar [m/s].
    forgetting_factor: beta_f in (0, 1]. coupling_gain: K_l for l < n. coupling_gain_last: K_n.
    radius_m: rho. initial_gain: Gamma(0) = initial_gain * I. estimator: ``rlse`` (the paper's)
    or ``ekf`` (:mod:`.ekf`, which needs ``filter``, its noise model and gate). shared_ranges:
    each edge (i, j) is updated with the mean of d_ij and the d_ji that j measured and shared
    (:func:`pair_ranges`), so that i's and j's estimates of the pair see the same data.
    bound_range_noise_std_m: sigma_r for which the RLSE keeps a bound of each estimate's error
    (:attr:`StepOutputs.bearing_std_rad`, for the separation guard) and skips ranges over
    displacements shorter than ``MIN_DISPLACEMENT_SIGMAS`` sigma_r; None: neither (the paper).
    """

    step_s: float
    beta: float
    saturation_m_s: float
    forgetting_factor: float
    coupling_gain: float
    coupling_gain_last: float
    radius_m: float
    initial_gain: float
    estimator: Literal["rlse", "ekf"]
    filter: FilterSettings | None
    shared_ranges: bool
    bound_range_noise_std_m: float | None

    def __post_init__(self) -> None:
        rules = [
            (self.step_s > 0, "step_s must be > 0"),
            (0 < self.beta < 1 / self.step_s, "beta must be in (0, 1/step_s)"),
            (self.saturation_m_s > 0, "saturation_m_s must be > 0"),
            (0 < self.forgetting_factor <= 1, "forgetting_factor must be in (0, 1]"),
            (self.radius_m > 0, "radius_m must be > 0"),
            (self.initial_gain > 0, "initial_gain must be > 0"),
            (self.estimator in ("rlse", "ekf"), "estimator must be rlse or ekf"),
            (self.estimator != "ekf" or self.filter is not None, "estimator ekf needs filter"),
            (
                self.bound_range_noise_std_m is None or self.bound_range_noise_std_m >= 0,
                "bound_range_noise_std_m must be >= 0",
            ),
        ]
        broken = [message for ok, message in rules if not ok]
        if broken:
            raise EnclosingError("; ".join(broken))


@dataclass(frozen=True)
class EnclosingState:
    """What the computing vehicles carry from step k to k+1.

    step: k. phase_rad: ``(..., R)`` theta_i(k). edges: estimator state ``(..., R, S)``, or
    ``(..., E)`` per edge of an :class:`.edges.EdgeIndex`.
    """

    step: int
    phase_rad: NDArray[np.float64]
    edges: EdgeEstimates | FilterEdges

    @classmethod
    def initial(
        cls, params: EnclosingParams, phase_rad: ArrayLike, n_slots: int, n_edges: int | None = None
    ) -> Self:
        """State at k = 0 for rows with phases ``(..., R)`` and ``n_slots`` slots; with
        ``n_edges``, estimators per edge of an :class:`.edges.EdgeIndex` ``(..., E)``."""
        phase_rad = np.asarray(phase_rad, dtype=float)
        shape = (*phase_rad.shape, n_slots) if n_edges is None else (*phase_rad.shape[:-1], n_edges)
        edges: EdgeEstimates | FilterEdges
        if params.estimator == "ekf":
            edges = FilterEdges.initial(shape, params.initial_gain)
        else:
            edges = EdgeEstimates.initial(shape, params.initial_gain)
        return cls(step=0, phase_rad=phase_rad, edges=edges)


@dataclass(frozen=True)
class StepInputs:
    """What the computing vehicles measure and hear at step k.

    odometry_m: ``(..., S, 2)`` every slot's cumulative displacement, north-east [m], in each
        slot's own frame (shared orientation, any origin); NaN where not heard. Slot 0: the target.
    phase_rad: ``(..., S)`` every vehicle's theta(k); NaN where not heard. Rows' own entries are
        taken from the state.
    range_m: ``(..., R, S)`` d_ij(k) [m]; NaN where not measured (and for the target, for
        vehicles that do not sense it).
    member: ``(..., S)`` bool, vehicles counted as live (n of the harmonic gains).
    target_velocity_m_s: ``(..., 2)`` u_0(k) [m/s]; NaN where unknown (no feed-forward).
    shape_now, shape_next: ``(..., 3, 3)`` affine shape at k and k+1.
    omega_rad_s: ``(..., R)`` each row's natural frequency.
    reverse_range_m: ``(..., R, S)`` d_ji(k) [m]: the range vehicle j measured to row i and shared
        in its step message; NaN where not heard (and for the target). None: nothing shared. Used
        only with ``EnclosingParams.shared_ranges``.
    neighbours: ``(..., R, S)`` bool, the slots each row may couple with, range to and take into
        its consensus (its graph neighbours and the target, :mod:`.graph`). None: every slot
        (the complete graph, the paper's Assumption 1).

    With an :class:`.edges.EdgeIndex`, ``range_m``, ``reverse_range_m`` and ``neighbours`` are
    ``(..., E)``, one entry per edge (``neighbours``: the edges in the graph at k).
    """

    odometry_m: NDArray[np.float64]
    phase_rad: NDArray[np.float64]
    range_m: NDArray[np.float64]
    member: NDArray[np.bool_]
    target_velocity_m_s: NDArray[np.float64]
    shape_now: NDArray[np.float64]
    shape_next: NDArray[np.float64]
    omega_rad_s: NDArray[np.float64]
    reverse_range_m: NDArray[np.float64] | None = None
    neighbours: NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class StepOutputs:
    """What the law computes at step k.

    velocity_m_s: ``(..., R, 2)`` u_i(k), north-east [m/s].
    consensus_m_s: ``(..., R, 2)`` the saturated term sat(ubar_i), |.| <= Ubar.
    estimate_north_m, estimate_east_m: ``(..., R, S)`` phat_ij(k), NaN where the edge is not
        estimated (see :attr:`estimate_m` for the ``(..., R, S, 2)`` form).
    consensus_weights: ``(..., R, S)`` abar_ij used this step.
    gated: ``(..., R, S)`` bool, ranges the estimator rejected as outliers this step.
    bearing_std_rad: ``(..., R, S)`` how far phat_ij's bearing may be off [rad], one std of a
        bound of its error (RLSE: :attr:`.rlse.EdgeEstimates.bearing_std_rad`, kept with
        ``EnclosingParams.bound_range_noise_std_m``; the filter: its covariance, once it has
        taken over); NaN where not known.

    With an :class:`.edges.EdgeIndex` every ``(..., R, S)`` plane is ``(..., E)``, per edge.
    """

    velocity_m_s: NDArray[np.float64]
    consensus_m_s: NDArray[np.float64]
    estimate_north_m: NDArray[np.float64]
    estimate_east_m: NDArray[np.float64]
    consensus_weights: NDArray[np.float64]
    gated: NDArray[np.bool_]
    bearing_std_rad: NDArray[np.float64]

    @property
    def estimate_m(self) -> NDArray[np.float64]:
        """phat_ij(k) as ``(..., R, S, 2)``."""
        return np.stack([self.estimate_north_m, self.estimate_east_m], axis=-1)


def enclosing_step(
    params: EnclosingParams,
    row_slots: ArrayLike,
    state: EnclosingState,
    inputs: StepInputs,
    *,
    edge_index: EdgeIndex | None = None,
) -> tuple[EnclosingState, StepOutputs]:
    """Advance the rows ``row_slots`` ``(R,)`` from step k to k+1. Returns ``(state, outputs)``.

    The four stages of the module docstring, in order; each is a function of its own below.
    edge_index: the directed edges the state, the inputs and the outputs are kept on (a sparse
    graph's, :mod:`.edges`); None: ``(..., R, S)`` planes.
    """
    row_slots = np.asarray(row_slots)
    not_self = _neighbour_mask(row_slots, state, inputs, edge_index)
    edges, gated, estimate_north, estimate_east = _localize(
        params, row_slots, not_self, state, inputs, edge_index
    )
    phase, phase_next = _advance_oscillators(
        params, row_slots, state, inputs, (edge_index, not_self)
    )
    error_north, error_east, feed_forward = _formation_errors(
        params,
        inputs,
        (phase, state.phase_rad, phase_next),
        estimate_north=estimate_north,
        estimate_east=estimate_east,
        edge_index=edge_index,
    )
    velocity, consensus, weights = _command(
        params,
        not_self,
        (error_north, error_east),
        feed_forward=feed_forward,
        target_velocity_m_s=inputs.target_velocity_m_s,
        edge_index=edge_index,
    )

    next_state = EnclosingState(step=state.step + 1, phase_rad=phase_next, edges=edges)
    outputs = StepOutputs(
        velocity_m_s=velocity,
        consensus_m_s=consensus,
        estimate_north_m=estimate_north,
        estimate_east_m=estimate_east,
        consensus_weights=weights,
        gated=gated,
        bearing_std_rad=_bearing_std_rad(edges, estimate_north),
    )
    return next_state, outputs


def _neighbour_mask(
    row_slots: NDArray[np.intp],
    state: EnclosingState,
    inputs: StepInputs,
    edge_index: EdgeIndex | None,
) -> NDArray[np.bool_]:
    """Which (row, slot) pairs are the rows' graph neighbours at k, self excluded: ``(R, S)``
    (or ``(..., R, S)``), or ``(..., E)`` per edge. Checks that the state fits the inputs."""
    n_slots = inputs.phase_rad.shape[-1]
    width = n_slots if edge_index is None else edge_index.size
    if state.edges.anchored.shape[-1] != width:
        unit = "slots" if edge_index is None else "edges"
        raise EnclosingError(
            f"state has {state.edges.anchored.shape[-1]} {unit}, inputs have {width}"
        )
    if edge_index is not None:  # edges are never self edges
        if inputs.neighbours is None:
            return np.ones(edge_index.size, dtype=bool)
        return inputs.neighbours
    not_self: NDArray[np.bool_] = np.arange(n_slots) != row_slots[:, None]  # (R, S)
    if inputs.neighbours is not None:
        not_self = not_self & inputs.neighbours
    return not_self


def _localize(  # noqa: PLR0917 - the stage's inputs, each named
    params: EnclosingParams,
    row_slots: NDArray[np.intp],
    not_self: NDArray[np.bool_],
    state: EnclosingState,
    inputs: StepInputs,
    edge_index: EdgeIndex | None,
) -> tuple[
    EdgeEstimates | FilterEdges, NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]
]:
    """Stage 1, relative localization: every edge's estimator updated from the ranges and
    odometries at k, then phat_ij(k) carried to now. Returns the updated edges, the ranges the
    estimator gated, and phat_ij(k) north and east, all on ``(..., R, S)`` planes (or per edge).

    Self edges carry no range, so they never anchor and never estimate.
    """
    relative_north, relative_east = (
        _relative(inputs.odometry_m[..., axis], row_slots, edge_index) for axis in (0, 1)
    )
    range_m = np.where(not_self, inputs.range_m, np.nan)
    readings: NDArray[np.float64] | None = None  # one range per edge
    if params.shared_ranges and inputs.reverse_range_m is not None:
        range_m, readings = pair_ranges(range_m, np.where(not_self, inputs.reverse_range_m, np.nan))
    edges, gated = _update_edges(
        params, state, range_m, relative_north, relative_east, readings=readings
    )
    estimate_north, estimate_east = edges.current(relative_north, relative_east)
    return edges, gated, estimate_north, estimate_east


def _relative(
    slot_values: NDArray[np.float64], row_slots: NDArray[np.intp], edge_index: EdgeIndex | None
) -> NDArray[np.float64]:
    """Row minus slot of values by slot ``(..., S)``: ``(..., R, S)`` or, per edge, ``(..., E)``."""
    if edge_index is None:
        return slot_values[..., row_slots, None] - slot_values[..., None, :]
    return edge_index.difference(slot_values[..., row_slots], slot_values)


def _update_edges(
    params: EnclosingParams,
    state: EnclosingState,
    range_m: NDArray[np.float64],
    relative_north: NDArray[np.float64],
    relative_east: NDArray[np.float64],
    *,
    readings: NDArray[np.float64] | None,
) -> tuple[EdgeEstimates | FilterEdges, NDArray[np.bool_]]:
    """One update by the estimator the state carries (the filter or the paper's RLSE). Returns
    the edges and the ranges gated as outliers ``(..., R, S)`` (none, for the RLSE)."""
    if isinstance(state.edges, FilterEdges):
        if params.filter is None:
            raise EnclosingError("the state carries filter edges but params have no filter")
        return filter_update(
            state.edges,
            range_m,
            relative_north,
            relative_east,
            step=state.step,
            settings=params.filter,
            initial_gain=params.initial_gain,
            readings=readings,
        )
    edges = rlse_update(
        state.edges,
        range_m,
        relative_north,
        relative_east,
        params.forgetting_factor,
        range_noise_std_m=params.bound_range_noise_std_m,
        min_displacement_m=MIN_DISPLACEMENT_SIGMAS * (params.bound_range_noise_std_m or 0.0),
    )
    return edges, np.zeros(range_m.shape, dtype=bool)


def _advance_oscillators(
    params: EnclosingParams,
    row_slots: NDArray[np.intp],
    state: EnclosingState,
    inputs: StepInputs,
    edges: tuple[EdgeIndex | None, NDArray[np.bool_]],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Stage 2, the oscillator over the vehicles heard this step. Returns every slot's phase at k
    as this row sees it ``(..., S)`` (the row's own from the state, the target's NaN) and the
    rows' theta_i(k+1) ``(..., R)``. ``edges``: the edge index (None: planes) and, with one,
    the edges in the graph at k ``(..., E)``."""
    n_slots = inputs.phase_rad.shape[-1]
    phase = inputs.phase_rad.copy()
    phase[..., row_slots] = state.phase_rad
    phase[..., TARGET_SLOT] = np.nan
    heard = np.isfinite(phase) & inputs.member
    n_live = inputs.member[..., 1:].sum(axis=-1)
    gains = harmonic_gains(n_live, n_slots - 1, params.coupling_gain, params.coupling_gain_last)
    edge_index, in_graph = edges
    if edge_index is None:
        coupling = coupling_rate(phase, row_slots, heard, gains, neighbours=inputs.neighbours)
    else:
        pairs = in_graph & heard[..., edge_index.slot]
        coupling = _edge_coupling(phase, row_slots, pairs, gains, edge_index)
    phase_next = advance_phase(state.phase_rad, inputs.omega_rad_s, coupling, params.step_s)
    return phase, phase_next


def _edge_coupling(
    phase: NDArray[np.float64],
    row_slots: NDArray[np.intp],
    pairs: NDArray[np.bool_],
    gains: NDArray[np.float64],
    edge_index: EdgeIndex,
) -> NDArray[np.float64]:
    """:func:`.oscillator.coupling_rate` per edge: the mean over each row's ``pairs``
    ``(..., E)`` (edges to heard neighbours) of :func:`.oscillator.pair_coupling`, ``(..., R)``."""
    finite = np.where(np.isfinite(phase), phase, 0.0)
    difference = edge_index.difference(finite[..., row_slots], finite)
    n_harmonics = gains.shape[-1]
    gain_rows = np.broadcast_to(gains, (*difference.shape[:-1], n_harmonics))
    gain_rows = gain_rows.reshape(-1, n_harmonics)
    which = np.repeat(np.arange(gain_rows.shape[0]), edge_index.size)
    per_pair = pair_coupling(difference.reshape(-1), gain_rows, which).reshape(difference.shape)
    total = edge_index.row_sums(np.where(pairs, per_pair, 0.0))
    return total / np.maximum(edge_index.row_sums(pairs), 1)


def _formation_errors(
    params: EnclosingParams,
    inputs: StepInputs,
    phases: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    *,
    estimate_north: NDArray[np.float64],
    estimate_east: NDArray[np.float64],
    edge_index: EdgeIndex | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Stage 3, desired offsets r(k), r_i(k+1) through the affine shape, from ``phases``: every
    slot's ``(..., S)``, the rows' ``(..., R)`` and the rows' at k+1. Returns the formation
    error phat_ij - (r_i - r_j) north and east ``(..., R, S)`` (or per edge) and the
    feed-forward delta_r_i / T ``(..., R, 2)``. The target's offset is 0 whatever the shape."""
    phase, row_phase, phase_next = phases
    offsets = desired_offsets(phase, params.radius_m, inputs.shape_now)
    offsets[..., TARGET_SLOT, :] = 0.0
    row_offsets = desired_offsets(row_phase, params.radius_m, inputs.shape_now)
    row_offsets_next = desired_offsets(phase_next, params.radius_m, inputs.shape_next)
    if edge_index is None:  # r_i - r_j, then phat_ij minus it in place (large swarms' planes)
        error_north = row_offsets[..., :, None, 0] - offsets[..., None, :, 0]
        error_east = row_offsets[..., :, None, 1] - offsets[..., None, :, 1]
        np.subtract(estimate_north, error_north, out=error_north)
        np.subtract(estimate_east, error_east, out=error_east)
    else:
        error_north = estimate_north - edge_index.difference(row_offsets[..., 0], offsets[..., 0])
        error_east = estimate_east - edge_index.difference(row_offsets[..., 1], offsets[..., 1])
    feed_forward = (row_offsets_next - row_offsets) / params.step_s
    return error_north, error_east, feed_forward


def _command(
    params: EnclosingParams,
    not_self: NDArray[np.bool_],
    errors: tuple[NDArray[np.float64], NDArray[np.float64]],
    *,
    feed_forward: NDArray[np.float64],
    target_velocity_m_s: NDArray[np.float64],
    edge_index: EdgeIndex | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Stage 4, u_i(k) = sat(ubar_i) + delta_r_i / T + u_0: saturated consensus plus
    feed-forward, from the formation errors north and east. Returns u_i ``(..., R, 2)``, the
    saturated term ``(..., R, 2)`` and the weights abar_ij ``(..., R, S)`` (or per edge) over
    the neighbours with an error this step."""
    error_north, error_east = errors
    used = not_self & np.isfinite(error_north + error_east)
    if edge_index is None:
        weights = row_normalised(used)
        unsaturated = consensus_velocity(error_north, error_east, weights, params.beta)
    else:
        weights, unsaturated = _edge_consensus(used, errors, params.beta, edge_index)
    consensus = saturate(unsaturated, params.saturation_m_s)
    target_velocity = np.where(np.isnan(target_velocity_m_s), 0.0, target_velocity_m_s)
    velocity = consensus + feed_forward + target_velocity[..., None, :]
    return velocity, consensus, weights


def _edge_consensus(
    used: NDArray[np.bool_],
    errors: tuple[NDArray[np.float64], NDArray[np.float64]],
    beta: float,
    edge_index: EdgeIndex,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`.control.row_normalised` and :func:`.control.consensus_velocity` per edge: the
    weights abar_ij ``(..., E)`` over the ``used`` edges and ubar_i ``(..., R, 2)``."""
    share = 1.0 / np.maximum(edge_index.row_sums(used), 1)
    weights = np.where(used, share[..., edge_index.row], 0.0)
    sums = [edge_index.row_sums(np.where(used, weights * error, 0.0)) for error in errors]
    return weights, -beta * np.stack(sums, axis=-1)


def pair_ranges(
    range_m: NDArray[np.float64], reverse_range_m: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The range of each pair from both ends: ``(d_ij + d_ji) / 2`` where both were measured, the
    one that was where only one was. Returns the ranges and how many readings each averages
    (0, 1 or 2), all ``(..., R, S)``.

    i->j and j->i are ranged with independent noise. Each vehicle's estimate carries its own
    range error, and the formation centre sums the estimates of both directions of every pair:
    their odometry errors cancel (both follow o_i - o_j) but the range errors would add. Fed the
    same range, i's and j's estimates of a pair are exactly opposite (the update is odd in the
    relative odometry), so the range error cancels in the centre as well, and each estimate sees
    half the range variance. The sum is commutative in floating point, so i and j compute the
    same number bit for bit.
    """
    own, reverse = np.isfinite(range_m), np.isfinite(reverse_range_m)
    both = own & reverse
    paired = np.where(
        both, 0.5 * (range_m + reverse_range_m), np.where(own, range_m, reverse_range_m)
    )
    return paired, own.astype(float) + reverse


def _bearing_std_rad(
    edges: EdgeEstimates | FilterEdges, estimate_north_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """How far each edge's estimate in force may be off in bearing [rad] ``(..., R, S)``; NaN
    where the edge has no estimate (``estimate_north_m`` NaN) or no bound is kept."""
    if isinstance(edges, EdgeEstimates) and edges.error_nn is None:
        return np.full(estimate_north_m.shape, np.nan)
    estimated = np.isfinite(estimate_north_m)
    if isinstance(edges, EdgeEstimates):
        return np.where(estimated, edges.bearing_std_rad, np.nan)
    covariance = edges.filter  # the filter keeps its covariance in the gain fields
    nn, ne, ee = covariance.gain_nn, covariance.gain_ne, covariance.gain_ee
    largest = 0.5 * (nn + ee) + np.sqrt(0.25 * (nn - ee) ** 2 + ne * ne)
    filtered = np.sqrt(np.maximum(largest, 0.0)) / covariance.anchor_range_m
    bearing = np.where(edges.engaged, filtered, edges.regression.bearing_std_rad)
    return np.where(estimated, bearing, np.nan)
